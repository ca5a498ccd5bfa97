"""``dtpf launch --twins K``: K twins against one information, one system service and one recorder.

The twins are ``<twin>-1`` .. ``<twin>-K``, with the run's options (the same
seed: the random streams are derived per twin, so every twin's numbers are
those of its own ``dtpf run --twin <twin>-i``), hosted by a few entity
processes (``dtpf.entity.service --twins``, one per CPU by default). The
information and system services are started with ``--twins '<twin>-*'`` and
learn each twin from its entity (:mod:`dtpf.shell.fleet`); the recorder records
every twin into one log (``--all-twins``). The run ends when every entity has
ended; the summary gives a line per twin and the fleet's totals.
"""
from __future__ import annotations

import os
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from dtpf.messages import keys
from dtpf.messages.codec import MessageError, decode_for_key
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate, Layer, ServiceState, Status
from dtpf.recording.logfile import what_it_holds
from dtpf.recording.writer import EXIT_LOG_WRITE
from dtpf.scripts.launch import (
    DEFAULT_RESTARTS,
    Bridge,
    EstimateTally,
    LaunchError,
    _describe_code,
    _stop,
    _wait_for_recorder,
    close_bridges,
    default_log_path,
    interrupts_held,
    open_router,
    pump_bridges,
    rejected_by_layer,
    segment_path,
    service_command,
    watch_recorder,
)
from dtpf.shell.bus import Claims, Inbox, Presence

__all__ = ["launch_fleet", "FleetResult", "twin_configs", "entity_groups"]

#: Most messages taken from the inbox before the launcher looks at its children again.
_BATCH = 256


#: Points of each twin's foxglove.PointCloud in a fleet unless asked: none. At K = 100, N = 1e3 the clouds of
#: 1000 points (one twin's default) made the recorder drop 11% of the fleet's messages (12,772 of 116,182).
FLEET_CLOUD_POINTS = 0


def entity_groups(twins: list[str], entities: int | None = None) -> list[list[str]]:
    """The twins of each entity process: ``entities`` groups (default: one per CPU), as even as can be,
    in order."""
    entities = min(len(twins), entities or os.cpu_count() or 1)
    if entities < 1:
        raise ValueError(f"a fleet needs at least one entity process, got {entities}")
    size, extra = divmod(len(twins), entities)
    groups, start = [], 0
    for index in range(entities):
        end = start + size + (index < extra)
        groups.append(twins[start:end])
        start = end
    return groups


def twin_configs(config: RunConfig, count: int) -> list[RunConfig]:
    """The run of each twin of a fleet of ``count``: ``<twin>-1`` .. ``<twin>-<count>``."""
    if count < 1:
        raise ValueError(f"--twins must be at least 1, got {count}")
    return [config.model_copy(update={"twin": f"{config.twin}-{i}"}) for i in range(1, count + 1)]


