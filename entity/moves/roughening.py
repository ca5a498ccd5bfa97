"""Roughening (Gordon, Salmond and Smith 1993, section 4).

Add N(0, diag(sigma^2)) with sigma_c = K E_c N^(-1/d), where E_c is the range
(max - min) of component c of the resampled set, d the state dimension and K a
tuning constant (0.2, the paper's suggestion).
"""
from __future__ import annotations

import numpy as np

from dtpf.messages.family import MOVES

__all__ = ["ROUGHENING_K", "roughening", "roughening_move"]

#: K of roughening (Gordon, Salmond and Smith 1993 suggest 0.2).
ROUGHENING_K = 0.2


def roughening(resampled: np.ndarray, rng: np.random.Generator, k: float = ROUGHENING_K,
               n: int | None = None) -> np.ndarray:
    """The resampled set plus N(0, (K E_c N^(-1/d))^2) per component c (E_c: range of component c).

    ``n``: the N of the bandwidth when it differs from the set's size (the system layer's copy of M
    particles moves them as the entity's N would); default the set's size.
    """
    m, d = resampled.shape
    n = m if n is None else int(n)
    sigma = k * np.ptp(resampled, axis=0) * n ** (-1.0 / d)
    return resampled + rng.standard_normal((m, d)) * sigma


@MOVES.builtin("roughening")
def roughening_move(resampled, particles, weights, rng, n=None):
    """Roughening (Gordon, Salmond and Smith 1993): Gaussian noise scaled by each component's range."""
    return roughening(resampled, rng, n=n)
