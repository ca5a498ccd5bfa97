"""Processed particles keep their weights: the paper moves positions only."""
from __future__ import annotations

import numpy as np

from dtpf.messages.names import WEIGHT_RULE_REGISTRY

__all__ = ["inherit"]


@WEIGHT_RULE_REGISTRY.builtin("inherit")
def inherit(weights: np.ndarray, threshold: float, particles: np.ndarray, moved: np.ndarray,
            log_likelihood=None) -> np.ndarray:
    """Keep the old weights: the paper moves positions only."""
    kept = weights.view()  # unchanged: a read-only view, not a copy
    kept.flags.writeable = False
    return kept
