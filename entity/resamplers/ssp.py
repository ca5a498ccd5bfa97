"""SSP resampling (Srinivasan sampling process; Gerber, Chopin and Whiteley 2019).

Particle i gets floor(N w_i) copies; the fractional parts f_i = N w_i - floor(N w_i), which add up to
the copies still to hand out, are settled by Srinivasan's (2001) process, taking the particles in
order. One particle is open; with the next one, j, and s = f_i + f_j:

- s < 1: one of the two takes s and stays open, j with probability f_j / s; the other is settled
  with no extra copy;
- s >= 1: one of the two is settled with an extra copy, j with probability (1 - f_i) / (2 - s); the
  other keeps s - 1 and stays open.

Each move keeps E[f_i] and E[f_j], so particle i has floor(N w_i) or floor(N w_i) + 1 offspring,
unbiased, with variance f_i (1 - f_i): the least of any unbiased integer count, and systematic
resampling's. Unlike systematic's, the counts are negatively associated, which makes the scheme
consistent whatever the order of the particles. (Srinivasan's rule in Gerber et al.'s form, moving
min(f_j, 1 - f_i) to i or min(f_i, 1 - f_j) to j, gives these moves; in survey sampling this is the
ordered pivotal method.)

Gerber M., Chopin N. and Whiteley N. (2019). Negative association, ordering and convergence of
resampling methods. Ann. Statist. 47(4), 2236-2260. Srinivasan A. (2001). Distributions on level-sets
with applications to approximation algorithms. FOCS 2001, 588-597. The negative association of this
linear process: Dubhashi D., Jonasson J. and Ranjan D. (2007). Positive influence and negative
dependence. Combin. Probab. Comput. 16(1), 29-41.
"""
from __future__ import annotations

import numba
import numpy as np

from dtpf.entity._merge import ROUNDING, _put
from dtpf.entity.resamplers.base import checked_weights, output_buffer
from dtpf.messages.family import RESAMPLERS

__all__ = ["ssp"]


@RESAMPLERS.builtin("ssp")
def ssp(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """SSP resampling (Gerber, Chopin and Whiteley 2019): floor(N w_i) or +1 copies, negatively associated.

    Draws ``rng.random(N - 1)``, one uniform per move of Srinivasan's process (see the module docstring).

    The weights are rescaled by their sum, so that the fractional parts add up to an integer (the check
    accepts sums within 1e-6 of 1); N w_i within 1e-9 below an integer counts as that integer, as in
    residual resampling (49 * (1/49) is 0.9999999999999999: equal weights give one copy each).
    """
    w = checked_weights(weights, checked)
    target = output_buffer(out, w.size)
    return _ssp(w, rng.random(w.size - 1), np.zeros(w.size, dtype=np.uint8), target)


@numba.njit(cache=True, nogil=True)
def _ssp(weights, uniforms, extra, out):  # pragma: no cover - compiled
    # Pass 1, the process: ``extra`` marks the particles settled with an extra copy. Written without
    # branches on the uniform: the open fraction is s - [s >= 1] whichever particle keeps it.
    n = weights.shape[0]
    scale = n / weights.sum()
    scaled = weights[0] * scale
    whole = np.floor(scaled + ROUNDING)
    fraction = max(scaled - whole, 0.0)
    copies = int(whole)
    i = 0
    for j in range(1, n):
        scaled = weights[j] * scale
        whole = np.floor(scaled + ROUNDING)
        f_j = max(scaled - whole, 0.0)
        copies += int(whole)
        s = fraction + f_j
        full = s >= 1.0
        share = (1.0 - fraction) if full else f_j  # j is picked with probability share / total
        total = (2.0 - s) if full else s
        pick_j = uniforms[j - 1] * total < share      # never for f_j = 0: a weight of 0 gains nothing
        extra[j if pick_j else i] = full              # the one settled full; else 0 on the one kept open
        copies += full
        i = j if pick_j != full else i
        fraction = s - full
    # The open particle holds the rounding error of the sums: a fraction of 0 or 1 up to it. The copy
    # still missing, if any, is its (only a particle of positive weight holds a positive fraction).
    missing = n - copies
    # Pass 2: the copies in particle order, so the ancestors come out sorted; never past N.
    k = 0
    for p in range(n):
        if k >= n:
            break
        count = int(np.floor(weights[p] * scale + ROUNDING)) + extra[p]
        if p == i and missing > 0:
            count += missing
        k = _put(out, k, min(k + count, n), p)
    return out
