"""The three layers in one process, without transport.

The entity's filter calls the twin (information and system layers) directly
where, over Zenoh, it would publish and wait. Random streams are keyed by
(seed, twin, step, layer), so a lockstep run over Zenoh reproduces these
numbers exactly::

    from dtpf.messages.config import RunConfig
    from dtpf.scripts.inprocess import run
    result = run(RunConfig(particles=1000, steps=100, seed=7))
    result.rmse, result.mean_ess
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from dtpf.entity import sources
from dtpf.entity.filter import FilterStep, ParticleFilter, Preprocessed
from dtpf.information.layer import InformationLayer, arms_for
from dtpf.messages.config import RunConfig
from dtpf.messages.streams import stream
from dtpf.system.layer import SystemLayer
from dtpf.system.policy import PSDecision
from dtpf.system.predict import Snapshot

__all__ = ["InProcessTwin", "RunResult", "build", "run", "simulate"]


class InProcessTwin:
    """The preprocessor hook of the filter: information layer, then system layer.

    The system layer sees what it sees over Zenoh: the weight-state summary
    and, when its policy simulates, the preprocessed set with the observation.
    """

    def __init__(self, information: InformationLayer, system: SystemLayer):
        self.information = information
        self.system = system
        self.decisions: list[PSDecision] = []

    def __call__(self, step, particles, weights, observation, parents=None, *, sensor=None,
                 drive=None) -> Preprocessed:
        """``sensor``, ``drive``: a driven step's sensor and drive (:mod:`dtpf.entity.timeline`), as the
        particle set carries them over Zenoh."""
        if sensor is None and drive is None:
            out = self.information.process(step, particles, weights, observation, parents)
        else:
            out = self.information.process(step, particles, weights, observation, parents, sensor=sensor)
        result = out.preprocessed
        snapshot = Snapshot.of(result.particles, result.weights, observation) if self.system.needs_particles else None
        if sensor is None and drive is None:
            decision = self.system.observe(step, out.summary, snapshot)
        else:
            decision = self.system.observe(step, out.summary, snapshot, sensor=sensor, drive=drive)
        self.information.set_ps(decision.ps, decision.applies_from_step, decision.preprocess, decision.arm)
        self.decisions.append(decision)
        return Preprocessed(out.preprocessed.particles, out.preprocessed.weights, out.preprocessed.report,
                            jitter=out.jitter)


@dataclass
class RunResult:
    """Per-step record of one run and its summary figures."""

    config: RunConfig
    #: (T, k) the known truth of the components ``truth_components`` (all of the state, mostly), or None.
    truth: np.ndarray | None
    observations: np.ndarray
    steps: list[FilterStep] = field(default_factory=list)
    elapsed: float = 0.0
    #: The state component of each column of ``truth`` (None: 0 .. k-1).
    truth_components: tuple[int, ...] | None = None
    #: The names of the truth columns (the observation file's), for the summary.
    truth_columns: tuple[str, ...] = ()
    #: A choosing policy's arms: the steps each arm was in force (None: a policy that names no arm).
    arms: dict[str, int] | None = None
    #: A choosing policy's base, and how it was reached (its rehearsal's size, "named" or "the default").
    base: tuple[str, str] | None = None

    @property
    def components(self) -> tuple[int, ...]:
        """The state components the truth (and so the RMSE) covers."""
        if self.truth is None:
            return ()
        if self.truth_components is None:
            return tuple(range(self.truth.shape[1]))
        return tuple(self.truth_components)

    @property
    def partial_truth(self) -> bool:
        """Whether the truth covers only some of the state's components (RMSE over those)."""
        return bool(self.steps) and self.truth is not None and self.components != tuple(range(len(self.steps[0].mean)))

    @property
    def means(self) -> np.ndarray:
        """(T, d) posterior means."""
        return np.array([s.mean for s in self.steps])

    @property
    def has_truth(self) -> bool:
        return self.truth is not None

    @property
    def errors(self) -> np.ndarray:
        """(T, k) estimate minus truth over the components the truth covers (:attr:`components`; all d
        mostly); ValueError when the run has no truth."""
        if self.truth is None:
            raise ValueError("this run has no truth: its observations came from outside")
        means = self.means
        if self.components != tuple(range(means.shape[1])):
            means = means[:, list(self.components)]
        return means - self.truth[: len(self.steps)]

    @property
    def rmse(self) -> float:
        """Root mean square error of the posterior mean against the truth, over steps and the
        components the truth covers (NaN without truth)."""
        return float(np.sqrt(np.mean(self.errors ** 2))) if self.has_truth else float("nan")

    @property
    def mse(self) -> float:
        return float(np.mean(self.errors ** 2)) if self.has_truth else float("nan")

    @property
    def log_predictive(self) -> np.ndarray:
        """(T,) log p(z_k | z_1:k-1) of every step."""
        return np.array([s.log_predictive for s in self.steps])

    @property
    def innovations(self) -> np.ndarray:
        """(T,) normalised innovation squared (NaN where not computed)."""
        return np.array([np.nan if s.innovation is None else s.innovation for s in self.steps])

    @property
    def ess(self) -> np.ndarray:
        return np.array([s.ess for s in self.steps])

    @property
    def mean_ess(self) -> float:
        return float(self.ess.mean())

    @property
    def resamplings(self) -> int:
        return sum(s.resampled for s in self.steps)

    @property
    def degraded(self) -> int:
        return sum(s.degraded for s in self.steps)

    @property
    def ps(self) -> np.ndarray:
        """PS used at each step (NaN where preprocessing did not run)."""
        return np.array([s.report.ps if s.report is not None else np.nan for s in self.steps])


