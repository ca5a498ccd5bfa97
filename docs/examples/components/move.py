"""A move after resampling of your own: ``moved = move(resampled, particles, weights, rng)``.

    dtpf run --scenario drift --move docs/examples/components/move.py:gaussian_shake
"""
import numpy as np

#: The noise's standard deviation, as a fraction of the weighted set's.
FRACTION = 0.1


def gaussian_shake(resampled, particles, weights, rng):
    """Add Gaussian noise whose standard deviation per component is FRACTION of the weighted set's."""
    mean = weights @ particles
    spread = np.sqrt(weights @ (particles - mean) ** 2)
    return resampled + rng.standard_normal(resampled.shape) * (FRACTION * spread)