@dataclass
class FleetResult:
    """What the launcher saw of a fleet's run."""

    config: RunConfig
    twins: list[RunConfig]
    log_path: Path
    tallies: dict[str, EstimateTally] = field(default_factory=dict)
    #: The last status of every (process, twin): a shared service reports for each twin it serves.
    statuses: dict[tuple[int, str], Status] = field(default_factory=dict)
    exit_codes: dict[str, int | None] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)
    #: Set when the log could not be written to the end (what happened and what the log holds, in words).
    log_problem: str | None = None
    #: What the launcher did when a shared service died, in words.
    restarts: list[str] = field(default_factory=list)
    #: Other entities that claimed a twin of the fleet during the run ('twin T: run R, process P on H').
    competitors: list[str] = field(default_factory=list)
    #: The files that make up the log, in order (more than one when the recorder was restarted).
    segments: list[Path] = field(default_factory=list)
    elapsed: float = 0.0
    #: Seconds from the first estimate to the last (the fleet's steady throughput window).
    stepping: float = 0.0
    interrupted: bool = False

    @property
    def twin_steps(self) -> int:
        return sum(t.count for t in self.tallies.values())

    @property
    def rejected(self) -> dict[str, int]:
        """Rejected messages by layer, summed over every process and every twin the layer served."""
        return rejected_by_layer(self.statuses.values())

    def summary(self) -> str:
        c = self.config
        lines = [f"fleet           {len(self.twins)} twins {self.twins[0].twin} .. {self.twins[-1].twin} of "
                 f"{c.model_ref} (N = {c.particles}, {'T = ' + str(c.steps) if c.steps else 'live'}, seed {c.seed})",
                 f"{'twin':<16}{'steps':>7}{'RMSE':>10}{'mean ESS':>10}{'degraded':>10}"]
        for twin in self.twins:
            t = self.tallies[twin.twin]
            rmse = f"{t.rmse:.4f}" if t.truth_steps else "-"
            ess = f"{t.mean_ess:.1f}" if t.count else "-"
            lines.append(f"{twin.twin:<16}{t.count:>7}{rmse:>10}{ess:>10}{t.degraded:>10}"
                         + (f"   {self.failures[twin.twin]}" if twin.twin in self.failures else ""))
        rate = self.twin_steps / self.stepping if self.stepping > 0 else float("nan")
        lines += [
            f"twin-steps      {self.twin_steps}" + (f" of {len(self.twins) * c.steps}" if c.steps else " (live)")
            + (" (interrupted)" if self.interrupted else ""),
            f"degraded steps  {sum(t.degraded for t in self.tallies.values())}",
            "rejected        " + (", ".join(f"{k} {v}" for k, v in sorted(self.rejected.items())) or "-"),
            *(["restarts        " + "; ".join(self.restarts)] if self.restarts else []),
            *[f"competing       another entity ran {who}" for who in self.competitors],
            *([f"log ended       {self.log_problem}"] if self.log_problem else []),
            f"throughput      {rate:.0f} twin-steps/s (first estimate to last)",
            f"time            {self.elapsed:.2f} s",
            f"log             {' + '.join(str(path) for path in (self.segments or [self.log_path]))}",
        ]
        return "\n".join(lines)


