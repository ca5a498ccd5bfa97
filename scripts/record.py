"""Recorder service: every dtpf message of a twin (or of all twins) into MCAP.

Subscribes to ``dtpf/<twin>/**`` (``--all-twins``: ``dtpf/**``) and writes
each message as received, bytes untouched, one channel per key expression,
schemas embedded. The log records what the run is: a payload that a service
would reject (it does not decode, belongs to another run, or does not fit
the run's N, dimension or steps) is not written to its channel; it is
counted, and a bounded sample of them (where, why, the first bytes) goes to
``dtpf/<twin>/recorder/rejected``. SIGINT or SIGTERM: the messages already
received are written and the file is finished (summary and footer), so the
log stays readable; a SIGKILL loses at most the last ``--flush-interval``
seconds. The log is a new file: the recorder never opens an existing one (it
exits with code 2, saying whether another recorder holds it) and holds an
advisory lock on it while writing. A log that cannot be written (a full disk,
a file-size limit, a read-only file system, the file deleted) ends the
recording: the recorder says in one line what happened and up to which step
the file holds the run, and exits with code 3 (:data:`dtpf.recording.writer.EXIT_LOG_WRITE`).

Nothing a publisher's cache holds is lost across a partition or a restart of
the recorder: every service's publisher keeps its last messages (the services'
``--cache-samples``, 600 by default: 30 s of a twin at 20 steps/s) and the
recorder's subscriber (Zenoh's advanced subscriber) asks for what it missed
when the publisher appears again or its sequence shows a gap, and, when it
starts, for what the caches hold of the run so far (a publisher whose live
messages come before its cache's answer gives only what follows). Recovered messages arrive
late, each publisher's in its order; the log tools order by step. What a cache
no longer held is noted in the log (``dtpf/<twin>/recorder/missed``: key, count
and the steps around the gap) and named by ``dtpf summary`` and ``dtpf verify``.

Run ``python -m dtpf.scripts.record --help`` for the options.
"""
from __future__ import annotations

import argparse
import time

import zenoh

from dtpf.entity import model_ref
from dtpf.messages import keys
from dtpf.messages.admission import RunShape
from dtpf.messages.codec import encode
from dtpf.messages.config import RunConfig, add_run_arguments
from dtpf.messages.models import Layer, ServiceState, Status
from dtpf.recording.admission import Admission
from dtpf.recording.logfile import what_it_holds
from dtpf.recording.writer import (COMPRESSION, EXIT_LOG_WRITE, LogExistsError, LogWriteError, McapRecording,
                                   auto_compression)
from dtpf.scripts.serve import FileHistory, answer_history
from dtpf.shell.bus import add_zenoh_arguments
from dtpf.shell.service import ServiceShell, add_service_arguments, run_service

#: The recorder's inbox holds this many of the run's largest payload, at least this many bytes.
RECORDER_INBOX_PAYLOADS, RECORDER_INBOX_BYTES = 64, 512 << 20
#: ... and at most this many messages (a fleet of 40 twins filled 4,096 with small ones in a burst).
RECORDER_INBOX_ITEMS = 1 << 16

