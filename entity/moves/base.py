"""The contract of a move after resampling, and the checks a user's move passes before a run.

Every move has the form ``moved = move(resampled, particles, weights, rng, n=None)``:

Parameters
----------
resampled : (M, d) float64 ndarray
    The resampled set to move (read-only: return a new array).
particles, weights : (N, d), (N,) ndarray
    The weighted set before resampling (its spread sets a kernel's width).
rng : numpy.random.Generator
    The only source of randomness: ``stream(seed, twin, k, "jitter")``, so a move changes no other random
    number of the run.
n : int, optional, keyword
    The N of a bandwidth when it differs from M (the system layer moves a copy of M particles as the
    entity's N would); a user's move may leave it out of its signature.

Returns
-------
moved : (M, d) float64 ndarray, finite.

A user's move may take four arguments, ``move(resampled, particles, weights, rng)``; :func:`adapt` gives it
the contract's form and checks its output at every call (shape, finite values: one line naming what is
wrong). It is tried on a small set before a run.
"""
from __future__ import annotations

import numpy as np

from dtpf.messages import references
from dtpf.messages.family import MOVES
from dtpf.messages.references import ReferenceLoadError, a

__all__ = ["MOVES", "adapt"]


def adapt(obj, where: str):
    """A user's move in the contract's form, tried on a small set."""
    signature = references.function_of(obj, where, "a move", "move(resampled, particles, weights, rng)",
                                       ("resampled", "particles", "weights", "rng"))
    takes_n = signature.takes("n")
    move = _Checked(obj, where, takes_n)
    rng = np.random.default_rng(0)
    particles = rng.standard_normal((5, 2))
    move(particles[[0, 0, 2, 3, 3]], particles, np.full(5, 0.2), rng)
    return move


class _Checked:
    """A user's move in the contract's form, its output checked."""

    def __init__(self, function, where: str, takes_n: bool):
        self.function, self.where, self.takes_n = function, where, takes_n
        self.__name__ = getattr(function, "__name__", "move")
        self.__doc__ = getattr(function, "__doc__", None)

    def __call__(self, resampled, particles, weights, rng, n=None) -> np.ndarray:
        try:
            if self.takes_n:
                result = self.function(resampled, particles, weights, rng, n=n)
            else:
                result = self.function(resampled, particles, weights, rng)
        except Exception as exc:
            raise ReferenceLoadError(f"{self.where} raised {type(exc).__name__}: {exc}") from exc
        moved = np.asarray(result, dtype=np.float64) if isinstance(result, np.ndarray) or \
            isinstance(result, (list, tuple)) else None
        if moved is None or moved.shape != resampled.shape:
            raise ReferenceLoadError(f"{self.where} returned {a(result)}"
                                     f"{f' of shape {moved.shape}' if moved is not None else ''}, expected the "
                                     f"moved set, shape {resampled.shape}")
        if not np.all(np.isfinite(moved)):
            raise ReferenceLoadError(f"{self.where} returned values that are not finite (NaN or inf)")
        return moved if moved is not resampled else moved.copy()
