"""The weight of a moved particle re-evaluated at its new position (not the paper's)."""
from __future__ import annotations

import numpy as np

from dtpf.messages.names import WEIGHT_RULE_REGISTRY

__all__ = ["likelihood"]


@WEIGHT_RULE_REGISTRY.builtin("likelihood")
def likelihood(weights: np.ndarray, threshold: float, particles: np.ndarray, moved: np.ndarray,
               log_likelihood) -> np.ndarray:
    """Re-evaluate the likelihood at the new position: w_l p(z | new x_l) / p(z | old x_l), renormalised.

    A particle whose weight underflowed to exactly 0 stays at 0.
    """
    with np.errstate(divide="ignore"):
        log_w = np.log(weights)
    small = np.flatnonzero(weights <= threshold)
    log_small = log_w[small]
    delta = log_likelihood(moved[small]) - log_likelihood(particles[small])
    log_w[small] = np.where(np.isneginf(log_small), -np.inf, log_small + delta)
    new_weights = np.exp(log_w - log_w.max())
    new_weights /= new_weights.sum()
    return new_weights


likelihood.needs_likelihood = True
