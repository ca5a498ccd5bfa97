"""A driven twin's files: one observation file per sensor and a control file, put in one stamp-ordered run.

::

    dtpf run --model docs/examples/unicycle.py:Unicycle \\
        --observations gps=gps.csv --observations beacons=beacons.csv --controls odometry.csv

Every file has a time column (``time``, ``t``, ``timestamp`` or ``stamp``: seconds, read from the text to
the nanosecond) and is in time order. A sensor's file holds its observation columns (as many as the model's
``sensors`` gives it) and optionally truth columns (``truth_*``); the control file holds the model's
``controls``, by name when its header has them, else every other column in order. Each row of every sensor
file is one filter step; the steps are in stamp order, a stamp shared by several sensors taken in the order
of the model's ``sensors``. :mod:`dtpf.entity.timeline` makes each step's drive (dt and the controls held
over it). A model of one unnamed sensor whose ``propagate`` takes ``dt`` reads its one file the same way.

Mistakes are one line (:class:`~dtpf.entity.observations.ObservationError`): a file without a time column,
one of the wrong width for its sensor, an unknown sensor name, a control file of the wrong width, a driven
model without its control file.
"""
from __future__ import annotations

import numpy as np

from dtpf.entity.calls import ModelCalls
from dtpf.entity.observations import ObservationError, ObservationTable, read_observations
from dtpf.entity.timeline import Drive, TimeError, Timeline

__all__ = ["StampedRun", "read_stamped", "sensor_sources", "rows"]


class StampedRun:
    """The steps of a driven run in stamp order.

    Attributes
    ----------
    observations : (T, M) ndarray
        Each step's observation, its sensor's values first, NaN after them (M: the widest sensor).
    sensors : tuple
        Each step's sensor (None for a model of one unnamed sensor).
    stamps : (T,) int64 ndarray
        Each step's time, ns.
    drives : list of Drive or None
        How each step is reached from the one before (None for the first).
    truth, truth_components, truth_columns :
        The truth of each step, when every sensor file has the same truth columns; else None.
    source : str
        The files, for messages.
    """

    def __init__(self, observations, sensors, stamps, drives, truth, truth_components, truth_columns, source):
        self.observations, self.sensors, self.stamps, self.drives = observations, sensors, stamps, drives
        self.truth, self.truth_components, self.truth_columns = truth, truth_components, truth_columns
        self.source = source


def sensor_sources(config, calls: ModelCalls) -> dict:
    """Sensor name -> file of the run: its ``sensor_files``, or its one ``observations`` file for the model's
    one sensor; ObservationError names a sensor the model does not have or one without a file."""
    files = dict(getattr(config, "sensor_files", None) or {})
    known = [name for name in calls.sensors if name is not None]
    if not files:
        if calls.named_sensors and len(known) > 1:
            raise ObservationError(f"the model has sensors {', '.join(known)}: give each its file with "
                                   f"--observations NAME=FILE")
        return {known[0] if calls.named_sensors else None: config.observation_file}
    if not calls.named_sensors:
        raise ObservationError(f"--observations {next(iter(files))}=...: the model has one sensor, unnamed; give "
                               f"--observations FILE")
    unknown = [name for name in files if name not in calls.sensors]
    if unknown:
        raise ObservationError(f"--observations {unknown[0]}=...: the model has no sensor {unknown[0]!r}; its "
                               f"sensors are {', '.join(known)}")
    return {name: files[name] for name in known if name in files}


def read_stamped(config, model, *, steps: int | None = None, calls: ModelCalls | None = None) -> StampedRun:
    """Read the run's sensor files and control file into :class:`StampedRun` (module docstring); at most
    ``steps`` steps."""
    calls = calls if calls is not None else ModelCalls(model)
    sources = sensor_sources(config, calls)
    tables: dict = {}
    for name, path in sources.items():
        tables[name] = read_observations(path, obs_dim=calls.sensors[name], state_dim=model.dim,
                                         exact_stamps=True)
    events = sorted((int(stamp), rank, row, name)
                    for rank, (name, table) in enumerate(tables.items())
                    for row, stamp in enumerate(table.stamps))
    if steps is not None:
        events = events[:steps]
    timeline = Timeline(len(calls.controls), piecewise=calls.takes_dt)
    control_file = getattr(config, "controls", None)
    if control_file is not None:
        if not calls.controls:
            raise ObservationError(f"--controls {control_file}: the model takes no control input (its controls "
                                   f"are empty)")
        stamps, values = read_controls(control_file, calls.controls)
        for stamp, u in zip(stamps, values):
            timeline.control(int(stamp), u)
    elif calls.controls:
        raise ObservationError(f"the model is driven by controls ({', '.join(calls.controls)}): give them with "
                               f"--controls FILE")
    width = max(calls.sensors[name] for name in tables)
    observations = np.full((len(events), width), np.nan)
    drives: list[Drive | None] = []
    for i, (stamp, _, row, name) in enumerate(events):
        z = tables[name].observations[row]
        observations[i, :z.size] = z
        try:
            drives.append(timeline.step(stamp))
        except TimeError as error:  # pragma: no cover - the events are sorted
            raise ObservationError(str(error)) from None
    truth, components, columns = _truth(tables, events)
    observations.flags.writeable = False
    return StampedRun(observations, tuple(name for _, _, _, name in events),
                      np.array([stamp for stamp, _, _, _ in events], dtype=np.int64), drives, truth, components,
                      columns, ", ".join(str(path) for path in sources.values()))


def rows(config) -> int:
    """The number of steps in the run's sensor files (the sum of their rows), without the model."""
    return sum(read_observations(path).steps for path in (config.sensor_files or {}).values())


def read_controls(path, controls: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The control file's stamps (ns) and values (C, c): the columns named as ``controls`` when its header has
    them all, else every observation column in order (which must be c of them)."""
    table: ObservationTable = read_observations(path, exact_stamps=True)
    names = list(table.columns)
    if all(name in names for name in controls):
        values = table.observations[:, [names.index(name) for name in controls]]
    elif len(names) == len(controls):
        values = table.observations
    else:
        raise ObservationError(f"{path}: {len(names)} control columns ({', '.join(names)}), the model's control "
                               f"has {len(controls)} ({', '.join(controls)})", source=str(path))
    return table.stamps, np.ascontiguousarray(values)


def _truth(tables: dict, events: list):
    """The truth of each step when every file has truth of the same components, else (None, (), ())."""
    first = next(iter(tables.values()))
    if any(t.truth is None or t.truth_components != first.truth_components for t in tables.values()):
        return None, (), ()
    truth = np.array([tables[name].truth[row] for _, _, row, name in events])
    return truth.reshape(len(events), len(first.truth_components)), first.truth_components, first.truth_columns
