"""Time between filter steps and the control in force: the drive of each step, from integer stamps.

Each observation, from whichever sensor, is one filter step at its own stamp (integer nanoseconds since an
epoch the data chooses; never the receiving machine's clock). The particles of step k are propagated over
(t_(k-1), t_k] with the controls held over it, zero-order hold: the control in force at a time t is the
latest one stamped at or before t (zeros before the first). When controls change inside the interval it is
split at their stamps, and the model is called once per piece::

    pieces of (t_(k-1), t_k]:  [t_(k-1), s_1) with u(t_(k-1)),  [s_1, s_2) with u(s_1), ...,  [s_j, t_k] with u(s_j)

for the control stamps t_(k-1) < s_1 < ... < s_j < t_k. A control stamped exactly t_k acts from t_k on, over
the next interval. An interval of more than :data:`MAX_PIECES` pieces (controls far faster than the
observations) is cut into that many runs of consecutive pieces, each with its dt-weighted mean control. A
model whose ``propagate`` takes ``control`` but not ``dt`` gets one piece: the control in force at t_(k-1). dt
is (t - s) / 10^9 seconds, computed from the integers, so every process gets the same float.

:class:`Reorder` puts observations (and controls) that arrive out of order in stamp order, within a window
of stamp time; :class:`Timeline` turns the ordered stamps into :class:`Drive` s::

    timeline = Timeline(controls=2, piecewise=True)
    timeline.control(0, [1.0, 0.1])
    timeline.step(0)                      # None: the first step starts from the prior
    timeline.step(100_000_000).pieces     # [[0.1, 1.0, 0.1]]: dt 0.1 s with u = (1.0, 0.1)
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from dtpf.messages.errors import DtpfError

__all__ = ["Drive", "Timeline", "Reorder", "TimeError", "NS"]

#: Nanoseconds in a second.
NS = 1_000_000_000
#: Most pieces one step's interval may be split into (what a particle set carries: MAX_DRIVE_PIECES).
MAX_PIECES = 4096


class TimeError(DtpfError, ValueError):
    """Stamps that cannot make a timeline (one going backwards); the message is one line."""


@dataclass(frozen=True, eq=False)
class Drive:
    """How step k is reached from step k - 1: pieces (P, 1 + c), each row (dt seconds, control u_0 .. u_(c-1))."""

    pieces: np.ndarray

    def iter_pieces(self):
        """(dt, control) per piece; control None for a model without controls."""
        c = self.pieces.shape[1] - 1
        for row in self.pieces:
            yield float(row[0]), (row[1:].copy() if c else None)

    @property
    def dt(self) -> float:
        """Seconds from step k - 1 to step k (the pieces' sum)."""
        return float(self.pieces[:, 0].sum())

    def rows(self) -> list[list[float]]:
        """The pieces as lists of floats (what a particle set carries)."""
        return self.pieces.tolist()

    @classmethod
    def from_fields(cls, dt, control) -> "Drive | None":
        """The drive a particle set carries (its ``dt`` per piece and ``control`` row by row), or None."""
        if dt is None:
            return None
        seconds = np.asarray(dt, dtype=np.float64)[:, None]
        if control is None:
            return cls(seconds)
        return cls(np.hstack([seconds, np.asarray(control, dtype=np.float64).reshape(seconds.shape[0], -1)]))

    @classmethod
    def of(cls, rows) -> "Drive":
        """A drive from :meth:`rows` (a decoded message's)."""
        pieces = np.asarray(rows, dtype=np.float64)
        if pieces.ndim != 2 or pieces.shape[0] < 1 or pieces.shape[1] < 1:
            raise ValueError(f"a drive has rows (dt, control...), got shape {pieces.shape}")
        return cls(pieces)


class Timeline:
    """The drives of steps at increasing stamps, with the controls given so far (module docstring).

    Parameters
    ----------
    controls : int
        c, the number of control components (0: the model takes none).
    piecewise : bool
        Split an interval at the control changes inside it (the model takes ``dt``); False: one piece with
        the control in force at the interval's start.
    """

    def __init__(self, controls: int = 0, piecewise: bool = True):
        self.c = int(controls)
        self.piecewise = bool(piecewise)
        self.last: int | None = None
        self._stamps: list[int] = []
        self._values: list[np.ndarray] = []

    def control(self, stamp: int, values) -> None:
        """Take the control stamped ``stamp`` (ns). TimeError when it is older than the last control or than
        the last step (it can no longer apply); ValueError when it has not c finite values."""
        stamp = int(stamp)
        u = np.asarray(values, dtype=np.float64).reshape(-1)
        if u.size != self.c:
            raise ValueError(f"a control has {u.size} values, the model's control has {self.c}")
        if not np.isfinite(u).all():
            raise ValueError(f"a control has a value that is not finite: {u.tolist()}")
        if self._stamps and stamp < self._stamps[-1]:
            raise TimeError(f"control at {_seconds(stamp)} s is before the last control at "
                            f"{_seconds(self._stamps[-1])} s")
        if self.last is not None and stamp < self.last:
            raise TimeError(f"control at {_seconds(stamp)} s is before the last step at {_seconds(self.last)} s")
        self._stamps.append(stamp)
        self._values.append(u)

    def held(self, stamp: int) -> np.ndarray:
        """The control in force at ``stamp``: the latest at or before it, zeros before the first."""
        i = _latest(self._stamps, stamp)
        return self._values[i].copy() if i >= 0 else np.zeros(self.c)

    def step(self, stamp: int) -> Drive | None:
        """The drive from the last step to a step at ``stamp`` (None for the first step); TimeError if
        ``stamp`` is before the last step's."""
        stamp = int(stamp)
        last, self.last = self.last, stamp
        if last is None:
            self._prune(stamp)
            return None
        if stamp < last:
            self.last = last
            raise TimeError(f"observation at {_seconds(stamp)} s is before the last step at {_seconds(last)} s")
        rows = []
        t, u = last, self.held(last)
        if self.piecewise:
            for s, v in zip(self._stamps, self._values):
                if last < s < stamp:
                    if s > t:
                        rows.append([(s - t) / NS, *u])
                    t, u = s, v
        rows.append([(stamp - t) / NS, *u])
        self._prune(stamp)
        pieces = np.array(rows, dtype=np.float64).reshape(len(rows), 1 + self.c)
        return Drive(pieces if len(rows) <= MAX_PIECES else _coarsened(pieces))

    def _prune(self, stamp: int) -> None:
        """Forget the controls before the one in force at ``stamp``."""
        i = _latest(self._stamps, stamp)
        if i > 0:
            del self._stamps[:i], self._values[:i]


class Reorder:
    """Items with stamps in stamp order, held for a window of stamp time (module docstring).

    An item is released once an item stamped at least ``window`` ns later has been pushed (or at
    :meth:`flush`); one older than the last released is late: :meth:`push` refuses it and counts it. Items
    with equal stamps come out by ``rank`` (controls before observations; sensors in the model's order),
    then in arrival order. At most ``limit`` items are held; beyond that the oldest is released.
    """

    def __init__(self, window: int = 0, limit: int = 100_000):
        if int(window) < 0:
            raise ValueError(f"the reorder window must be >= 0 ns, got {window}")
        self.window = int(window)
        self.limit = int(limit)
        self.late = 0
        self.released: int | None = None
        self._newest: int | None = None
        self._heap: list = []
        self._count = 0

    def push(self, stamp: int, rank: int, item) -> bool:
        """Hold ``item``; False (counted in :attr:`late`) when it is older than what was released already."""
        stamp = int(stamp)
        if self.released is not None and stamp < self.released:
            self.late += 1
            return False
        self._count += 1
        heapq.heappush(self._heap, (stamp, int(rank), self._count, item))
        self._newest = stamp if self._newest is None else max(self._newest, stamp)
        return True

    def ready(self) -> list:
        """The items whose stamp is at least ``window`` older than the newest pushed, in order."""
        out = []
        while self._heap and (self._heap[0][0] <= self._newest - self.window or len(self._heap) > self.limit):
            out.append(self._pop())
        return out

    def flush(self) -> list:
        """Every held item, in order (the stream has ended)."""
        return [self._pop() for _ in range(len(self._heap))]

    def __len__(self) -> int:
        return len(self._heap)

    def _pop(self):
        stamp, _, _, item = heapq.heappop(self._heap)
        self.released = stamp
        return item


def _coarsened(pieces: np.ndarray) -> np.ndarray:
    """At most MAX_PIECES pieces from more: runs of consecutive pieces merged, each with its total dt and its
    dt-weighted mean control (what a particle set can carry; the controls came far faster than the
    observations)."""
    groups = np.array_split(np.arange(pieces.shape[0]), MAX_PIECES)
    out = np.empty((MAX_PIECES, pieces.shape[1]))
    for i, rows in enumerate(groups):
        dt = pieces[rows, 0]
        total = dt.sum()
        out[i, 0] = total
        weights = dt / total if total > 0 else np.full(dt.size, 1.0 / dt.size)
        out[i, 1:] = weights @ pieces[rows, 1:]
    return out


def _latest(stamps: list[int], stamp: int) -> int:
    """Index of the last of ``stamps`` (sorted) at or before ``stamp``; -1 if none."""
    import bisect

    return bisect.bisect_right(stamps, stamp) - 1


def _seconds(stamp: int) -> str:
    sec, ns = divmod(int(stamp), NS)
    return f"{sec}.{ns:09d}"
