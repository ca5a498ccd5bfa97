"""CSV files: a header naming the columns, one row per step (:mod:`dtpf.entity.observations`)."""
from __future__ import annotations

from dtpf.entity.observations import read_observations
from dtpf.messages.family import READERS

__all__ = ["read_csv"]


@READERS.builtin("csv")
def read_csv(source, *, obs_dim=None, state_dim=None, steps=None, topic=None, fields=None, model=None,
             partial=False):
    """A CSV file with a header line: observation, truth and time columns by their names."""
    return read_observations(source, obs_dim=obs_dim, state_dim=state_dim, steps=steps, kind=".csv")
