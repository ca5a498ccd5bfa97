"""Moves after resampling: the field's standard cures for particle impoverishment.

Resampling copies particles; with small process noise the copies stay
together and the set loses its diversity (impoverishment). Two classical
remedies move every resampled particle by a small random amount. They are
not the paper's method; dtpf offers them to compare the paper's
preprocessing against (``--jitter``)::

    from dtpf.entity import jitter
    moved = jitter.roughening(resampled, rng)                  # Gordon, Salmond and Smith (1993)
    moved = jitter.regularised(resampled, particles, weights, rng)   # Musso, Oudjane and Le Gland (2001)

- **Roughening** (Gordon, Salmond and Smith 1993, section 4): add
  N(0, diag(sigma^2)) with sigma_c = K E_c N^(-1/d), where E_c is the range
  (max - min) of component c of the resampled set, d the state dimension and
  K a tuning constant (0.2, the paper's suggestion).
- **Regularised particle filter** (post-regularised, Musso, Oudjane and Le
  Gland 2001, section 12.2.2): draw from a Gaussian kernel around each
  resampled particle, x + h D eps with eps ~ N(0, I), D D the weighted
  covariance of the set before resampling and h the bandwidth that is
  optimal for a Gaussian density, h = (4 / (N (d + 2)))^(1 / (d + 4)).

Both draw from the generator given (the filter passes
``stream(seed, twin, k, "jitter")``, so turning a jitter on changes no other
random number of the run) and return a new array.
"""
from __future__ import annotations

import numpy as np

__all__ = ["JITTERS", "ROUGHENING_K", "roughening", "regularised", "bandwidth", "apply"]

#: Names of the moves; "none" leaves the resampled set as it is (the paper).
JITTERS = ("none", "roughening", "regularised")
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


def bandwidth(n: int, d: int) -> float:
    """h_opt of the Gaussian kernel: (4 / (N (d + 2)))^(1 / (d + 4)) (Musso et al. 2001, Eq. 12.12)."""
    return (4.0 / (n * (d + 2.0))) ** (1.0 / (d + 4.0))


def regularised(resampled: np.ndarray, particles: np.ndarray, weights: np.ndarray,
                rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """The resampled set plus h D eps, D the symmetric root of the weighted covariance of (particles, weights).

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


def apply(name: str, resampled: np.ndarray, particles: np.ndarray, weights: np.ndarray,
          rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """The move ``name`` (:data:`JITTERS`) of the resampled set; ``particles, weights``: the set before;
    ``n``: the N of the bandwidth (default the resampled set's size)."""
    if name == "roughening":
        return roughening(resampled, rng, n=n)
    if name == "regularised":
        return regularised(resampled, particles, weights, rng, n=n)
    if name == "none":
        return resampled
    raise ValueError(f"unknown jitter {name!r}; expected one of {', '.join(JITTERS)}")
