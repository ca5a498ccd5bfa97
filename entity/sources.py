"""Where a run's model and observations come from, the same in every process of a twin.

A run (:class:`~dtpf.messages.config.RunConfig`) names its model (``--scenario``
or ``--model REF``) and its observations (``--observations``): none (the
model is simulated, so the truth is known), a file, or a live sensor::

    from dtpf.entity import sources
    model = sources.load_model(config)                 # resolved and checked on a probe
    data = sources.observations_of(config, model)      # file or simulation; None when live
    data.observations, data.truth                      # (T, m), (T, d) or None
    data.known_truth, data.truth_components            # (T, k), the k state components the truth covers

A driven model (its ``propagate`` takes ``dt`` or ``control``, or it declares ``controls`` or ``sensors``)
reads its sensors' files and its control file in stamp order (:mod:`dtpf.entity.stamped`): ``data.sensors``
and ``data.drives`` give each step's sensor and how it is reached from the one before.

Every layer process calls :func:`load_model`, so the information layer's
likelihood rule and the system layer's simulation use the model the entity
filters with. Mistakes raise :class:`~dtpf.entity.model_ref.ModelError` or
:class:`~dtpf.entity.observations.ObservationError` (both ValueError), one line each.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dtpf.entity.model_check import load_checked
from dtpf.entity.model_ref import ModelError
from dtpf.entity.models import StateSpaceModel
from dtpf.entity.observations import ObservationTable, read_observations
from dtpf.messages import family
from dtpf.messages.streams import stream

__all__ = ["RunData", "load_model", "observations_of", "read_table", "sampling_need", "ModelError"]


@dataclass(frozen=True)
class RunData:
    """The observations a run filters, with the truth where it is known.

    ``truth`` is the whole state per step, or None; a file whose truth covers
    only some components of the state (positions of a state with velocities)
    has ``truth`` None and those components in ``known_truth``, the state
    component of each column in ``truth_components``.
    """

    observations: np.ndarray
    truth: np.ndarray | None
    #: Where they came from: "simulation of <model>" or the file name.
    source: str
    #: (T, k) the truth as known: all of ``truth``, or the part of the state a file gives.
    known_truth: np.ndarray | None = None
    #: The state component of each column of ``known_truth``.
    truth_components: tuple[int, ...] = ()
    #: The names of those columns (the file's truth columns; x0, x1, ... for a simulation).
    truth_columns: tuple[str, ...] = ()
    #: (T,) int64 nanoseconds since the Unix epoch: each step's time, the stamp of its estimate (a rosbag2
    #: log's receive times); None: the estimates carry their publish time.
    stamps: np.ndarray | None = None
    #: What was wrong with the file and how it was read anyway (a rosbag2 log cut short), or None.
    problem: str | None = None
    #: Each step's sensor (a driven run of a model with sensors), or None.
    sensors: tuple | None = None
    #: How each step is reached from the one before (:class:`~dtpf.entity.timeline.Drive`; None for the
    #: first), a driven run's; None for a model that is not driven.
    drives: list | None = None

    def __post_init__(self):
        if self.truth is not None and self.known_truth is None:
            object.__setattr__(self, "known_truth", self.truth)
            object.__setattr__(self, "truth_components", tuple(range(self.truth.shape[1])))
            if not self.truth_columns:
                object.__setattr__(self, "truth_columns", tuple(f"x{j}" for j in range(self.truth.shape[1])))

    @property
    def steps(self) -> int:
        return self.observations.shape[0]


def sampling_need(config, *, sensor: bool = False) -> str | bool:
    """Why this run needs ``sample_observation`` (a text for the error), or False."""
    if sensor:
        return "dtpf sensor (it simulates observations)"
    if config.preprocess and family.POLICIES.trait(config.policy, "samples_observations", False):
        return f"the system layer's policy {config.policy!r} (it simulates observations)"
    return False


def _check_simulation(config, model: StateSpaceModel) -> None:
    """A simulated run needs a model that can simulate: its own ``simulate``, or ``sample_observation``; a
    driven model's run needs observation files (a simulation has no stamps, sensors or controls)."""
    from dtpf.entity.calls import ModelCalls

    if config.simulated and ModelCalls(model).driven:
        raise ModelError(f"model {config.model_ref!r} is driven (time steps, controls or several sensors): give "
                         f"its observations with --observations (NAME=FILE per sensor) and --controls")
    if config.simulated and type(model).simulate is StateSpaceModel.simulate and not model.samples_observations:
        raise ModelError(f"model {config.model_ref!r}: sample_observation is not implemented, so it cannot be "
                         f"simulated; give the observations to filter with --observations")


