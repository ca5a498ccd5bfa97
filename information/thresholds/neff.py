"""W from the effective sample size (the paper: "W is usually selected as the N_eff value")."""
from __future__ import annotations

import numpy as np

from dtpf.information.select import kth_largest
from dtpf.information.thresholds.base import Split
from dtpf.messages.family import THRESHOLDS

__all__ = ["neff", "order"]


def order(weights: np.ndarray) -> tuple[int, int]:
    """(the ascending rank of W among the weights, k): with k = round(1 / sum w^2) (Eq. 25) clipped to
    [1, N], W is the (k+1)-th largest weight; rank -1 and capacity N when k = N (W = 0)."""
    n = weights.size
    k = min(max(round(1.0 / float(np.dot(weights, weights))), 1), n)
    return (n - k - 1, k) if k < n else (-1, n)


@THRESHOLDS.builtin("neff")
def neff(weights: np.ndarray) -> Split:
    """The (k+1)-th largest weight with k = round(ESS), so k particles are large: the paper's reading.

    With k = round(1 / sum w^2) (Eq. 25) clipped to [1, N], W is the (k+1)-th largest weight and k
    particles are large (ties at W count as small). With k = N every positive weight is large: W = 0.
    """
    rank, k = order(weights)
    return Split(0.0 if rank < 0 else kth_largest(weights, weights.size - rank), k)


neff.order = order
