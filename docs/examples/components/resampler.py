"""A resampler of your own, in the form textbooks use: ``ancestors = f(weights, rng)``.

    dtpf run --resampler docs/examples/components/resampler.py:systematic_numpy

dtpf tries it on a small case before the run (offspring counts against the weights over a few thousand
draws) and checks what it returns at every step.
"""
import numpy as np


def systematic_numpy(weights, rng):
    """Systematic resampling in plain numpy: one uniform shared by N evenly spaced points."""
    n = len(weights)
    points = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(np.cumsum(weights), points, side="right"), n - 1)


def greedy(weights, rng):
    """Every new particle a copy of the heaviest: biased, so dtpf refuses it."""
    return np.full(len(weights), int(np.argmax(weights)))
