"""``dtpf sensor``: a stand-in for the physical system, publishing observations over Zenoh.

It simulates the run's model (a built-in scenario or ``--model REF``, the
path the twin's ``dtpf run`` would simulate for the same seed and twin), or
reads ``--observations FILE``, and publishes one
:class:`~dtpf.messages.models.Observation` per step on
``dtpf/<twin>/sensor/observation`` at ``--rate`` per second, with the truth
in the message's ``truth`` field (``--no-truth`` leaves it out), then an
end-of-stream message. A twin launched with ``--observations live`` filters
each as it arrives::

    dtpf launch --observations live          # terminal 1: the twin waits for its sensor
    dtpf sensor --rate 20                    # terminal 2: 100 observations, then the end

Replaying a rosbag2 log (``--observations BAG --topic TOPIC``) stamps each
observation with its message's ``header.stamp`` (its record time without
one), as the twin would have heard it live; a file's rows are stamped when
they are sent.

A restarted sensor continues where the twin is: it reads the last sequence
number the entity accepted from the entity's status and goes on after it.

For a driven model (docs/guides/driven.md) it stands in for every sensor and
the control source at once: it reads ``--observations NAME=FILE`` per sensor
and ``--controls FILE`` and publishes, in stamp order, each sensor's
observations (numbered per sensor, named in ``sensor``, stamped with the
file's time) and each control on ``dtpf/<twin>/sensor/control``, each when
its stamp comes (``--speed`` times real time; 0: as fast as possible, which
only a twin whose ``--reorder-window`` spans the whole run puts in order)::

    dtpf launch --model docs/examples/unicycle.py:Unicycle --observations live
    dtpf sensor --model docs/examples/unicycle.py:Unicycle --observations gps=gps.csv \
        --observations beacons=beacons.csv --controls odometry.csv
"""
from __future__ import annotations

import argparse
import sys
import time

import zenoh

from dtpf.entity import sources
from dtpf.messages import keys
from dtpf.messages.codec import MessageError, decode_for_key
from dtpf.messages.config import RunConfig, add_run_arguments, config_from_args
from dtpf.messages.models import Control, Observation, Status, Time
from dtpf.scripts.console import run_command
from dtpf.shell.bus import BusError, Inbox, add_zenoh_arguments, zenoh_config_from_args
from dtpf.shell.service import ServiceShell

__all__ = ["main", "register", "resume_point", "sensor_command"]


def sensor_command(config: RunConfig, endpoint: str, secure=None) -> str:
    """The ``dtpf sensor`` command line, shell-quoted, that feeds the live twin of ``config`` through the
    router at ``endpoint``: the same model (scenario or ``--model``), seed, twin and run id, and with
    ``secure`` (the secure folder) the sensor's role."""
    import shlex

    from dtpf.messages.config import RunConfig as Defaults

    defaults = Defaults()
    words = ["dtpf", "sensor"]
    words += ["--model", config.model] if config.model is not None else ["--scenario", config.scenario]
    words += ["--twin", config.twin]
    if config.seed != defaults.seed:
        words += ["--seed", str(config.seed)]
    if config.run_id != defaults.run_id:
        words += ["--run-id", config.run_id]
    words += ["--connect", endpoint]
    if secure is not None:
        words += ["--secure", str(secure), "--role", "sensor"]
    text = shlex.join(words)
    try:
        from dtpf.entity import model_ref
        from dtpf.entity.calls import ModelCalls

        calls = ModelCalls(model_ref.resolve(config.model_ref))
    except Exception:  # the hint only; the twin itself has loaded its model
        return text
    if calls.driven:  # a driven model is not simulated: the sensor reads its files
        named = [name for name in calls.sensors if name is not None]
        text += "".join(f" --observations {name}=FILE" for name in named) or " --observations FILE"
        text += " --controls FILE" if calls.controls else ""
    return text


