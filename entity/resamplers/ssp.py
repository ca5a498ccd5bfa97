"""SSP resampling (Srinivasan sampling process; Gerber, Chopin and Whiteley 2019).

Particle i gets floor(N w_i) copies, and the fractional parts f_i = N w_i - floor(N w_i), which sum to
the R copies still to hand out, are settled two at a time by Srinivasan's (2001) sampling process: of
the two open particles i and j, with a = min(f_j, 1 - f_i) and b = min(f_i, 1 - f_j), i gains a and j
loses it with probability b / (a + b), otherwise j gains b and i loses it. Each move keeps E[f_i] and
settles one of the two at 0 or 1 (1: one more copy); the next particle takes its place. So particle i
has floor(N w_i) or floor(N w_i) + 1 offspring, unbiased, with variance f_i (1 - f_i), the smallest of
any unbiased integer count and systematic resampling's; unlike systematic, the counts are negatively
associated, which makes the scheme consistent whatever the order of the particles.

Gerber M., Chopin N. and Whiteley N. (2019). Negative association, ordering and convergence of
resampling methods. Ann. Statist. 47(4), 2236-2260. Srinivasan A. (2001). Distributions on level-sets
with applications to approximation algorithms. FOCS 2001, 588-597. The negative association of this
linear process: Dubhashi D., Jonasson J. and Ranjan D. (2007). Positive influence and negative
dependence. Combin. Probab. Comput. 16(1), 29-41.
"""
from __future__ import annotations

import numba
import numpy as np

from dtpf.entity._merge import ROUNDING
from dtpf.entity.resamplers.base import checked_weights, output_buffer
from dtpf.messages.family import RESAMPLERS

__all__ = ["ssp"]


@RESAMPLERS.builtin("ssp")
def ssp(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """SSP resampling (Gerber, Chopin and Whiteley 2019): floor(N w_i) or floor(N w_i) + 1 copies of each
    particle, negatively associated; draws ``rng.random(N - 1)``.

    The weights are rescaled by their sum, so that the fractional parts add up to an integer (the check
    accepts sums within 1e-6 of 1); N w_i within 1e-9 below an integer counts as that integer, as in
    residual resampling (49 * (1/49) is 0.9999999999999999: equal weights give one copy each).
    """
    w = checked_weights(weights, checked)
    target = output_buffer(out, w.size)
    return _ssp(w, rng.random(w.size - 1), target)


@numba.njit(cache=True, nogil=True)
def _ssp(weights, uniforms, out):  # pragma: no cover - compiled
    # Pass 1: the integer parts into ``copies``, the fractional parts into ``fraction``.
    n = weights.shape[0]
    scale = n / weights.sum()
    copies = np.empty(n, dtype=np.int64)
    fraction = np.empty(n)
    for k in range(n):
        scaled = weights[k] * scale
        whole = np.floor(scaled + ROUNDING)
        copies[k] = int(whole)
        fraction[k] = max(scaled - whole, 0.0)
    # Pass 2: Srinivasan's process on the open pair (i, j); the particle settled by move k is replaced
    # by particle k + 2. A particle of fraction 0 never gains (a or b is 0, and the uniform is below 1).
    i, j = 0, 1
    for k in range(n - 1):
        gain_i = min(fraction[j], 1.0 - fraction[i])
        gain_j = min(fraction[i], 1.0 - fraction[j])
        total = gain_i + gain_j
        if total > 0.0 and uniforms[k] < gain_i / total:  # j gains: swap the roles, so that i gains
            i, j = j, i
            gain_i = gain_j
        if fraction[j] < 1.0 - fraction[i]:  # j is spent: settled with no extra copy
            fraction[i] += gain_i
            j = k + 2
        else:  # i is full: settled with one extra copy
            fraction[j] -= gain_i
            copies[i] += 1
            i = k + 2
    # The particle left open holds the rounding error of the sums: a fraction of 0 or 1 up to it. The copies
    # still missing (0 or 1) go to it; a fraction near 1 is only ever held by a particle of positive weight.
    last = j if i == n else i
    missing = n - copies.sum()
    if missing > 0:
        copies[last] += missing
    # Pass 3: the copies in particle order, so the ancestors are sorted; never past N.
    k = 0
    for particle in range(n):
        end = min(k + copies[particle], n)
        while k < end:
            out[k] = particle
            k += 1
    return out
