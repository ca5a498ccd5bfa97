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

Each is a module of :mod:`dtpf.entity.moves` (the contract is stated once in
:mod:`dtpf.entity.moves.base`); :func:`apply` and :func:`get` also take a
user's move by reference (``path/to/file.py:NAME``) or by the name an
installed package registers in the entry-point group ``dtpf.moves``.

Every move draws from the generator given (the filter passes
``stream(seed, twin, k, "jitter")``, so turning a jitter on changes no other
random number of the run) and return a new array.
"""
from __future__ import annotations

import numpy as np

from dtpf.entity.moves.regularised import bandwidth, regularised
from dtpf.entity.moves.roughening import ROUGHENING_K, roughening
from dtpf.messages.family import MOVES

__all__ = ["JITTERS", "ROUGHENING_K", "roughening", "regularised", "bandwidth", "apply", "get"]

#: Names of the built-in moves; "none" leaves the resampled set as it is (the paper).
JITTERS = tuple(MOVES.builtins())


def get(name: str):
    """The move ``name`` names, in the contract's form (a built-in, an installed package's, or a reference)."""
    return MOVES.get(name)


def apply(name: str, resampled: np.ndarray, particles: np.ndarray, weights: np.ndarray,
          rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """The move ``name`` of the resampled set; ``particles, weights``: the set before;
    ``n``: the N of the bandwidth (default the resampled set's size)."""
    return MOVES.get(name)(resampled, particles, weights, rng, n=n)
