"""Systematic resampling (Kitagawa 1996): one uniform shared by all N strata."""
from __future__ import annotations

import numpy as np

from dtpf.entity import _merge
from dtpf.entity.resamplers.base import output_buffer, checked_weights
from dtpf.messages.family import RESAMPLERS

__all__ = ["systematic"]


@RESAMPLERS.builtin("systematic")
def systematic(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Systematic resampling (Kitagawa 1996): Eq. 27 with one uniform shared by all strata; draws ``rng.random()``."""
    w = checked_weights(weights, checked)
    return _merge.systematic(w, rng.random(), output_buffer(out, w.size))
