"""The regularised particle filter's kernel (post-regularised; Musso, Oudjane and Le Gland 2001, 12.2.2).

Draw from a Gaussian kernel around each resampled particle, x + h D eps with eps ~ N(0, I), D D the
weighted covariance of the set before resampling and h the bandwidth that is optimal for a Gaussian
density, h = (4 / (N (d + 2)))^(1 / (d + 4)).
"""
from __future__ import annotations

import numpy as np

from dtpf.messages.family import MOVES

__all__ = ["bandwidth", "regularised"]


def bandwidth(n: int, d: int) -> float:
    """h_opt of the Gaussian kernel: (4 / (N (d + 2)))^(1 / (d + 4)) (Musso et al. 2001, Eq. 12.12)."""
    return (4.0 / (n * (d + 2.0))) ** (1.0 / (d + 4.0))


@MOVES.builtin("regularised")
def regularised(resampled: np.ndarray, particles: np.ndarray, weights: np.ndarray,
                rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """The regularised filter's kernel (Musso, Oudjane and Le Gland 2001).

    The resampled set plus h D eps, D the symmetric root of the weighted covariance of (particles, weights).

    D is the symmetric square root of the covariance, from its eigenvalues
    clipped at 0: a set collapsed onto one point in some direction is not
    jittered in that direction. ``n``: the N of the bandwidth (default the set's size), as for
    :func:`roughening`.
    """
    m, d = resampled.shape
    n = m if n is None else int(n)
    mean = weights @ particles
    centred = particles - mean
    cov = (centred * weights[:, None]).T @ centred
    values, vectors = np.linalg.eigh(cov)
    root = (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T  # the symmetric root: no sign choice
    return resampled + bandwidth(n, d) * (rng.standard_normal((m, d)) @ root)
