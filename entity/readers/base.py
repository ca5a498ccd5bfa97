"""The contract of an observation reader, and the checks a user's reader passes.

A reader turns the text of ``--observations`` (a file, a folder, a device: the reader decides) into the
observations to filter, one row per step::

    table = reader(source, *, obs_dim=None, state_dim=None, steps=None, topic=None, fields=None, model=None,
                   partial=False)

Parameters
----------
source : str
    What ``--observations`` gave, as given.
obs_dim, state_dim : int or None
    The model's m and d: the table must have m observation columns and truth of at most d columns.
steps : int or None
    Read at most this many rows (None: all).
topic, fields, model :
    A rosbag2 log's topic and field paths (``--topic``, ``--ros2-fields``) and the run's model; readers
    that have no use for them ignore them.
partial : bool
    ``--partial``: read what is intact of a damaged file and say what was skipped (the table's
    ``problem``), instead of refusing it; a reader that cannot tell ignores it.

Returns
-------
:class:`~dtpf.entity.observations.ObservationTable`: observations (T, m) finite float64, optional truth,
times and integer-nanosecond stamps.

A user's reader is simpler: ``read(source)`` (or ``read(source, steps=None)``) returning the observations,
``(T, m)`` or ``(T,)``, or a dict with ``observations`` and optional ``truth`` (``(T, d)``), ``times``
(``(T,)`` seconds) and ``stamps`` (``(T,)`` int64 nanoseconds), or an ObservationTable. :func:`adapt`
puts it in the contract's form: it keeps the first ``steps`` rows, checks every value is finite and the
columns fit the model, and names what is wrong in one line (an
:class:`~dtpf.entity.observations.ObservationError`, exit 2).
"""
from __future__ import annotations

import os

import numpy as np

from dtpf.entity.observations import ObservationError, ObservationTable
from dtpf.messages import references
from dtpf.messages.family import READERS
from dtpf.messages.references import a

__all__ = ["READERS", "adapt"]


def adapt(obj, where: str):
    """A user's reader in the contract's form."""
    signature = references.function_of(obj, where, "a reader", "read(source) -> observations", ("source",))
    takes_steps = signature.takes("steps")
    return _Checked(obj, where, takes_steps)


class _Checked:
    """A user's ``read(source)`` in the contract's form, its result checked and made a table."""

    def __init__(self, function, where: str, takes_steps: bool):
        self.function, self.where, self.takes_steps = function, where, takes_steps
        self.__name__ = getattr(function, "__name__", "reader")
        self.__doc__ = getattr(function, "__doc__", None)

    def __call__(self, source, *, obs_dim=None, state_dim=None, steps=None, topic=None, fields=None,
                 model=None, partial=False) -> ObservationTable:
        source = os.fsdecode(source)
        try:
            result = self.function(source, steps=steps) if self.takes_steps else self.function(source)
        except ObservationError:
            raise
        except Exception as exc:
            raise ObservationError(f"{self.where} raised {type(exc).__name__}: {exc}", source=source) from exc
        table = result if isinstance(result, ObservationTable) else self._table(result, source)
        table = table.head(steps)
        if not np.isfinite(table.observations).all():
            row = int(np.flatnonzero(~np.isfinite(table.observations).all(axis=1))[0])
            raise ObservationError(f"{self.where} returned a value that is not finite at row {row + 1}",
                                   source=source)
        if obs_dim is not None and table.observations.shape[1] != obs_dim:
            raise ObservationError(f"{self.where} returned {table.observations.shape[1]} observation columns; "
                                   f"the model observes {obs_dim}", source=source)
        if state_dim is not None and table.truth is not None and table.truth.shape[1] > state_dim:
            raise ObservationError(f"{self.where} returned truth of {table.truth.shape[1]} columns; the model's "
                                   f"state has {state_dim}", source=source)
        return table

    def _table(self, result, source: str) -> ObservationTable:
        parts = dict(result) if isinstance(result, dict) else {"observations": result}
        unknown = sorted(set(parts) - {"observations", "truth", "times", "stamps"})
        if unknown or "observations" not in parts:
            raise ObservationError(f"{self.where} returned a dict with keys {sorted(parts)}; expected "
                                   f"'observations' and optionally 'truth', 'times', 'stamps'", source=source)
        try:
            z = np.asarray(parts["observations"], dtype=np.float64)
            z = z[:, None] if z.ndim == 1 else z
            truth = parts.get("truth")
            if truth is not None:
                truth = np.asarray(truth, dtype=np.float64)
                truth = truth[:, None] if truth.ndim == 1 else truth
            times = None if parts.get("times") is None else np.asarray(parts["times"], dtype=np.float64)
            stamps = parts.get("stamps")
            if stamps is not None:
                stamps = np.asarray(stamps)
                if not np.issubdtype(stamps.dtype, np.integer):
                    raise ValueError(f"stamps must be integer nanoseconds, got {stamps.dtype}")
            return ObservationTable(
                observations=z, truth=truth, times=times, stamps=stamps,
                columns=tuple(f"z{j}" for j in range(z.shape[1]) if z.ndim == 2),
                truth_columns=() if truth is None else tuple(f"x{j}" for j in range(truth.shape[1])),
                source=source)
        except (TypeError, ValueError, IndexError) as exc:
            raise ObservationError(f"{self.where} returned {a(result)} that is not a table of observations: "
                                   f"{exc}", source=source) from None
