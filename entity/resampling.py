"""Traditional resampling schemes (paper section 2.3).

The recommended import is::

    from entity import resampling as rs
    ancestors = rs.systematic(weights, rng)
    particles = particles[ancestors]

Every scheme has the same contract, ``ancestors = scheme(weights, rng)``:

Parameters
----------
weights : (N,) array_like
    Normalised weights: finite, non-negative, summing to 1 (checked; a
    ValueError names what is wrong).
rng : numpy.random.Generator
    The only source of randomness; schemes never touch global state.

Returns
-------
ancestors : (N,) ndarray of int64
    Index of the parent of each new particle, in non-decreasing order.

All four are unbiased: the expected number of copies of particle i is N w_i.
They differ in the variance of that number: multinomial (largest),
residual, stratified, systematic (smallest in practice).

Each scheme is one compiled pass (numba) over the particles that hands
each particle the sorted points falling below its running weight sum; the
points are never searched for (``np.searchsorted`` costs a binary search per
point and is 2-3x slower at N = 1e6).
"""
from __future__ import annotations

from typing import Callable

import numba
import numpy as np

from messages.arrays import check_weights

__all__ = [
    "multinomial",
    "stratified",
    "systematic",
    "residual",
    "RESAMPLERS",
    "get",
    "inverse_cdf",
]

Resampler = Callable[[np.ndarray, np.random.Generator], np.ndarray]


@numba.njit(cache=True, nogil=True)
def _fill_tail(ancestors, k, last):  # pragma: no cover - compiled
    # Points past the running sum (it can end a few ulps below 1) go to the
    # last particle with positive weight: the tail guard.
    while k < ancestors.shape[0]:
        ancestors[k] = last
        k += 1


@numba.njit(cache=True, nogil=True)
def _last_positive(weights):  # pragma: no cover - compiled
    for j in range(weights.shape[0] - 1, -1, -1):
        if weights[j] > 0.0:
            return j
    return weights.shape[0] - 1


@numba.njit(cache=True, nogil=True)
def _inverse_cdf(points, weights):  # pragma: no cover - compiled
    # One pass over the particles; each takes the points below its running sum.
    n = points.shape[0]
    ancestors = np.empty(n, dtype=np.int64)
    cumulative = 0.0
    k = 0
    for j in range(weights.shape[0]):
        cumulative += weights[j]
        while k < n and points[k] < cumulative:
            ancestors[k] = j
            k += 1
    _fill_tail(ancestors, k, _last_positive(weights))
    return ancestors


@numba.njit(cache=True, nogil=True)
def _systematic(weights, u):  # pragma: no cover - compiled
    # Points (k + u) / N are computed, not stored: point k < C_j  <=>  k < N C_j - u.
    n = weights.shape[0]
    ancestors = np.empty(n, dtype=np.int64)
    cumulative = 0.0
    k = 0
    for j in range(n):
        cumulative += weights[j]
        end = min(n, int(np.ceil(cumulative * n - u)))
        while k < end:
            ancestors[k] = j
            k += 1
    _fill_tail(ancestors, k, _last_positive(weights))
    return ancestors


@numba.njit(cache=True, nogil=True)
def _spacings(weights, exponentials):  # pragma: no cover - compiled
    # Sorted uniforms as normalised partial sums of M + 1 exponentials,
    # merged with the running sum scaled by the same total.
    m = exponentials.shape[0] - 1
    total = 0.0
    for i in range(m + 1):
        total += exponentials[i]
    ancestors = np.empty(m, dtype=np.int64)
    cumulative = 0.0
    point = exponentials[0]
    k = 0
    for j in range(weights.shape[0]):
        cumulative += weights[j] * total
        while k < m and point < cumulative:
            ancestors[k] = j
            k += 1
            point += exponentials[k]
    _fill_tail(ancestors, k, _last_positive(weights))
    return ancestors


@numba.njit(cache=True, nogil=True)
def _stratified(weights, v):  # pragma: no cover - compiled
    # Point k is (k + v_k) / N, computed as the merge reaches it.
    n = weights.shape[0]
    ancestors = np.empty(n, dtype=np.int64)
    cumulative = 0.0
    k = 0
    # Compare N * point = k + v_k with N * running sum: no division per point.
    point = v[0]
    for j in range(n):
        cumulative += weights[j]
        scaled = cumulative * n
        while k < n and point < scaled:
            ancestors[k] = j
            k += 1
            if k < n:
                point = k + v[k]
    _fill_tail(ancestors, k, _last_positive(weights))
    return ancestors