def launch_fleet(config: RunConfig, count: int, *, log_path: Path | None = None, port: int | None = None,
                 timeout: float = 2.0, startup_timeout: float = 20.0, log_level: str = "WARNING",
                 rate: float | None = None, progress=None, child_output=None, cloud_points: int | None = None,
                 secure=None, notify=None, entities: int | None = None,
                 keep_estimates: bool = False, restarts: int = DEFAULT_RESTARTS,
                 observation_timeout: float | None = None, threads: int | None = None) -> FleetResult:
    """Run ``count`` twins of ``config`` around an embedded Zenoh router (see the module's text).

    ``threads``: each process's ``--threads``; None: each entity process computes on its share of the
    cores (cores // entity processes, at least 1), the shared services on every core.
    ``entities``: how many entity processes host the twins (default: one per CPU, at most one per twin).
    ``cloud_points``: the entities' ``--cloud-points``; None: :data:`FLEET_CLOUD_POINTS`.
    A live fleet (``--observations live``) has no deadline: each twin takes its observations from its own
    sensor, on ``dtpf/<twin>-<i>/sensor/observation``, and ends when its sensor ends its stream (or after
    ``steps``); the fleet ends when every twin has. ``observation_timeout``: see ``dtpf launch``.
    ``keep_estimates``: keep every twin's estimates (in ``tallies[twin].estimates``).
    ``restarts``: how many times a dead shared information or system service or recorder is started
    again. The twins run on with plain resampling while a shared layer is gone; while a recorder is, the
    launcher records the fleet's keys into a segment of its own (:class:`~dtpf.scripts.launch.Bridge`), and the
    new recorder writes the next segment (``run.1.mcap``, ``run.2.mcap``, ...; ``result.segments``), so a
    recorder's death loses only what it had not flushed.
    """
    twins = twin_configs(config, count)
    cloud_points = FLEET_CLOUD_POINTS if cloud_points is None else cloud_points
    if config.live and config.observations != "live":
        raise LaunchError(f"--twins with live observations takes each twin's from its own key "
                          f"(--observations live), not one key for all ({config.observations!r})")
    log_path = Path(log_path) if log_path else default_log_path(config)
    router, endpoint, secure = open_router(port, secure)
    chunk = keys.twins_chunk(f"{config.twin}-*")
    result = FleetResult(config, twins, log_path,
                         tallies={t.twin: EstimateTally(t.steps, keep=keep_estimates) for t in twins})
    result.segments.append(log_path)
    children: dict[str, subprocess.Popen] = {}
    layer_of_pid: dict[int, str] = {}
    bridges: list[Bridge] = []  # the launcher's own recording while a new recorder starts
    early: dict[int, Inbox] = {}  # a dead recorder's pid -> the bridge's inbox, opened the moment it died
    watchers: dict[int, threading.Thread] = {}  # a recorder's pid -> the thread that waits for it
    stopping = threading.Event()  # set once the recorder is being stopped on purpose
    total = count * (config.steps or 0)
    start = time.monotonic()
    first_estimate = last_estimate = None

    def start_child(name: str, layer: str, run: RunConfig, *extra: str, output: Path | None = None,
                    child_threads: int | None = threads) -> None:
        command = service_command(layer, run, endpoint, timeout=timeout, log_path=output or log_path,
                                  log_level=log_level, observation_timeout=observation_timeout,
                                  rate=rate, cloud_points=cloud_points,
                                  secure=secure.path if secure is not None else None, wait_for_recorder=False,
                                  threads=child_threads)
        children[name] = subprocess.Popen(command + list(extra), stderr=child_output, start_new_session=True)
        layer_of_pid[children[name].pid] = layer
        if layer == "recorder":
            watchers[children[name].pid] = watch_recorder(
                children[name], lambda: Inbox(router, "dtpf/**"), early, stopping.is_set)

    # The shared services serve the fleet's twins and load the fleet's own model (a service learns a twin's
    # model from the bus and loads no other user code).
    shared = ("--twins", f"{config.twin}-*", *(("--allow-model", config.model) if config.model else ()))
    watch = presence = claims = None
    try:
        watch = Inbox(router, f"dtpf/{chunk}/entity/estimate", f"dtpf/{chunk}/*/status",
                      keys.any_layer_pattern(config.twin, "status"), max_payload=1 << 20, max_items=100_000)
        # One twin, one entity: every entity that claims a twin of the fleet, the fleet's own and any other.
        claims = Claims(router, chunk, twins=[twin.twin for twin in twins])
        presence = Presence(router, config.twin, "launcher", names=[layer.value for layer in Layer])
        start_child("recorder", "recorder", config, "--all-twins")
        _wait_for_recorder(children["recorder"], presence, startup_timeout)
        start_child("system", "system", config, *shared)
        start_child("information", "information", config, *shared)
        groups = entity_groups([twin.twin for twin in twins], entities)
        share = threads if threads is not None else max(1, len(os.sched_getaffinity(0)) // len(groups))
        for index, group in enumerate(groups, start=1):
            start_child(f"entity-{index}", "entity", config, "--twins", ",".join(group), child_threads=share)
        per_step = timeout + (1.0 / rate if rate else 0.0)
        # A live fleet waits for its sensors as long as it takes; a file or simulation has T steps.
        deadline = float("inf") if config.live else (
            time.monotonic() + startup_timeout * max(1.0, count / 10) + per_step * (config.steps or 0) + 60.0)
        entity_names = [f"entity-{index}" for index in range(1, len(groups) + 1)]
        restarted = {"information": 0, "system": 0, "recorder": 0}
        gone: set[str] = set()  # a recorder that could not write the log is not started again
        while True:
            with interrupts_held():  # a message taken off the inbox is folded in, whatever signal comes
                item = watch.get(timeout=0.1)
                taken = 0
                while item is not None:
                    if isinstance(_take(result, item, layer_of_pid), Estimate):
                        last_estimate = time.monotonic()
                        first_estimate = first_estimate or last_estimate
                        if progress is not None:
                            progress(result.twin_steps, total)
                    taken += 1
                    item = watch.get(timeout=0) if taken < _BATCH else None
            pump_bridges(bridges, result, notify)
            if bridges and any(pid == children["recorder"].pid for pid, _ in result.statuses):
                bridges.pop().close()  # the new recorder listens: it said so
            if all(children[name].poll() is not None for name in entity_names):
                break
            for layer in ("recorder", "information", "system"):
                if layer in gone or children[layer].poll() is None:
                    continue
                code = children[layer].returncode
                inbox = None
                if layer == "recorder" and (watcher := watchers.pop(children[layer].pid, None)) is not None:
                    watcher.join(timeout=2.0)  # it opens the inbox right after the process ended
                    inbox = early.pop(children[layer].pid, None)
                if inbox is not None and (code == 2 or code == EXIT_LOG_WRITE or restarted[layer] >= restarts):
                    inbox.close()  # no bridge follows
                    inbox = None
                if layer == "recorder" and code == EXIT_LOG_WRITE:
                    # The log's disk is full, over a size limit or read-only: a new recorder would write into
                    # the same place. The fleet goes on unrecorded.
                    gone.add(layer)
                    said = [s.last_error for (pid, _), s in result.statuses.items()
                            if pid == children[layer].pid and s.last_error]
                    result.log_problem = said[-1] if said else \
                        f"the recorder could not write {result.segments[-1]}; {what_it_holds(result.segments[-1])}"
                    if notify is not None:
                        notify(f"{result.log_problem}; the fleet goes on without a recorder (not started again: "
                               f"it would write to the same place)")
                    continue
                if code == 2 or restarted[layer] >= restarts:
                    raise LaunchError(f"the shared {layer} service died ({_describe_code(code)})"
                                      + ("" if code == 2 else "; no restarts left"))
                # The twins run on with plain resampling meanwhile; the new service learns them from their
                # entities' next statuses and serves them from the step they are at.
                restarted[layer] += 1
                result.restarts.append(f"the shared {layer} service died ({_describe_code(code)}) after "
                                       f"{result.twin_steps} twin-steps; started again")
                if notify is not None:
                    notify(result.restarts[-1])
                if layer == "recorder":  # the launcher records until the new recorder listens
                    bridge = segment_path(log_path, len(result.segments))
                    bridges.append(Bridge(router, config, bridge, patterns=("dtpf/**",), inbox=inbox))
                    segment = segment_path(log_path, len(result.segments) + 1)
                    result.segments += [bridge, segment]
                    start_child("recorder", "recorder", config, "--all-twins", output=segment)
                else:
                    start_child(layer, layer, config, *shared)
            if time.monotonic() > deadline:
                raise LaunchError("the fleet did not finish in time")
        for name, group in zip(entity_names, groups):
            code = children[name].returncode
            if code != 0:
                for twin in group:
                    result.failures[twin] = f"its entity process ended: {_describe_code(code)}"
        _stop(children, ("information", "system"), result)
        _drain(watch, result, layer_of_pid)
        stopping.set()
        _stop(children, ("recorder",), result)
    except KeyboardInterrupt:
        result.interrupted = True
    finally:
        stopping.set()
        _stop(children, tuple(children), result)
        close_bridges(bridges, result)
        for inbox in list(early.values()):  # a recorder that died as the run ended: no bridge followed
            inbox.close()
        result.elapsed = time.monotonic() - start
        if first_estimate is not None:
            result.stepping = last_estimate - first_estimate
        if presence is not None:
            presence.close()
        if claims is not None:
            mine = [pid for pid, layer in layer_of_pid.items() if layer == "entity"]
            for claim in claims.others(mine):
                result.competitors.append(claim.describe())
                result.failures.setdefault(claim.twin, "another entity ran this twin during the run: its "
                                                       "estimates are not one twin's run")
            claims.close()
        if watch is not None:
            watch.close()
        router.close()
    return result


def _take(result: FleetResult, item, layer_of_pid) -> Estimate | Status | None:
    """Fold one received message into the result; the message when it was the fleet's own and taken."""
    try:
        message = decode_for_key(item.key, item.payload)
    except MessageError:
        return None
    if message.run_id != result.config.run_id:
        return None
    if isinstance(message, Estimate):
        tally = result.tallies.get(message.twin_id)
        if tally is not None and tally.add(message):
            return message
    elif isinstance(message, Status) and layer_of_pid.get(message.pid) == message.layer.value:
        result.statuses[message.pid, message.twin_id] = message
        return message
    return None


def _drain(watch: Inbox, result: FleetResult, layer_of_pid, quiet: float = 0.3) -> None:
    """Take what is still in flight until none of the fleet's own estimates or statuses came for ``quiet``
    seconds (what others publish meanwhile does not hold the launcher), at most 5 s, and not before every
    twin's entity has said its run ended (its last message: what it published before has arrived by then,
    however far behind a loaded machine left this process), as a solo launch waits for its entity."""
    deadline = time.monotonic() + 5.0
    last_taken = time.monotonic()

    def entities_done() -> bool:
        ended = {twin for (pid, twin), status in result.statuses.items() if layer_of_pid.get(pid) == "entity"
                 and status.state in (ServiceState.FINISHED, ServiceState.FAILED)}
        return ended >= set(result.tallies)

    while (now := time.monotonic()) < deadline:
        if now - last_taken >= quiet and entities_done():
            break
        item = watch.get(timeout=max(0.01, quiet - (now - last_taken)))
        if item is not None and _take(result, item, layer_of_pid) is not None:
            last_taken = time.monotonic()
