"""The three layers in one process, without transport.

The entity's filter calls the twin (information and system layers) directly
where, over Zenoh, it would publish and wait. Random streams are keyed by
(seed, twin, step, layer), so a lockstep run over Zenoh reproduces these
numbers exactly::

    from messages.config import RunConfig
    from scripts.inprocess import run
    result = run(RunConfig(particles=1000, steps=100, seed=7))
    result.rmse, result.mean_ess
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from entity import models
from entity.filter import FilterStep, ParticleFilter, Preprocessed
from information.layer import InformationLayer
from messages.config import RunConfig
from messages.streams import stream
from system.layer import SystemLayer
from system.policy import PSDecision
from system.predict import Snapshot

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

    def __call__(self, step, particles, weights, observation, parents=None) -> Preprocessed:
        out = self.information.process(step, particles, weights, observation, parents)
        result = out.preprocessed
        snapshot = Snapshot.of(result.particles, result.weights, observation) if self.system.needs_particles else None
        decision = self.system.observe(step, out.summary, snapshot)
        self.information.set_ps(decision.ps, decision.applies_from_step)
        self.decisions.append(decision)
        return Preprocessed(out.preprocessed.particles, out.preprocessed.weights, out.preprocessed.report)


@dataclass
class RunResult:
    """Per-step record of one run and its summary figures."""

    config: RunConfig
    truth: np.ndarray
    observations: np.ndarray
    steps: list[FilterStep] = field(default_factory=list)
    elapsed: float = 0.0

    @property
    def means(self) -> np.ndarray:
        """(T, d) posterior means."""
        return np.array([s.mean for s in self.steps])

    @property
    def errors(self) -> np.ndarray:
        """(T, d) estimate minus truth."""
        return self.means - self.truth[: len(self.steps)]

    @property
    def rmse(self) -> float:
        """Root mean square error of the posterior mean against the truth, over steps and dimensions."""
        return float(np.sqrt(np.mean(self.errors ** 2)))

    @property
    def mse(self) -> float:
        return float(np.mean(self.errors ** 2))

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


def simulate(config: RunConfig) -> tuple[np.ndarray, np.ndarray]:
    """Truth and observations of the run's scenario, from stream(seed, twin, 0, "scenario")."""
    model = models.get(config.scenario)
    return model.simulate(config.steps, stream(config.seed, config.twin, 0, "scenario"))


def build(config: RunConfig, observations) -> ParticleFilter:
    """The filter of ``config``, wired to an in-process twin when preprocessing is on."""
    model = models.get(config.scenario)
    twin = None
    if config.preprocess:
        system = SystemLayer.from_config(config)
        information = InformationLayer(model, ps=system.policy.initial_ps, threshold_rule=config.threshold,
                                       weight_rule=config.weight_rule, seed=config.seed, twin=config.twin)
        twin = InProcessTwin(information, system)
    return ParticleFilter(model, observations, config.particles, resampler=config.resampler,
                          resample_below=config.resample_below, seed=config.seed, twin=config.twin,
                          preprocessor=twin)


def run(config: RunConfig, progress=None) -> RunResult:
    """Simulate the scenario and filter it; ``progress(step, total)`` is called after each step."""
    truth, observations = simulate(config)
    result = RunResult(config, truth, observations)
    pf = build(config, observations)
    start = time.perf_counter()
    for step in pf:
        result.steps.append(step)
        if progress is not None:
            progress(step.step, pf.steps)
    result.elapsed = time.perf_counter() - start
    return result
