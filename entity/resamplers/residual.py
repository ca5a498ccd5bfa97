"""Residual resampling (Liu and Chen 1998): the integer parts, then multinomial on the residuals."""
from __future__ import annotations

import numpy as np

from dtpf.entity import _merge
from dtpf.entity.resamplers.base import exponential_merge, output_buffer, checked_weights
from dtpf.messages.family import RESAMPLERS

__all__ = ["residual"]


@RESAMPLERS.builtin("residual")
def residual(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Residual resampling (Liu and Chen 1998).

    Particle i first gets floor(N w_i) copies; the R remaining offspring are
    drawn multinomially (Eq. 26) from the residual weights
    N w_i - floor(N w_i), normalised; draws ``rng.standard_exponential(R + 1)``.
    """
    w = checked_weights(weights, checked)
    return exponential_merge(w, rng, output_buffer(out, w.size), _merge.residual, _merge.residual_pcg)
