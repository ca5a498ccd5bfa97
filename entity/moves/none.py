"""No move: the resampled set as it is (the paper)."""
from __future__ import annotations

from dtpf.messages.family import MOVES

__all__ = ["none"]


@MOVES.builtin("none")
def none(resampled, particles, weights, rng, n=None):
    """No move: the resampled set as it is (the paper)."""
    return resampled
