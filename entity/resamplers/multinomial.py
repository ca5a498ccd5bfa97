"""Multinomial resampling: N i.i.d. draws from the weights (Eq. 26)."""
from __future__ import annotations

import numpy as np

from dtpf.entity import _merge
from dtpf.entity.resamplers.base import exponential_merge, output_buffer, checked_weights
from dtpf.messages.family import RESAMPLERS

__all__ = ["multinomial"]


@RESAMPLERS.builtin("multinomial")
def multinomial(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Multinomial resampling: N i.i.d. draws from W, via ordered uniforms (Eq. 26).

    Eq. 26 builds the order statistics of M uniforms by the recursion
    u_M = v^(1/M), u_j = u_(j+1) v_j^(1/j). The same joint law comes from
    normalised partial sums of M + 1 standard exponentials ("uniform
    spacings"), which costs one exponential draw and one add per point
    instead of a log, a division and an exp; both are O(M). The draws are
    ``rng.standard_exponential(N + 1)``'s, made in the compiled pass.
    """
    w = checked_weights(weights, checked)
    return exponential_merge(w, rng, output_buffer(out, w.size), _merge.multinomial, _merge.multinomial_pcg)
