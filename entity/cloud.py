"""The particle set of a step as a point cloud to look at (Foxglove's 3D panel).

A viewer needs the shape of the posterior, not every particle: at most ``cap``
points are drawn, every ``ceil(N / cap)``-th particle in index order. The
particles of a set are exchangeable (propagation treats them alike), so a
stride is a fair sample of the cloud; their weights come along. Each point is
four float64: x, y, z and weight, where a 1-D state is drawn as (x, w * N, 0)
(the relative weight as height: 1 is the mean weight), a 2-D state as
(x0, x1, 0) and a state of 3 or more dimensions by its first three.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["cloud_points", "FIELDS", "POINT_STRIDE"]

#: The fields of a point: name and byte offset (all float64).
FIELDS = (("x", 0), ("y", 8), ("z", 16), ("weight", 24))
#: Bytes per point.
POINT_STRIDE = 32


def cloud_points(particles: np.ndarray, weights: np.ndarray, cap: int) -> np.ndarray:
    """(K, 4) float64 points (x, y, z, weight) of at most ``cap`` particles, K = ceil(N / stride)."""
    n, d = particles.shape
    stride = max(1, math.ceil(n / cap))
    chosen = particles[::stride]
    w = weights[::stride]
    points = np.zeros((chosen.shape[0], 4), dtype=np.float64)
    if d == 1:
        points[:, 0] = chosen[:, 0]
        points[:, 1] = w * n
    else:
        points[:, : min(d, 3)] = chosen[:, :3]
    points[:, 3] = w
    return points
