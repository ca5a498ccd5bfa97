"""Killing resampling: each particle survives with probability w_i / max_j w_j, else a multinomial draw.

Particle i is kept (one copy of itself) when U_i < w_i / m, m = max_j w_j, U_i uniform; the K particles
killed are replaced by K i.i.d. draws from the weights (Eq. 26). The offspring count of i is
B_i + M_i with B_i ~ Bernoulli(p_i), p_i = w_i / m, and M_i ~ Binomial(K, w_i) given K, so

    E[B_i + M_i] = p_i + (N - 1/m) w_i = N w_i                                  (unbiased)
    Var[B_i + M_i] = N w_i (1 - w_i) - w_i^2 (sum_j p_j^2 + (1 - 2 w_i) / m^2)

(from Var B_i = p_i (1 - p_i), Var K = sum_j p_j (1 - p_j), Cov(B_i, M_i) = -w_i p_i (1 - p_i)): at
most the multinomial variance N w_i (1 - w_i), since sum_j p_j^2 >= 1 and w_i <= m. Equal weights keep
every particle. It is the selection of Del Moral's Feynman-Kac particle models with potentials
G_i = w_i / m <= 1: a particle is killed with probability 1 - G_i and replaced by one drawn in
proportion to G (Del Moral P. (2004). Feynman-Kac Formulae: Genealogical and Interacting Particle
Systems with Applications. Springer), as the ``particles`` library's ``resampling.killing`` offers it.
"""
from __future__ import annotations

import numba
import numpy as np

from dtpf.entity import _merge
from dtpf.entity.resamplers.base import checked_weights, exponential_merge, output_buffer
from dtpf.messages.family import RESAMPLERS

__all__ = ["killing"]


@RESAMPLERS.builtin("killing")
def killing(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Killing resampling (Del Moral 2004): each particle survives with probability w_i / max w, else a draw.

    The killed are replaced by multinomial draws from W. Draws ``rng.random(N)``, then
    ``rng.standard_exponential(K + 1)`` for the K killed (their sorted uniforms as normalised partial
    sums, Eq. 26, as multinomial's).

    The survivors (in order) and the K draws (sorted) are merged, so the ancestors come out sorted.
    """
    w = checked_weights(weights, checked)
    n = w.size
    target = output_buffer(out, n)
    survivors = np.empty(n + 1, dtype=np.int64)
    kept = _survivors(w, rng.random(n), survivors)
    drawn = np.empty(n - kept + 1, dtype=np.int64)
    exponential_merge(w, rng, drawn[:-1], _merge.multinomial, _merge.multinomial_pcg)
    drawn[-1] = n  # past every ancestor, as survivors[kept]
    return _merge_sorted(survivors, drawn, target)


@numba.njit(cache=True, nogil=True)
def _survivors(weights, uniforms, survivors):  # pragma: no cover - compiled
    # The particles kept, u_i < w_i / max w, in order, then N; their number. A weight of max w is kept
    # (u < 1), one of 0 never.
    top = weights.max()
    kept = 0
    for i in range(weights.shape[0]):
        survivors[kept] = i
        kept += uniforms[i] < weights[i] / top
    survivors[kept] = weights.shape[0]
    return kept


@numba.njit(cache=True, nogil=True)
def _merge_sorted(first, second, out):  # pragma: no cover - compiled
    # The two sorted lists, each ending with a value above all others, merged into ``out``.
    a = 0
    b = 0
    for k in range(out.shape[0]):
        x, y = first[a], second[b]
        take_first = x <= y
        out[k] = x if take_first else y
        a += take_first
        b += not take_first
    return out