def resume_point(shell: ServiceShell, wait: float) -> int:
    """The last sequence number the twin's entity accepted, from its status (0 if none is heard)."""
    inbox = Inbox(shell.session, keys.key(shell.config.twin, "entity", "status"))
    deadline = time.monotonic() + wait
    try:
        while time.monotonic() < deadline and not shell.stopping:
            item = inbox.get(timeout=min(0.1, max(0.0, deadline - time.monotonic())))
            if item is None:
                continue
            try:
                status = decode_for_key(item.key, item.payload)
            except MessageError:
                continue
            if isinstance(status, Status) and status.run_id == shell.config.run_id and status.observations:
                return status.observations.last_sequence
        return 0
    finally:
        inbox.close()


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Publish the observations of ``config`` (simulated or from its file) until done or stopped."""
    model = sources.load_model(config, sensor=config.simulated)
    data = sources.observations_of(config, model)
    if data.drives is not None or data.sensors is not None:
        return driven(config, model, data, zenoh_config, args)
    key = keys.key(config.twin, "sensor", "observation")
    with ServiceShell("sensor", config, zenoh_config) as shell:
        shell.running()
        if args.wait_for_entity:
            missing = shell.presence.wait_for(["entity"], args.wait_for_entity)
            if missing:
                shell.log.warning("no entity of twin %s after %.1f s: publishing anyway", config.twin,
                                  args.wait_for_entity)
        start = args.start if args.start is not None else resume_point(shell, args.resume_wait) + 1
        if start > 1:
            shell.log.info("continuing after observation %d, the last the entity accepted", start - 1)
        period = 1.0 / args.rate if args.rate else 0.0
        next_tick = time.monotonic()
        sent = 0
        bag = bag_stamps(config, data)
        for sequence in range(start, data.steps + 1):
            if shell.stopping:
                shell.log.info("stopped after observation %d of %d", sequence - 1, data.steps)
                return 130
            truth = None if data.truth is None or args.no_truth else data.truth[sequence - 1].tolist()
            stamp = {} if bag is None else {"stamp": Time.from_ns(int(bag[sequence - 1]))}
            shell.publish(Observation(**shell.header(sequence), values=data.observations[sequence - 1].tolist(),
                                      truth=truth, **stamp))
            sent += 1
            if period:
                next_tick += period
                time.sleep(max(0.0, next_tick - time.monotonic()))
        if not args.no_end:
            shell.publish(Observation(**shell.header(data.steps + 1), values=[], end=True))
        shell.log.info("published %d observations on %s%s", sent, key, "" if args.no_end else ", then the end")
    return 0


def bag_stamps(config: RunConfig, data):
    """The stamps (ns) a replayed rosbag2 log gives its observations (each message's header stamp, else its
    record time), or None for another source: its observations are stamped when they are sent."""
    from dtpf.entity import rosbag

    path = config.observation_file
    if path is None or data.stamps is None or not (config.topic is not None or rosbag.is_bag(path)):
        return None
    return data.stamps


def driven(config: RunConfig, model, data, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Publish a driven run's observations of every sensor and its controls, in stamp order (module
    docstring)."""
    from dtpf.entity import stamped
    from dtpf.entity.calls import ModelCalls

    calls = ModelCalls(model)
    events = []  # (stamp, 0 control / 1 observation, index)
    controls = None
    if config.controls is not None:
        controls = stamped.read_controls(config.controls, calls.controls, fields=config.control_fields,
                                         partial=config.partial)
        events += [(int(stamp), 0, i) for i, stamp in enumerate(controls[0])]
    events += [(int(stamp), 1, i) for i, stamp in enumerate(data.stamps)]
    events.sort()
    with ServiceShell("sensor", config, zenoh_config) as shell:
        shell.running()
        if args.wait_for_entity and shell.presence.wait_for(["entity"], args.wait_for_entity):
            shell.log.warning("no entity of twin %s after %.1f s: publishing anyway", config.twin,
                              args.wait_for_entity)
        speed = args.speed
        start = time.monotonic()
        first = events[0][0] if events else 0
        sequence = {name: 0 for name in calls.sensors}
        sent = 0
        for stamp, kind, i in events:
            if shell.stopping:
                shell.log.info("stopped after %d observations of %d", sent, data.steps)
                return 130
            if speed:
                time.sleep(max(0.0, start + (stamp - first) / 1e9 / speed - time.monotonic()))
            if kind == 0:
                shell.publish(Control(**shell.header(i + 1), stamp=Time.from_ns(stamp),
                                      control=controls[1][i].tolist()))
                continue
            sensor = data.sensors[i] if data.sensors is not None else None
            sequence[sensor] += 1
            truth = None if data.truth is None or args.no_truth else data.truth[i].tolist()
            values = data.observations[i][:calls.sensors[sensor]].tolist()
            shell.publish(Observation(**shell.header(sequence[sensor]), stamp=Time.from_ns(stamp), values=values,
                                      truth=truth, sensor=sensor))
            sent += 1
        if not args.no_end:
            if controls is not None:  # each stream says it ended: the two keys can overtake each other
                shell.publish(Control(**shell.header(len(controls[0]) + 1), end=True))
            name = next(iter(sequence))
            shell.publish(Observation(**shell.header(sequence[name] + 1), values=[], end=True, sensor=name))
        shell.log.info("published %d observations of %d sensors%s", sent, len(sequence),
                       f" and {len(controls[0])} controls" if controls is not None else "")
    return 0


