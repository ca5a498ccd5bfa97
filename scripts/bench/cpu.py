"""Each process's CPU time and peak RSS under this one, by kind, sampled from /proc.

:class:`RssSampler` serves :mod:`~dtpf.scripts.bench.fleet` (a fleet's layers) and
:mod:`~dtpf.scripts.bench.fleet_floor` (its stand-ins, with a ``kind`` of their own).
"""
from __future__ import annotations

import os
import threading
import time

import numpy as np


class RssSampler:
    """The largest RSS of every child process of this process (and their children), by kind, and
    every process's CPU time, this one's included, at each sample (wall time, CPU seconds)."""

    def __init__(self, interval: float = 0.25, kind=None):
        self.interval = interval
        #: The kind of a process from its command line (its arguments as bytes); the layers' by default.
        self.kind = kind or _kind
        self.peak: dict[int, tuple[str, int]] = {}
        self.cpu: dict[int, tuple[str, list[tuple[float, float]]]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        me = os.getpid()
        while not self._stop.wait(self.interval):
            self.record(time.time(), _descendants(me, self.kind), me)

    def record(self, now: float, processes, me: int | None = None) -> None:
        """Fold in one sample, (pid, kind, RSS bytes, CPU seconds) per process (``me``: the launcher).

        A process's kind is the last one other than "other" that its samples gave: a child sampled
        between its fork and its exec still shows this process's command line (kind "other"), and a
        sampler that kept the first kind lost that layer's CPU for good (it read no time at all for the
        information service, or half the entities' time). Some samples of a running layer read an
        empty command line too (seen for a fleet's one entity process); they keep the kind it had. A
        process never seen as a layer stays "other", counted in "all". Its peak RSS starts again when its
        kind changes.
        """
        for pid, kind, rss, cpu in processes:
            if pid == me:
                kind = "launcher"
            else:
                if kind == "other" and pid in self.cpu:
                    kind = self.cpu[pid][0]
                old = self.peak.get(pid)
                if old is None or old[0] != kind or rss > old[1]:
                    self.peak[pid] = (kind, rss)
            samples = self.cpu[pid][1] if pid in self.cpu else []
            samples.append((now, cpu))
            self.cpu[pid] = (kind, samples)

    def cpu_between(self, start: float, end: float) -> dict[str, float]:
        """CPU seconds of each kind of process between wall times ``start`` and ``end`` (time.time()),
        each process's samples interpolated linearly (a process that ended in the window counts to its
        last sample)."""
        kinds: dict[str, float] = {}
        for kind, samples in self.cpu.values():
            times, cpus = zip(*samples)
            used = float(np.interp(end, times, cpus) - np.interp(start, times, cpus))
            kinds[kind] = kinds.get(kind, 0.0) + used
        return kinds

    def by_kind(self) -> dict[str, list[int]]:
        kinds: dict[str, list[int]] = {}
        for kind, rss in self.peak.values():
            kinds.setdefault(kind, []).append(rss)
        return kinds


def _descendants(root: int, kind_of=None):
    """(pid, kind, rss bytes, CPU seconds) of ``root`` and every process below it; kind from its
    command line."""
    parents, info = {}, {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                command = f.read().split(b"\0")
            with open(f"/proc/{entry}/statm") as f:
                pages = int(f.read().split()[1])
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()  # fields 3.. of proc(5): state, ppid, ..., utime, stime
        parents[int(entry)] = int(fields[1])
        info[int(entry)] = ((kind_of or _kind)(command), pages * os.sysconf("SC_PAGE_SIZE"),
                            (int(fields[11]) + int(fields[12])) / _TICKS)
    below = {root}
    changed = True
    while changed:
        changed = False
        for pid, ppid in parents.items():
            if ppid in below and pid not in below:
                below.add(pid)
                changed = True
    return [(pid, *info[pid]) for pid in below if pid in info]


_TICKS = os.sysconf("SC_CLK_TCK")


def _kind(command: list[bytes]) -> str:
    text = b" ".join(command).decode(errors="replace")
    for module, kind in (("dtpf.entity.service", "entity"), ("dtpf.information.service", "information"),
                         ("dtpf.system.service", "system"), ("dtpf.scripts.record", "recorder")):
        if module in text:
            return kind
    return "other"
