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

The sensors may also share one CSV file with a ``sensor`` column naming each row's sensor, its values in the
columns after it (a sensor with fewer values than the widest leaves the rest of its row empty)::

    time,sensor,z0,z1,z2
    0.100,beacons,30.19,31.44,29.15
    1.000,gps,-1.58,-1.02,
    1.000,beacons,29.63,31.81,30.41

Its rows may be out of order by up to the run's ``reorder_window`` seconds: they are put in stamp order, as
a live twin does (:class:`~dtpf.entity.timeline.Reorder`); a row older than that is counted, skipped and
named in the run's note.

Mistakes are one line (:class:`~dtpf.entity.observations.ObservationError`): a file without a time column,
one of the wrong width for its sensor, an unknown sensor name, a control file of the wrong width, a driven
model without its control file.
"""
from __future__ import annotations

import numpy as np

from dtpf.entity import topics
from dtpf.entity.calls import ModelCalls
from dtpf.entity.observations import MAX_LINE_CHARS, ObservationError, ObservationTable, read_observations
from dtpf.entity.timeline import Drive, TimeError, Timeline

__all__ = ["StampedRun", "read_stamped", "sensor_sources", "rows", "has_sensor_column"]


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
        #: What was skipped (rows of a shared CSV later than the reorder window), or None.
        self.problem = None


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
    if not getattr(config, "sensor_files", None) and calls.named_sensors and has_sensor_column(
            config.observation_file):
        return _read_sensor_column(config, model, calls, steps)
    sources = sensor_sources(config, calls)
    tables: dict = {}
    for name, path in sources.items():
        bag = topics.bag_topic(path)  # a rosbag2 bag's topic, BAG:/TOPIC
        if bag is not None:
            tables[name] = topics.read_sensor(bag, name, config, obs_dim=calls.sensors[name], state_dim=model.dim,
                                              model=model)
            continue
        tables[name] = read_observations(path, obs_dim=calls.sensors[name], state_dim=model.dim,
                                         exact_stamps=True)
    events = sorted((int(stamp), rank, row, name)
                    for rank, (name, table) in enumerate(tables.items())
                    for row, stamp in enumerate(table.stamps))
    if steps is not None:
        events = events[:steps]
    problems = [table.problem for table in tables.values() if getattr(table, "problem", None)]
    return _assemble(config, model, calls, tables, events, ", ".join(str(path) for path in sources.values()),
                     "; ".join(problems) or None)


def _assemble(config, model, calls, tables, events, source, problem=None) -> StampedRun:
    """Steps in the order of ``events`` ((stamp, rank, row, sensor) of ``tables``), with their drives."""
    timeline = Timeline(len(calls.controls), piecewise=calls.takes_dt)
    control_file = getattr(config, "controls", None)
    if control_file is not None:
        if not calls.controls:
            raise ObservationError(f"--controls {control_file}: the model takes no control input (its controls "
                                   f"are empty)")
        bag = topics.bag_topic(control_file)
        if bag is not None:  # a rosbag2 bag's topic: what a damaged one skipped is said with the run
            stamps, values, skipped = topics.read_control(bag, calls.controls, getattr(config, "control_fields", None),
                                                          bool(getattr(config, "partial", False)))
            problem = "; ".join(filter(None, [problem, skipped])) or None
        else:
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
    run = StampedRun(observations, tuple(name for _, _, _, name in events),
                     np.array([stamp for stamp, _, _, _ in events], dtype=np.int64), drives, truth, components,
                     columns, source)
    run.problem = problem
    return run


def has_sensor_column(path) -> bool:
    """Whether ``path`` is a CSV file whose header (its first line that is not a comment) has a column
    ``sensor``."""
    import csv
    import os

    if path is None or os.path.splitext(str(path))[1].lower() != ".csv":
        return False
    try:
        with open(path, encoding="utf-8-sig", newline="") as handle:
            for line in iter(lambda: handle.readline(MAX_LINE_CHARS + 1), ""):
                if line.lstrip().startswith("#"):
                    continue
                return "sensor" in [h.strip().lower() for h in next(csv.reader([line]))]
    except (OSError, UnicodeDecodeError, csv.Error, StopIteration):
        return False  # the ordinary reader names what is wrong
    return False


def _read_sensor_column(config, model, calls, steps) -> StampedRun:
    """One CSV of every sensor, a ``sensor`` column naming each row's (module docstring)."""
    import csv

    from dtpf.entity.observations import MAX_COLUMNS, _Lines, _cell, _open_check, _show, stamp_of_text
    from dtpf.entity.timeline import Reorder

    path = str(config.observation_file)
    name = _show(path)
    _open_check(path, name, ".csv")
    rank = {sensor: i + 1 for i, sensor in enumerate(calls.sensors)}
    window = int(round(float(getattr(config, "reorder_window", 0.0)) * 1e9))
    order = Reorder(window)
    ordered: list = []
    late: list[int] = []
    with open(path, encoding="utf-8-sig", newline="") as handle:
        lines = _Lines(handle, name, path)
        reader = csv.reader(lines, skipinitialspace=True)
        header = [h.strip() for h in next(reader)]
        if len(header) > MAX_COLUMNS:
            raise ObservationError(f"{name}: {len(header)} columns, more than {MAX_COLUMNS}", source=path)
        low = [h.lower() for h in header]
        times = [i for i, h in enumerate(low) if h in ("time", "t", "timestamp", "stamp")]
        if len(times) != 1:
            raise ObservationError(f"{name}: needs one time column (time, t, timestamp or stamp), its header has "
                                   f"{len(times)}", source=path)
        time_i, sensor_i = times[0], low.index("sensor")
        truth_i = [i for i, h in enumerate(low) if h == "truth" or h.startswith(("truth_", "true_"))]
        value_i = [i for i in range(len(header)) if i not in (time_i, sensor_i, *truth_i)]
        for row in reader:
            if not row or (len(row) == 1 and not row[0].strip()):
                continue
            line = lines.number
            if len(row) != len(header):
                raise ObservationError(f"{name} line {line}: {len(row)} values, the header has {len(header)} "
                                       f"columns", source=path, line=line)
            sensor = row[sensor_i].strip()
            if sensor not in rank:
                raise ObservationError(f"{name} line {line}: sensor {_cell(sensor)} is not one of the model's "
                                       f"({', '.join(rank)})", source=path, line=line)
            stamp = stamp_of_text(row[time_i])
            if stamp is None:
                raise ObservationError(f"{name} line {line}, column {header[time_i]!r}: {_cell(row[time_i])} is "
                                       f"not a time in seconds written as a decimal (e.g. 12.25)", source=path,
                                       line=line)
            m = calls.sensors[sensor]
            cells = [row[i] for i in value_i]
            if len(cells) < m or any(not c.strip() for c in cells[:m]) or any(c.strip() for c in cells[m:]):
                raise ObservationError(f"{name} line {line}: sensor {sensor!r} has {m} values, in the first {m} "
                                       f"value columns (the rest empty)", source=path, line=line)
            try:
                values = [float(c) for c in cells[:m]]
                truth = [float(row[i]) for i in truth_i]
            except ValueError:
                raise ObservationError(f"{name} line {line}: a value is not a number", source=path,
                                       line=line) from None
            if not np.isfinite(values).all() or not np.isfinite(truth).all():
                raise ObservationError(f"{name} line {line}: a value is not finite", source=path, line=line)
            if order.push(stamp, rank[sensor], (stamp, sensor, values, truth)):
                ordered.extend(order.ready())
            else:
                late.append(line)
    ordered.extend(order.flush())
    if steps is not None:
        ordered = ordered[:steps]
    if not ordered:
        raise ObservationError(f"{name}: no data rows", source=path)
    tables = {sensor: _Rows([], [] if truth_i else None) for sensor in calls.sensors}
    events = []
    for stamp, sensor, values, truth in ordered:
        table = tables[sensor]
        events.append((stamp, rank[sensor], len(table.observations), sensor))
        table.observations.append(np.array(values))
        if table.truth is not None:
            table.truth.append(np.array(truth))
    for table in tables.values():
        table.truth_components = tuple(range(len(truth_i)))
        table.truth_columns = tuple(header[i] for i in truth_i)
    problem = None
    if late:
        shown = ", ".join(map(str, late[:5])) + (", ..." if len(late) > 5 else "")
        plural = "s" if len(late) > 1 else ""
        problem = (f"{name}: {len(late)} row{plural} stamped before a row already put in order, beyond the "
                   f"reorder window of {config.reorder_window:g} s, skipped (line{plural} {shown})")
    return _assemble(config, model, calls, tables, events, path, problem)


class _Rows:
    """A sensor's rows of a shared CSV, as :func:`_assemble` reads a table."""

    def __init__(self, observations: list, truth: list | None):
        self.observations, self.truth = observations, truth
        self.truth_components: tuple = ()
        self.truth_columns: tuple = ()



def rows(config) -> int:
    """The number of steps in the run's sensor files (the sum of their rows), without the model."""
    total = 0
    for name, path in (config.sensor_files or {}).items():
        bag = topics.bag_topic(path)
        total += (topics.read_sensor(bag, name, config, obs_dim=None, state_dim=None, model=None) if bag
                  else read_observations(path)).steps
    return total


def read_controls(path, controls: tuple[str, ...], *, fields: str | None = None,
                  partial: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The control file's stamps (ns) and values (C, c): the columns named as ``controls`` when its header has
    them all, else every observation column in order (which must be c of them); a bag's topic
    (``BAG:/TOPIC``) by ``fields`` or its type (:func:`dtpf.entity.topics.read_control`)."""
    bag = topics.bag_topic(path)
    if bag is not None:
        return topics.read_control(bag, controls, fields, partial)[:2]
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