#: N w_i this close below an integer counts as that integer in residual
#: resampling: 49 * (1/49) is 0.9999999999999999 in float64, and equal
#: weights must give one copy each, not a multinomial draw.
_ROUNDING = 1e-9


@numba.njit(cache=True, nogil=True)
def _residual(weights, rng):  # pragma: no cover - compiled
    # Pass 1: R = N - sum floor(N w_j) and the total residual mass.
    n = weights.shape[0]
    kept = 0
    residual_total = 0.0
    for j in range(n):
        scaled = weights[j] * n
        whole = np.floor(scaled + _ROUNDING)
        kept += int(whole)
        residual_total += max(scaled - whole, 0.0)
    # Weights may sum to 1 +- SUM_TOLERANCE, so the floors may overshoot N
    # by a few; never write past the end.
    remaining = max(n - kept, 0)
    # Pass 2: floor(N w_j) copies of j, then j's share of the R multinomial
    # draws (uniform spacings over the residuals), so the output stays sorted.
    exponentials = rng.standard_exponential(remaining + 1)
    total = 0.0
    for i in range(remaining + 1):
        total += exponentials[i]
    scale = total / residual_total if residual_total > 0.0 else 0.0
    ancestors = np.empty(n, dtype=np.int64)
    k = 0
    drawn = 0
    point = exponentials[0]
    cumulative = 0.0
    for j in range(n):
        scaled = weights[j] * n
        whole = np.floor(scaled + _ROUNDING)
        for _ in range(min(int(whole), n - k)):
            ancestors[k] = j
            k += 1
        cumulative += max(scaled - whole, 0.0) * scale
        while drawn < remaining and k < n and point < cumulative:
            ancestors[k] = j
            k += 1
            drawn += 1
            point += exponentials[drawn]
    _fill_tail(ancestors, k, _last_positive(weights))
    return ancestors


def inverse_cdf(points, weights) -> np.ndarray:
    """Ancestors of sorted ``points`` in [0, 1): for each, the first i with cumsum(W)[i] > point.

    Parameters
    ----------
    points : (M,) array_like, non-decreasing, in [0, 1)
    weights : (N,) ndarray, normalised

    Notes
    -----
    The running sum can end a few ulps below 1; points in that gap go to
    the last particle with positive weight (the tail guard). Zero-weight
    particles are never chosen: the running sum does not grow across them.
    """
    return _inverse_cdf(np.ascontiguousarray(points, dtype=np.float64),
                        np.ascontiguousarray(weights, dtype=np.float64))


def _multinomial_ancestors(weights: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """M sorted i.i.d. draws from ``weights`` via ordered uniforms (Eq. 26).

    Eq. 26 builds the order statistics of M uniforms by the recursion
    u_M = v^(1/M), u_j = u_(j+1) v_j^(1/j). The same joint law comes from
    normalised partial sums of M + 1 standard exponentials ("uniform
    spacings"), which costs one exponential draw and one add per point
    instead of a log, a division and an exp; both are O(M). Measured at
    M = 1e6 by scripts/bench/resampling.py: see the README.
    """
    return _spacings(weights, rng.standard_exponential(m + 1))


def multinomial(weights, rng: np.random.Generator) -> np.ndarray:
    """Multinomial resampling: N i.i.d. draws from W, via ordered uniforms (Eq. 26)."""
    w = check_weights(weights)
    return _multinomial_ancestors(w, w.size, rng)


def stratified(weights, rng: np.random.Generator) -> np.ndarray:
    """Stratified resampling: one uniform in each stratum [(j-1)/N, j/N) (Eq. 27)."""
    w = check_weights(weights)
    return _stratified(w, rng.random(w.size))


def systematic(weights, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling (Kitagawa 1996): Eq. 27 with one uniform shared by all strata."""
    w = check_weights(weights)
    return _systematic(w, rng.random())


def residual(weights, rng: np.random.Generator) -> np.ndarray:
    """Residual resampling (Liu and Chen 1998).

    Particle i first gets floor(N w_i) copies; the R remaining offspring are
    drawn multinomially (Eq. 26) from the residual weights
    N w_i - floor(N w_i), normalised.
    """
    return _residual(check_weights(weights), rng)


#: Registry of the traditional schemes by name.
RESAMPLERS: dict[str, Resampler] = {
    "multinomial": multinomial,
    "stratified": stratified,
    "systematic": systematic,
    "residual": residual,
}


def get(name: str) -> Resampler:
    """The resampling scheme called ``name``, or a ValueError listing the valid names."""
    try:
        return RESAMPLERS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown resampler {name!r}; expected one of {', '.join(RESAMPLERS)}"
        ) from None
