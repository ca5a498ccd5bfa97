"""Compiled kernels of :mod:`entity.resampling`: one pass over the weights each.

Every scheme merges sorted points with the running weight sum C_j and hands
particle j the points below C_j. Written as "while the next point is below
C_j, take it", the merge's loop exit depends on the data at every particle,
and at N = 1e6 the mispredicted branches cost three times the pass itself.
Here particle j first writes its index twice, unconditionally, at the next
two output positions k and k + 1 and then moves k to the end of its points;
a loop runs only from the third copy on. A particle with no point has its
two stores overwritten by the next particle with one (or by the tail guard),
so every position ends with the value the plain merge gives it: the same
numbers, from the same floating-point operations in the same order.

Outputs are written into a caller's (N,) int64 array, once per position
(plus the overwritten stores, in cache). Nothing here checks the weights;
:mod:`entity.resampling` does, once.
"""
from __future__ import annotations

import numba
import numpy as np

#: N w_i this close below an integer counts as that integer in residual
#: resampling: 49 * (1/49) is 0.9999999999999999 in float64, and equal
#: weights must give one copy each, not a multinomial draw.
ROUNDING = 1e-9


@numba.njit(inline="always")
def _put(out, k, end, j):  # pragma: no cover - compiled
    # j at out[k:end] (k < N), as two unconditional stores and a loop from the third copy; the new k.
    out[k] = j
    if k + 1 < out.shape[0]:
        out[k + 1] = j
    i = k + 2
    while i < end:
        out[i] = j
        i += 1
    return max(k, end)


@numba.njit(cache=True, nogil=True)
def fill_tail(ancestors, k, weights):  # pragma: no cover - compiled
    # Points past the running sum (it can end a few ulps below 1) go to the
    # last particle with positive weight: the tail guard.
    if k >= ancestors.shape[0]:
        return
    last = weights.shape[0] - 1
    for j in range(weights.shape[0] - 1, -1, -1):
        if weights[j] > 0.0:
            last = j
            break
    while k < ancestors.shape[0]:
        ancestors[k] = last
        k += 1


@numba.njit(cache=True, nogil=True)
def inverse_cdf(points, weights, out):  # pragma: no cover - compiled
    # One pass over the particles; each takes the given sorted points below its running sum.
    n = points.shape[0]
    cumulative = 0.0
    k = 0
    for j in range(weights.shape[0]):
        cumulative += weights[j]
        while k < n and points[k] < cumulative:
            out[k] = j
            k += 1
    fill_tail(out, k, weights)
    return out


@numba.njit(cache=True, nogil=True)
def _by_ends(weights, u, v, out):  # pragma: no cover - compiled
    # The merges whose points need no search: particle j's last point follows from the running sum
    # C_j. Systematic (v empty): points (k + u) / N, and point k < C_j <=> k < N C_j - u, so particle
    # j ends at ceil(N C_j - u). Stratified: point k is k + v_k on the scale N C_j (v_k in [0, 1), one
    # per stratum). With s = N C_j and m = floor(s), every point below m - 1 lies below s and every
    # point from m + 1 on above it, so particle j ends at m, less one if point m - 1 rounds up to s
    # (only when s is the integer m), plus one if point m is below s; the points are computed as the
    # plain merge computes them, float(k) + v_k.
    n = weights.shape[0]
    stratified = v.shape[0] == n
    cumulative = 0.0
    k = 0
    for j in range(n):
        if k >= n:
            break
        cumulative += weights[j]
        if stratified:
            scaled = cumulative * n
            m = min(max(int(scaled), 0), n)  # floor: scaled >= 0
            at = min(m, n - 1)
            end = m + int((m < n) & (at + v[at] < scaled))
            if scaled == m and m >= 1 and (m - 1) + v[m - 1] >= scaled:  # N C_j an integer: rare
                end -= 1
        else:
            end = min(n, int(np.ceil(cumulative * n - u)))
        k = _put(out, k, end, j)
    fill_tail(out, k, weights)
    return out


_NO_STRATA = np.empty(0)


def systematic(weights, u, out):
    """Systematic ancestors of ``weights`` with the uniform ``u``, into ``out``."""
    return _by_ends(weights, u, _NO_STRATA, out)


def stratified(weights, v, out):
    """Stratified ancestors of ``weights`` with the uniforms ``v`` (one per stratum), into ``out``."""
    return _by_ends(weights, 0.0, v, out)


@numba.njit(cache=True, nogil=True)
def multinomial(weights, rng, out):  # pragma: no cover - compiled
    # Sorted uniforms as normalised partial sums of M + 1 standard exponentials (Eq. 26, "uniform
    # spacings"), merged with the running sum scaled by the same total. The exponentials are drawn
    # here, as numpy's Generator draws standard_exponential(M + 1) (numba's port, the same numbers),
    # into ``out`` itself: position k is written only after point k has been added up.
    m = out.shape[0]
    spacings = out.view(np.float64)
    total = 0.0
    for i in range(m):
        e = rng.standard_exponential()
        spacings[i] = e
        total += e
    total += rng.standard_exponential()  # the (M + 1)-th, past the last point
    cumulative = 0.0
    point = spacings[0]
    k = 0
    for j in range(weights.shape[0]):
        cumulative += weights[j] * total
        while k < m and point < cumulative:
            following = spacings[k + 1] if k + 1 < m else 0.0
            out[k] = j
            k += 1
            point += following
    fill_tail(out, k, weights)
    return out


@numba.njit(cache=True, nogil=True)
def residual(weights, rng, out):  # pragma: no cover - compiled
    # Pass 1: R = N - sum floor(N w_j) and the total residual mass.
    n = weights.shape[0]
    kept = 0
    residual_total = 0.0
    for j in range(n):
        scaled = weights[j] * n
        whole = np.floor(scaled + ROUNDING)
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
    k = 0
    drawn = 0
    point = exponentials[0]
    cumulative = 0.0
    for j in range(n):
        if k >= n:
            break
        scaled = weights[j] * n
        whole = np.floor(scaled + ROUNDING)
        k = _put(out, k, min(k + int(whole), n), j)
        cumulative += max(scaled - whole, 0.0) * scale
        while drawn < remaining and k < n and point < cumulative:
            out[k] = j
            k += 1
            drawn += 1
            point += exponentials[drawn]
    fill_tail(out, k, weights)
    return out


@numba.njit(cache=True, nogil=True)
def distinct(ancestors):  # pragma: no cover - compiled
    # Distinct values of a non-decreasing array: 1 + the number of changes.
    changes = 0
    for i in range(1, ancestors.shape[0]):
        changes += ancestors[i] != ancestors[i - 1]
    return 1 + changes



@numba.njit(cache=True, nogil=True, parallel=True)
def gather_parallel(particles, ancestors, out):  # pragma: no cover - compiled
    # out[i] = particles[ancestors[i]] on numba's threads: the same array whatever their number.
    for i in numba.prange(ancestors.shape[0]):
        for c in range(particles.shape[1]):
            out[i, c] = particles[ancestors[i], c]
    return out
