"""W = 1/N, the weight of every particle of an evenly weighted set."""
from __future__ import annotations

import numpy as np

from dtpf.information.thresholds.base import Split
from dtpf.messages.family import THRESHOLDS

__all__ = ["inverse_n"]


@THRESHOLDS.builtin("inverse-n")
def inverse_n(weights: np.ndarray) -> Split:
    """1/N: particles heavier than an even share are large."""
    n = weights.size
    return Split(1.0 / n, n)
