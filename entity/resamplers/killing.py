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

from dtpf.entity._merge import fill_tail
from dtpf.entity.resamplers.base import checked_weights, output_buffer
from dtpf.messages.family import RESAMPLERS

__all__ = ["killing"]


@RESAMPLERS.builtin("killing")
def killing(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Killing resampling: particle i survives with probability w_i / max w, each killed one is replaced by
    a multinomial draw (Del Moral 2004); draws ``rng.random(N)``, then ``rng.standard_exponential(K + 1)``
    for the K killed (their sorted uniforms as normalised partial sums, Eq. 26).

    The survivors and the draws are merged particle by particle, so the ancestors come out sorted.
    """
    w = checked_weights(weights, checked)
    target = output_buffer(out, w.size)
    kept = rng.random(w.size) < w / w.max()
    killed = w.size - int(np.count_nonzero(kept))
    return _killing(w, kept, rng.standard_exponential(killed + 1), target)


@numba.njit(cache=True, nogil=True)
def _killing(weights, kept, exponentials, out):  # pragma: no cover - compiled
    # Particle j writes itself if it survived, then the sorted points below its running sum: the
    # uniform spacings, partial sums of the exponentials, against the running sum times their total.
    draws = exponentials.shape[0] - 1
    total = exponentials.sum()
    point = exponentials[0]
    cumulative = 0.0
    k = 0
    drawn = 0
    for j in range(weights.shape[0]):
        if kept[j]:
            out[k] = j
            k += 1
        cumulative += weights[j] * total
        while drawn < draws and point < cumulative:
            out[k] = j
            k += 1
            drawn += 1
            point += exponentials[drawn]
    fill_tail(out, k, weights)  # draws past a running sum that ends a few ulps below 1
    return out
