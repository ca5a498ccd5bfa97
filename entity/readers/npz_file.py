"""NumPy archives (``np.savez``): observations, truth and time arrays (:mod:`dtpf.entity.observations`)."""
from __future__ import annotations

from dtpf.entity.observations import read_observations
from dtpf.messages.family import READERS

__all__ = ["read_npz"]


@READERS.builtin("npz")
def read_npz(source, *, obs_dim=None, state_dim=None, steps=None, topic=None, fields=None, model=None,
             partial=False):
    """A NumPy archive (np.savez) with arrays observations, truth and time."""
    return read_observations(source, obs_dim=obs_dim, state_dim=state_dim, steps=steps, kind=".npz")
