"""Stratified resampling: one uniform in each of N strata (Eq. 27)."""
from __future__ import annotations

import numpy as np

from dtpf.entity import _merge
from dtpf.entity.resamplers.base import output_buffer, checked_weights
from dtpf.messages.family import RESAMPLERS

__all__ = ["stratified"]


@RESAMPLERS.builtin("stratified")
def stratified(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Stratified resampling: one uniform in each stratum [(j-1)/N, j/N) (Eq. 27); draws ``rng.random(N)``."""
    w = checked_weights(weights, checked)
    out = output_buffer(out, w.size)
    words = _merge.pcg_state(rng)
    if words is None:
        return _merge.stratified(w, rng.random(w.size), out)
    _merge.stratified_pcg(w, words, out)  # draws the uniforms as it merges, from a copy of the state
    rng.bit_generator.advance(w.size)  # where rng.random(N) leaves the PCG64
    return out