def read_table(config, model: StateSpaceModel | None = None, *, steps: int | None = None) -> ObservationTable:
    """The run's observation file as a table: read by the run's ``reader`` (:mod:`dtpf.entity.readers`: a
    built-in or a user's own), else by the file's kind: a CSV, .npy or .npz, or a rosbag2 log (folder or
    .mcap) read on ``config.topic`` by ``config.ros2_fields`` (:mod:`dtpf.entity.rosbag`). ``model`` checks the
    dimensions (None: not checked; a bag mapped by the model's own method loads it)."""
    from dtpf.entity import rosbag

    path = config.observation_file
    from dtpf.entity import stamped
    if config.reader is None and stamped.has_sensor_column(path) and _named_sensors(config, model):
        model = model if model is not None else _resolved(config)  # a driven twin's sensors in one CSV
        run = stamped.read_stamped(config, model, steps=steps)
        return ObservationTable(observations=run.observations, truth=run.truth, times=None,
                                columns=tuple(f"z{j}" for j in range(run.observations.shape[1])),
                                truth_columns=run.truth_columns, source=str(path),
                                truth_components=run.truth_components, stamps=run.stamps, problem=run.problem)
    if config.reader is not None:
        if model is None:
            from dtpf.entity import model_ref
            model = model_ref.resolve(config.model_ref)
        read = family.READERS.get(config.reader)
        return read(path, obs_dim=model.obs_dim, state_dim=model.dim, steps=steps, topic=config.topic,
                    fields=config.ros2_fields, model=model, partial=config.partial)
    if config.topic is not None or rosbag.is_bag(path):
        if model is None and config.ros2_fields is None:
            from dtpf.entity import model_ref
            model = model_ref.resolve(config.model_ref)
        return rosbag.read_bag(path, config.topic, config.ros2_fields, obs_dim=None if model is None else model.obs_dim,
                               state_dim=None if model is None else model.dim, steps=steps, model=model,
                               partial=config.partial)
    if model is None:
        return read_observations(path, steps=steps)
    return read_observations(path, obs_dim=model.obs_dim, state_dim=model.dim, steps=steps)


def _resolved(config) -> StateSpaceModel:
    from dtpf.entity import model_ref
    return model_ref.resolve(config.model_ref)


def _named_sensors(config, model) -> bool:
    """Whether the run's model declares named sensors (only such a model reads a CSV's ``sensor`` column as
    the sensors' names; any other reads it as it always has)."""
    from dtpf.entity.calls import ModelCalls
    return ModelCalls(model if model is not None else _resolved(config)).named_sensors


def _probe_observation(config, model: StateSpaceModel) -> np.ndarray | None:
    """The first row of the observation file, to probe the likelihood with (its columns checked
    against the model's dimensions first, so a file that does not fit is named as the problem)."""
    from dtpf.entity.calls import ModelCalls

    if ModelCalls(model).driven:
        if config.simulated or config.live:
            return None
        from dtpf.entity import stamped
        run = stamped.read_stamped(config, model, steps=1)
        return {run.sensors[0]: run.observations[0][~np.isnan(run.observations[0])]}
    if config.observation_file is None:
        return None
    return read_table(config, model, steps=1).observations[0]


def load_model(config, *, check: bool = True, sensor: bool = False) -> StateSpaceModel:
    """The run's model, resolved from its reference and (``check``) probed on a few particles.

    Raises ModelError (or ObservationError for the probe's observation file).
    """
    from dtpf.entity import model_ref

    model = model_ref.resolve(config.model_ref)
    if not check:
        return model
    model = load_checked(config.model_ref, observation=_probe_observation(config, model),
                         needs_sampling=sampling_need(config, sensor=sensor))
    _check_simulation(config, model)
    return model


def observations_of(config, model: StateSpaceModel) -> RunData | None:
    """The observations of a file or simulated run (None for a live one).

    A simulation draws from ``stream(seed, twin, 0, "scenario")``, so every
    process and ``dtpf run`` see the same path.
    """
    if config.live:
        return None
    from dtpf.entity.calls import ModelCalls

    if ModelCalls(model).driven and not config.simulated:
        from dtpf.entity import stamped
        run = stamped.read_stamped(config, model, steps=config.steps)
        whole = run.truth is not None and run.truth_components == tuple(range(model.dim))
        return RunData(run.observations, run.truth if whole else None, run.source, known_truth=run.truth,
                       truth_components=run.truth_components, truth_columns=run.truth_columns, stamps=run.stamps,
                       sensors=run.sensors, drives=run.drives, problem=run.problem)
    if config.observation_file is not None:
        table: ObservationTable = read_table(config, model, steps=config.steps)
        whole = table.covers(model.dim)
        return RunData(table.observations, table.truth if whole else None, table.source,
                       known_truth=table.truth, truth_components=table.truth_components,
                       truth_columns=table.truth_columns, stamps=table.stamps, problem=table.problem)
    truth, observations = model.simulate(config.steps, stream(config.seed, config.twin, 0, "scenario"))
    return RunData(np.asarray(observations, dtype=np.float64), np.asarray(truth, dtype=np.float64),
                   f"simulation of {config.model_ref}")