def simulate(config: RunConfig, model=None) -> tuple[np.ndarray, np.ndarray]:
    """Truth and observations of the run's scenario, from stream(seed, twin, 0, "scenario");
    ``model``: the run's model if it is loaded already (default: the one the configuration names)."""
    if model is None:
        model = sources.load_model(config, check=False)
    return model.simulate(config.steps, stream(config.seed, config.twin, 0, "scenario"))


def build(config: RunConfig, observations, model=None, innovation: bool = False, *, sensors=None,
          drives=None) -> ParticleFilter:
    """The filter of ``config``, wired to an in-process twin when preprocessing is on.

    ``model``: the run's model if it is loaded already (default: the one the
    configuration names); ``innovation``, ``sensors``, ``drives``: see
    :class:`~dtpf.entity.filter.ParticleFilter`.
    """
    if model is None:
        model = sources.load_model(config, check=False)
    twin = None
    if config.preprocess:
        system = SystemLayer.from_config(config, model=model)
        information = InformationLayer(model, ps=system.policy.initial_ps, threshold_rule=config.threshold,
                                       weight_rule=config.weight_rule, seed=config.seed, twin=config.twin,
                                       move_rule=config.move_rule, preprocess=system.policy.initial_preprocess,
                                       arm=getattr(system.policy, "initial_arm", None),
                                       arms=arms_for(config.jitter), block=config.block_particles)
        twin = InProcessTwin(information, system)
    return ParticleFilter(model, observations, config.particles, resampler=config.resampler,
                          resample_below=config.resample_below, seed=config.seed, twin=config.twin,
                          preprocessor=twin, innovation=innovation, jitter=config.jitter, sensors=sensors,
                          drives=drives, block=config.block_particles)


def run(config: RunConfig, progress=None, model=None, note=None) -> RunResult:
    """Filter the run's observations (simulated, or from its file); ``progress(step, total)`` is
    called after each step, ``note(problem)`` before the first when the file was read despite a problem
    (a rosbag2 log cut short). The model is checked on a probe first unless ``model`` is given.

    Raises ValueError for a live run (it needs the sensor's Zenoh: ``dtpf launch``).
    """
    if config.live:
        raise ValueError("dtpf run filters in one process, without Zenoh: live observations need "
                         "dtpf launch (or give an observation file)")
    if model is None:
        model = sources.load_model(config)
    data = sources.observations_of(config, model)
    if note is not None and data.problem is not None:
        note(data.problem)
    result = RunResult(config, data.known_truth, data.observations, truth_components=data.truth_components,
                       truth_columns=data.truth_columns)
    pf = build(config, data.observations, model, innovation=data.known_truth is None, sensors=data.sensors,
               drives=data.drives)
    start = time.perf_counter()
    for step in pf:
        result.steps.append(step)
        if progress is not None:
            progress(step.step, pf.steps)
    result.elapsed = time.perf_counter() - start
    _note_arms(result, pf)
    return result


def _note_arms(result: RunResult, pf) -> None:
    """A choosing policy's arms in force at each step of the run, counted, and its base (``result.arms``,
    ``result.base``)."""
    preprocessor = getattr(pf, "preprocessor", None)
    policy = getattr(getattr(preprocessor, "system", None), "policy", None)
    arm = getattr(policy, "initial_arm", None)
    if arm is None or not result.steps:
        return
    changes = {decision.applies_from_step: decision.arm for decision in preprocessor.decisions if decision.arm}
    counts: dict[str, int] = {}
    for step in result.steps:
        arm = changes.get(step.step, arm)
        counts[arm] = counts.get(arm, 0) + 1
    result.arms = dict(sorted(counts.items(), key=lambda item: -item[1]))
    rehearsal = getattr(policy, "rehearsal", None)
    result.base = (policy.base, f"a rehearsal of {rehearsal.runs:,} simulated runs" if rehearsal is not None
                   else "named" if result.config.choose_base else "the default")
