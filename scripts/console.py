"""What every command shares on the terminal: progress on stderr, one way to end.

:class:`ProgressBar` follows the steps of one run (``dtpf run``, ``launch``,
``play``); :class:`TaskProgress` the runs of an experiment (the paper's
reports). Imported by the commands, the log tools and the reports alike.

Progress is drawn only on a terminal: piped output and CI logs get the
summary lines alone. ``DTPF_PROGRESS=1`` in the environment draws it anyway
(``DTPF_PROGRESS=0`` never).
"""
from __future__ import annotations

import os
import sys
import time

from dtpf.messages.errors import DtpfError

__all__ = ["ProgressBar", "TaskProgress", "run_command", "stop_on_signals", "shows_progress"]

#: Environment variable that forces progress on ("1") or off ("0") whatever the stream is.
PROGRESS_ENV = "DTPF_PROGRESS"


def shows_progress(stream, force: bool | None = None) -> bool:
    """Whether progress is drawn on ``stream``: ``force`` if given, else ``DTPF_PROGRESS`` if set to 1 or 0,
    else whether the stream is a terminal."""
    if force is not None:
        return bool(force)
    setting = os.environ.get(PROGRESS_ENV, "").strip()
    if setting in ("0", "1"):
        return setting == "1"
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def stop_on_signals():
    """An event SIGINT or SIGTERM sets, for a command that serves until it is stopped (``dtpf router``,
    ``dtpf bridge``): install it before serving, then ``while not stop.wait(0.5): pass``."""
    import signal
    import threading

    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    return stop


def run_command(parser, args) -> int:
    """Call the handler a subcommand set (``args.handler``): any :class:`DtpfError` (or ValueError) is
    one line and exit 2, Ctrl-C exit 130, output piped into ``head`` and closed a quiet exit 0."""
    try:
        return args.handler(args)
    except (DtpfError, ValueError) as error:
        parser.exit(2, f"dtpf {args.command}: error: {error}\n")
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        sys.stderr.close()
        return 0


class ProgressBar:
    """A one-line progress bar on stderr, redrawn at most every 2 %; drawn only on a terminal
    (``force``: True draws it anyway, False never; default: :func:`shows_progress`)."""

    def __init__(self, stream=None, width: int = 30, force: bool | None = None):
        self.stream = sys.stderr if stream is None else stream
        self.width = width
        self.shown = -1
        self.enabled = shows_progress(self.stream, force)

    def __call__(self, done: int, total: int | None) -> None:
        if not self.enabled:
            return
        if not total:  # a live run: no end known
            if done - self.shown >= 10 or self.shown < 0:
                self.shown = done
                self.stream.write(f"\rstep {done}")
                self.stream.flush()
            return
        percent = 100 * done // total
        if percent // 2 == self.shown // 2 and done != total:
            return
        self.shown = percent
        filled = self.width * done // total
        self.stream.write(f"\r[{'#' * filled}{'.' * (self.width - filled)}] step {done}/{total}")
        if done == total:
            self.stream.write("\n")
        self.stream.flush()


class TaskProgress:
    """Progress of one experiment on stderr: a redrawn line on a terminal; nothing otherwise unless
    forced (``force`` or ``DTPF_PROGRESS=1``: then a line per 10%)."""

    def __init__(self, name: str, total: int, force: bool | None = None):
        self.name, self.total, self.start = name, total, time.perf_counter()
        try:
            self.tty = sys.stderr.isatty()
        except (AttributeError, ValueError):
            self.tty = False
        self.enabled = shows_progress(sys.stderr, force)
        self.shown = -1

    def __call__(self, done: int) -> None:
        if not self.enabled:
            return
        percent = 100 * done // max(self.total, 1)
        step = 1 if self.tty else 10
        if percent // step == self.shown // step and done != self.total:
            return
        self.shown = percent
        elapsed = time.perf_counter() - self.start
        eta = elapsed / done * (self.total - done) if done else float("nan")
        line = f"{self.name}: {done}/{self.total} runs ({percent}%), {elapsed:.0f} s, about {eta:.0f} s left"
        sys.stderr.write(("\r" + line + " " * 8) if self.tty else line + "\n")
        if self.tty and done == self.total:
            sys.stderr.write("\n")
        sys.stderr.flush()
