"""``dtpf serve LOG...``: a finished log answers ``history`` questions over Zenoh, as a recorder does live.

::

    dtpf serve runs/ungm-1.mcap --listen tcp/127.0.0.1:7448
    dtpf ask ungm-1 history --steps 10:20 --connect tcp/127.0.0.1:7448

Each twin of the log gets a queryable on ``dtpf/<twin>/recorder/history``;
its answers are those of :mod:`dtpf.scripts.logs.history` (the JSON of
``dtpf cat --json``), bounded by the selector's limits (docs/guides/ask.md).
The recorder answers the same questions from the file it is writing
(:func:`answer_history`): what it has flushed, at most its flush interval
behind.
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

from dtpf.messages import keys, queries
from dtpf.recording.logfile import Log, LogError, read_log
from dtpf.scripts.console import stop_on_signals
from dtpf.scripts.logs.history import StepIndex, history_answer
from dtpf.scripts.logs.summary import read_for_command
from dtpf.shell.bus import BusError, add_zenoh_arguments, free_port, open_session, zenoh_config_from_args
from dtpf.shell.queries import Queryable, worker

__all__ = ["LogHistory", "FileHistory", "answer_history", "register", "cmd_serve", "HISTORY_RATE"]

#: History questions a second one queryable answers (each reads the selection from the log).
HISTORY_RATE, HISTORY_BURST = 10.0, 20
#: A growing log is read again at most this often (seconds): a recorder's answers are at most this much, and its
#: flush interval, behind.
REREAD_INTERVAL = 1.0
#: The largest growing log a recorder reads to answer (it holds what it read in memory): beyond it, history is
#: asked of ``dtpf serve`` (on a copy of the segment, or once the run is over).
MAX_LIVE_LOG_BYTES = 512 << 20
#: Most twins of one log served.
MAX_TWINS = 10_000


def twins_of(log: Log) -> list[str]:
    """The twins of a log, from its channels' topics (``dtpf/<twin>/...``)."""
    found = []
    for topic in log.topics():
        chunks = topic.split("/")
        if len(chunks) == 4 and chunks[0] == keys.PREFIX and chunks[1] not in found:
            found.append(chunks[1])
    return found


class LogHistory:
    """Answers history questions from a log read once."""

    def __init__(self, log: Log):
        self.log = log
        self.index = StepIndex()

    def current(self) -> Log:
        return self.log

    def __call__(self, key: str, text: str) -> bytes:
        twin = key.split("/")[1]
        if "*" in twin or "$" in twin:
            raise queries.SelectorError("history answers one twin at a time: ask dtpf/<twin>/recorder/history")
        selector = queries.parse("history", text)
        return history_answer(self.current(), twin, selector, self.index)


class FileHistory(LogHistory):
    """Answers history questions from a log being written: read again when the file has grown, at most every
    :data:`REREAD_INTERVAL` seconds; the steps of the messages read before are kept. A file of more than
    :data:`MAX_LIVE_LOG_BYTES` is not read (the error reply says so)."""

    def __init__(self, path):
        self.path = Path(path)
        self._seen: tuple[int, int] | None = None
        self._lock = threading.Lock()
        self.log = None
        self.index = StepIndex()
        self._read_at = 0.0

    def current(self) -> Log:
        with self._lock:
            try:
                stat = os.stat(self.path)
            except OSError as error:  # the reply names the file, not where it is on this machine
                raise LogError(f"the log {self.path.name} cannot be read: {error.strerror}") from None
            if stat.st_size > MAX_LIVE_LOG_BYTES:
                self.log = None  # what was read goes
                raise queries.SelectorError(f"the log {self.path.name} is {stat.st_size >> 20} MiB, more than the "
                                            f"{MAX_LIVE_LOG_BYTES >> 20} MiB a recorder reads to answer; ask a dtpf "
                                            f"serve of it")
            seen = (stat.st_size, stat.st_mtime_ns)
            now = time.monotonic()
            if self.log is None or (seen != self._seen and now - self._read_at >= REREAD_INTERVAL):
                try:
                    self.log = read_log(self.path)
                except LogError:
                    raise LogError(f"the log {self.path.name} cannot be read yet") from None
                self._seen, self._read_at = seen, now
            return self.log


def answer_history(session, twins, source: LogHistory, log=None) -> list[Queryable]:
    """One history queryable a twin on ``session``, answered from ``source``; ``twins``: twin ids, or "*"
    (any twin: the key ``dtpf/*/recorder/history``, a recorder of every twin)."""
    names = ["*"] if twins == "*" else list(twins)
    on = worker("history")
    return [Queryable(session, f"{keys.PREFIX}/{twin}/recorder/history" if twin == "*" else queries.key(twin, "history"),
                      source, on=on, rate=HISTORY_RATE, burst=HISTORY_BURST, log=log) for twin in names]


def cmd_serve(args: argparse.Namespace) -> int:
    """``dtpf serve LOG...``: 0 after Ctrl-C, 1 when a log cannot be read, 2 on a bad option."""
    log = read_for_command(args, "serve")
    if log is None:
        return 1
    if log.problem:
        print(f"dtpf serve: note: {log.problem}", file=sys.stderr)
    twins = twins_of(log)
    if not twins:
        print(f"dtpf serve: error: {', '.join(map(str, args.log))} holds no twin's messages", file=sys.stderr)
        return 1
    if len(twins) > MAX_TWINS:
        print(f"dtpf serve: error: the log holds {len(twins)} twins; at most {MAX_TWINS} are served", file=sys.stderr)
        return 1
    if not args.listen and not args.connect and not args.secure and not args.zenoh_config:
        args.listen = [f"tcp/127.0.0.1:{free_port()}"]  # a port a client can be told
    try:
        session = open_session(zenoh_config_from_args(args, role="recorder"))
    except BusError as error:
        print(f"dtpf serve: error: {error}", file=sys.stderr)
        return 2
    stop = stop_on_signals()
    served = answer_history(session, twins, LogHistory(log))
    try:
        where = ", ".join(args.listen or args.connect) or "the configured endpoints"
        shown = ", ".join(twins[:5]) + (f" and {len(twins) - 5} more" if len(twins) > 5 else "")
        print(f"dtpf serve: answering history of {shown} ({len(log.messages)} messages) on {where}; "
              f"e.g. dtpf ask {twins[0]} history --steps 1:10 --connect {(args.listen or args.connect or ['ENDPOINT'])[0]}"
              f"; Ctrl-C ends", file=sys.stderr, flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        for queryable in served:
            queryable.close()
        session.close()
    counts = [q.counts for q in served]
    print(f"dtpf serve: answered {sum(c.answered for c in counts)} questions, refused "
          f"{sum(c.refused + c.failed for c in counts)}", file=sys.stderr)
    return 0


def register(subparsers) -> None:
    """Add ``serve`` to an argparse subparsers object."""
    serve = subparsers.add_parser(
        "serve", help="answer history questions (dtpf ask TWIN history) from a finished log over Zenoh",
        description="Serve a finished log over Zenoh: each twin of the log answers 'dtpf ask TWIN history' (the "
                    "queryable dtpf/<twin>/recorder/history) with the messages of the steps, times and topics "
                    "asked, as 'dtpf cat --json' prints them, bounded (docs/guides/ask.md). Without --listen or "
                    "--connect it listens on a free loopback port and says which. Ctrl-C ends it.")
    serve.add_argument("log", type=Path, nargs="+", metavar="LOG",
                       help="MCAP log written by dtpf (several: the segments of one run)")
    add_zenoh_arguments(serve)
    serve.set_defaults(handler=cmd_serve)