def cmd_sensor(args: argparse.Namespace) -> int:
    import logging

    logging.basicConfig(level=args.log_level, stream=sys.stderr, format="%(asctime)s sensor      %(levelname)s %(message)s")
    config = config_from_args(args)
    if config.live:
        raise ValueError("a sensor publishes observations: give it a scenario, --model or an --observations "
                         "file, not 'live'")
    try:
        return main(config, zenoh_config_from_args(args, role="sensor"), args)
    except BusError as error:
        print(f"dtpf sensor: error: {error}", file=sys.stderr)
        return 2


def register(subparsers) -> None:
    """Add the ``sensor`` command to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "sensor", help="publish a model's simulated observations (or a file's) over Zenoh, like a sensor",
        description="A stand-in for the physical system: simulates the run's model (a scenario or --model REF; "
                    "the path dtpf run simulates for the same seed and twin) or reads --observations FILE, and "
                    "publishes one observation per step on dtpf/<twin>/sensor/observation at --rate per second, "
                    "with the truth unless --no-truth, then an end-of-stream message. A restarted sensor "
                    "continues after the last observation the twin's entity accepted. Start the twin with "
                    "'dtpf launch --observations live'.")
    add_run_arguments(parser)
    group = parser.add_argument_group("sensor")
    group.add_argument("--rate", type=float, default=10.0, metavar="PER_SECOND",
                       help="observations per second; 0: as fast as possible (default: %(default)s)")
    group.add_argument("--speed", type=float, default=1.0, metavar="FACTOR",
                       help="a driven model's sensors and controls: publish each when its stamp comes, at FACTOR "
                            "times real time; 0: as fast as possible (default: %(default)s)")
    group.add_argument("--no-truth", action="store_true",
                       help="publish the observations only, as a real sensor would")
    group.add_argument("--no-end", action="store_true",
                       help="do not send the end-of-stream message at the end (the twin keeps waiting)")
    group.add_argument("--start", type=int, default=None, metavar="SEQUENCE",
                       help="first sequence number to publish (default: one after the last the twin's entity "
                            "accepted, 1 if none is heard)")
    group.add_argument("--resume-wait", type=float, default=1.5, metavar="SECONDS",
                       help="how long to listen for the entity's status to find where to continue "
                            "(default: %(default)s)")
    group.add_argument("--wait-for-entity", type=float, default=20.0, metavar="SECONDS",
                       help="wait at most this long for the twin's entity before publishing; 0: do not "
                            "wait (default: %(default)s)")
    group.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                       help="logging level on stderr (default: %(default)s)")
    add_zenoh_arguments(parser)
    parser.set_defaults(handler=cmd_sensor)


def command_line(argv: list[str] | None = None) -> int:
    """``python -m dtpf.scripts.sensor``: the same as ``dtpf sensor``."""
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.sensor")
    commands = parser.add_subparsers(dest="command", required=True)
    register(commands)
    return run_command(parser, parser.parse_args(["sensor", *(sys.argv[1:] if argv is None else argv)]))


if __name__ == "__main__":
    sys.exit(command_line())
