"""NumPy arrays (``np.save``): the observations, (T, m) or (T,) (:mod:`dtpf.entity.observations`)."""
from __future__ import annotations

from dtpf.entity.observations import read_observations
from dtpf.messages.family import READERS

__all__ = ["read_npy"]


@READERS.builtin("npy")
def read_npy(source, *, obs_dim=None, state_dim=None, steps=None, topic=None, fields=None, model=None,
             partial=False):
    """A NumPy array file (np.save): the observations, one row per step."""
    return read_observations(source, obs_dim=obs_dim, state_dim=state_dim, steps=steps, kind=".npy")