__all__ = ["main"]


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Record until SIGINT/SIGTERM."""
    pattern = keys.ALL if args.all_twins else keys.twin_pattern(config.twin)
    compression = args.compression
    dim = model_ref.resolve(config.model_ref).dim
    if compression == "auto":
        compression = auto_compression(config.particles * (dim + 1) * 8)
    # The file is finished before the Zenoh session closes, so a session slow to close (the
    # launcher SIGKILLs a service after 10 s) cannot cost the log its summary and footer.
    with ServiceShell("recorder", config, zenoh_config) as shell:
        if not args.all_twins:  # other twins may run other sizes
            shell.expect(RunShape(config.particles, dim, None, config.steps))
        try:
            # Created, never opened: a log is never overwritten, and a second recorder on the path fails here.
            recording = McapRecording(args.output, compression=compression, flush_interval=args.flush_interval,
                                      exclusive=True)
        except LogExistsError as error:
            shell.state, shell.last_error = ServiceState.FAILED, str(error)
            shell.log.error("%s", shell.last_error)
            return 2
        except OSError as error:
            shell.state, shell.last_error = ServiceState.FAILED, f"cannot write the log {args.output}: {error}"
            shell.log.error("%s", shell.last_error)
            return 2
        try:
            with recording:
                code = _record(shell, recording, pattern, compression, args)
        except LogWriteError as error:
            shell.state, shell.last_error = ServiceState.FAILED, f"{error}; {what_it_holds(error.path)}"
            shell.log.error("%s", shell.last_error)
            return EXIT_LOG_WRITE
        # The log is finished: a Zenoh close that outlasts the exit watchdog's grace (a loaded machine)
        # cannot make the run's exit code say otherwise.
        shell.watchdog.settle(code)
        return code


def _record(shell: ServiceShell, recording: McapRecording, pattern: str, compression: str,
            args: argparse.Namespace) -> int:
    """Write what arrives on ``pattern`` until SIGINT/SIGTERM, then what is still in flight."""
    # A live twin may follow another twin's sensor: its observations are recorded too.
    sensor = shell.config.observation_key()
    extra = [sensor] if sensor and not args.all_twins and not sensor.startswith(pattern[:-2]) else []
    # The recorder takes every message of the twin and must lose none: a burst it cannot write at once
    # (a busy machine, N = 1e5 at 120 steps/s is 390 MB/s of particle sets) waits in a deeper inbox than a
    # layer's; 64 MiB dropped sets at N = 1e5 with the machine's 2 cores shared. A set by reference that
    # finds it full stays in its slot and its writer waits for the recorder.
    inbox = shell.inbox_on(pattern, *extra, payloads=RECORDER_INBOX_PAYLOADS, min_bytes=RECORDER_INBOX_BYTES,
                           max_items=RECORDER_INBOX_ITEMS, recover=True, back_pressure=True)
    silences = Silences(shell.log, args.gap_after)
    admission = Admission(shell, all_twins=args.all_twins, silences=silences)
    # dtpf ask TWIN history: answered from what the file holds (dtpf.scripts.serve).
    answer_history(shell.session, "*" if args.all_twins else [shell.config.twin], FileHistory(args.output), shell.log)
    shell.running()
    shell.log.info("recording %s into %s (%s chunks)", pattern, args.output, compression)
    next_check = time.monotonic() + 1.0
    while not shell.stopping:
        item = inbox.get(timeout=0.2)
        if item is not None:
            admission.record(recording, item)
        else:
            recording.flush_if_due()
        if time.monotonic() >= next_check:
            silences.check()
            next_check = time.monotonic() + 1.0
    # Stopping: write what had arrived (the inbox's bound bounds it: the exit watchdog waits while
    # this moves), then what is still in flight for at most --drain seconds.
    shell.watchdog.step = "writing the messages received before the stop"
    for _ in range(len(inbox)):
        item = inbox.get(timeout=0)
        if item is None:
            break
        admission.record(recording, item)
        shell.watchdog.progress()
    shell.watchdog.step = "writing the messages in flight"
    # In flight: what arrives within --drain seconds and, while a twin heard from has not yet said its run
    # ended, for up to --drain-finished seconds: an entity's final status is its last message, so what it
    # published before has arrived once that status has (a recorder behind on a loaded machine would
    # otherwise close its session on the run's last steps).
    start = time.monotonic()
    while True:
        waiting = silences.waiting()
        if time.monotonic() - start >= (max(args.drain, args.drain_finished) if waiting else args.drain):
            if waiting:
                shell.log.warning("stopped before %s said their run ended", ", ".join(sorted(waiting)[:10]))
            break
        # A wait bounded just above: the exit watchdog (whose grace is shorter than --drain-finished) must not
        # cut it and leave the log without its summary and footer.
        shell.watchdog.progress()
        item = inbox.get(timeout=0.05)
        if item is not None:
            admission.record(recording, item)
        elif not waiting:
            break
    shell.watchdog.step = "finishing the log"
    inbox.close()
    admission.finish(recording)
    # The recorder's own last word goes into its log too (its published one would arrive too late).
    shell.state = ServiceState.FINISHED
    final = shell.status()
    recording.write(keys.key_for(final), encode(final))
    shell.log.info("wrote %d messages to %s", recording.messages, args.output)
    return 0


class Silences:
    """When a twin's messages stop and when they come back, said in the recorder's log.

    A twin whose messages stop for ``after`` seconds before its entity said it finished (a link cut, a
    partition between hosts, a dead entity) is named once with its last step; when its messages come back,
    the recorder says after how long and from which step, so a gap in the record is never silent. At most
    :data:`MAX_TWINS` twins are followed (the oldest forgotten first).
    """

    def __init__(self, log, after: float):
        self.log, self.after = log, after
        self.last: dict[str, tuple[float, int]] = {}  # twin -> (monotonic time, step) of its last message
        self.silent: dict[str, float] = {}            # twin -> when it was found silent
        self.finished: set[str] = set()               # twins whose entity said its run is over
        self.gaps = 0

    def heard(self, message) -> None:
        """Note a recorded message of a twin; only its entity's count (a shared service elsewhere may still
        speak of a twin whose entity is out of reach)."""
        if message.layer != Layer.ENTITY:
            return
        twin, now = message.twin_id, time.monotonic()
        if isinstance(message, Status):
            if message.state in (ServiceState.FINISHED, ServiceState.FAILED):
                self.last.pop(twin, None)  # its run is over: its silence from now on is no gap
                self.silent.pop(twin, None)
                if len(self.finished) >= MAX_TWINS:
                    self.finished.pop()
                self.finished.add(twin)
                return
            self.finished.discard(twin)  # running (again)
        if twin in self.finished:
            return  # the other layers' last words after its entity's
        since = self.silent.pop(twin, None)
        if since is not None:
            gone = now - self.last[twin][0] if twin in self.last else now - since
            self.log.warning("twin %s: messages again after %.1f s without any, from step %d", twin, gone,
                             message.step)
        if twin not in self.last and len(self.last) >= MAX_TWINS:
            del self.last[next(iter(self.last))]
        self.last.pop(twin, None)
        self.last[twin] = (now, message.step)

    def waiting(self) -> list[str]:
        """The twins heard from that have not said their run ended and have not fallen silent."""
        return [twin for twin in self.last if twin not in self.silent]

    def check(self) -> None:
        """Name the twins that have just gone silent."""
        now = time.monotonic()
        for twin, (when, step) in self.last.items():
            if twin not in self.silent and now - when >= self.after:
                self.silent[twin] = now
                self.gaps += 1
                self.log.warning("twin %s: no message for %.0f s, the last at step %d; the record has a gap "
                                 "until its messages come back", twin, now - when, step)


#: Most twins :class:`Silences` follows.
MAX_TWINS = 10_000


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m dtpf.scripts.record",
        description="dtpf recorder: writes every message of a twin into an MCAP file, one channel per key "
                    "expression, schemas embedded.",
        epilog="Recovery: every dtpf service's publishers keep their last messages (--cache-samples N, 600 by "
               "default: 30 s of a twin at 20 steps/s; --cache-mb, a budget per process shared by its twins, bounds "
               "caches of large particle sets and large fleets), and the "
               "recorder recovers from them what a partition, a cut link or its own late start made it miss. A "
               "partition longer than the cache loses the rest: the log notes it on dtpf/<twin>/recorder/missed "
               "(key, count, the steps around the gap), and dtpf summary and dtpf verify name those steps. The "
               "--cache-* options below size this recorder's own publishers (its status).")
    parser.add_argument("--output", "-o", required=True, help="MCAP file to write; created, never overwritten "
                                                                    "(an existing file is an error)")
    parser.add_argument("--all-twins", action="store_true", help="record dtpf/** instead of one twin")
    parser.add_argument("--compression", default="auto", choices=["auto", *sorted(COMPRESSION)],
                        help="chunk compression; 'auto': lz4 while a particle set (N x (d + 1) float64) "
                             "is at most 64 KiB, none above, where random states do not compress "
                             "(default: %(default)s)")
    parser.add_argument("--flush-interval", type=float, default=1.0, metavar="SECONDS",
                        help="flush the open chunk at least this often (default: %(default)s)")
    parser.add_argument("--gap-after", type=float, default=5.0, metavar="SECONDS",
                        help="say in the log when a twin's messages stop for this long before its entity finished "
                             "(a link cut, a partition), and when they come back (default: %(default)s)")
    parser.add_argument("--drain", type=float, default=0.5, metavar="SECONDS",
                        help="on SIGINT/SIGTERM, after writing every message already received, keep writing "
                             "the ones still arriving for at most this long; it stops as soon as none comes "
                             "for 50 ms (default: %(default)s)")
    parser.add_argument("--drain-finished", type=float, default=5.0, metavar="SECONDS",
                        help="... and while a twin it heard from has not said its run ended, keep writing for "
                             "at most this long (default: %(default)s)")
    add_run_arguments(parser)
    add_service_arguments(parser)
    add_zenoh_arguments(parser)
    return parser


if __name__ == "__main__":
    raise SystemExit(run_service("recorder", main, build_parser()))
