"""Evidence from the real observations: has preprocessing been predicting them better than not?

The twin's what-if simulation (:mod:`dtpf.system.predict`) scores candidates
against states drawn from the filter's own posterior; an impoverished
posterior, collapsed onto a few values, is sure of itself there and cannot
see what diversity would gain. :class:`Evidence` asks the real observations
instead, without truth, two steps at a time:

1. At step k it draws M = min(N, ``particles``) particles from the set of
   step k - 1 the system layer received (the set the entity resampled:
   systematic points), propagates them to k through the model and weights
   them by the *real* z_k: the twin's copy of the entity's weighted set of k,
   before any preprocessing.
2. Two arms from that copy, with common random numbers: *off* (resampled as
   it is) and *on* (the run's preprocessing with PS, then resampled; the
   same uniform points). Both are propagated to k + 1 with the same numbers.
3. At step k + 1 the real z_(k+1) scores both: the predictive
   log-likelihood log mean_j p(z_(k+1) | x_j) of each arm, and their
   difference d_k = on - off (nats; positive: preprocessing predicted the
   observation better).

The sum of the last W differences is a sliding-window prequential log Bayes
factor of "preprocess" against "do not" (Dawid 1984): the guard-observed
policy preprocesses when it exceeds log(19), odds of 19 to 1 (95% with even
prior odds). The arms are counterfactual copies of the filter, so the sum
is an estimate of that log Bayes factor, not the factor itself.

Every random number comes from the generator passed (the system layer's
stream of step k), after any the what-if simulation drew. The model needs
``propagate`` and ``log_likelihood`` only, not ``sample_observation``: the
evidence works on a real twin and on the video scenario.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from dtpf.entity import resampling
from dtpf.entity.models import StateSpaceModel
from dtpf.information import rules

__all__ = ["Evidence", "predictive_log_likelihood"]


def predictive_log_likelihood(model: StateSpaceModel, particles: np.ndarray, observation: np.ndarray,
                              k: int) -> float:
    """log mean_j p(z_k | x_j) over equally weighted ``particles`` (shifted by the maximum)."""
    values = model.log_likelihood(particles, observation, k)
    top = float(np.max(values))
    if not np.isfinite(top):
        return -np.inf
    return top + float(np.log(np.mean(np.exp(values - top))))


@dataclass(frozen=True)
class _Arms:
    step: int                 # k: the arms start from the weighted copy of step k
    off: np.ndarray           # (M, d) at k + 1
    on: np.ndarray            # (M, d) at k + 1


class Evidence:
    """The running on-against-off log-likelihood evidence of one twin (see the module docstring).

    Parameters
    ----------
    model : StateSpaceModel
    ps : float
        The PS the *on* arm uses.
    threshold_rule, weight_rule, move_rule :
        The run's preprocessing options, which the *on* arm replays.
    particles : int
        M, at most this many particles per arm.
    window : int
        W, the differences kept and summed.
    """

    def __init__(self, model: StateSpaceModel, ps: float, *, threshold_rule="neff", weight_rule: str = "inherit",
                 move_rule: str = "paper", particles: int = 1000, window: int = 20):
        if int(window) < 1:
            raise ValueError(f"window must be at least 1, got {window!r}")
        self.model = model
        self.ps = float(ps)
        self.threshold_rule = threshold_rule
        self.weight_rule = weight_rule
        self.move_rule = move_rule
        self.particles = int(particles)
        self.differences: deque[float] = deque(maxlen=int(window))
        self._start: tuple[int, np.ndarray] | None = None   # (k + 1, M particles propagated to k + 1)
        self._arms: _Arms | None = None

    @property
    def window(self) -> int:
        return self.differences.maxlen

    @property
    def total(self) -> float:
        """Sum of the kept differences (nats): the windowed log Bayes factor of on against off."""
        return float(sum(self.differences))

    @property
    def full(self) -> bool:
        """Whether W differences are in (before that, the evidence is not judged)."""
        return len(self.differences) == self.window

    def observe(self, step: int, particles: np.ndarray, weights: np.ndarray, observation: np.ndarray,
                rng: np.random.Generator) -> float | None:
        """Take the set of ``step`` (as the entity resamples it) and its observation z_step.

        Returns the new difference d_(step-1) (scored with z_step), or None
        when there was no pair of arms of step - 1 to score. Call once per
        step, in order.
        """
        model, k = self.model, int(step)
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
        difference = None
        arms, self._arms = self._arms, None
        if arms is not None and arms.step == k - 1:
            on = predictive_log_likelihood(model, arms.on, z, k)
            off = predictive_log_likelihood(model, arms.off, z, k)
            if np.isfinite(on) or np.isfinite(off):
                difference = (on - off) if np.isfinite(on) and np.isfinite(off) else (np.inf if np.isfinite(on)
                                                                                      else -np.inf)
                difference = float(np.clip(difference, -50.0, 50.0))  # one wild step cannot decide W of them
                self.differences.append(difference)
        start, self._start = self._start, None
        if start is not None and start[0] == k:
            self._arms = self._make_arms(k, start[1], z, rng)
        m = min(weights.size, self.particles)
        points = (rng.random() + np.arange(m)) / m
        drawn = particles[resampling.inverse_cdf(points, weights)]
        self._start = (k + 1, model.propagate(drawn, k + 1, rng))
        return difference

    def _make_arms(self, k: int, prior: np.ndarray, z: np.ndarray, rng: np.random.Generator) -> _Arms | None:
        model = self.model
        log_w = model.log_likelihood(prior, z, k)
        top = float(np.max(log_w))
        if not np.isfinite(top):
            return None
        w = np.exp(log_w - top)
        w /= w.sum()
        log_likelihood = (lambda x: model.log_likelihood(x, z, k)) if self.weight_rule == "likelihood" else None
        moved = rules.preprocess(prior, w, self.ps, rng, threshold_rule=self.threshold_rule,
                                 weight_rule=self.weight_rule, log_likelihood=log_likelihood,
                                 move_rule=self.move_rule)
        m = w.size
        points = (rng.random() + np.arange(m)) / m       # the same points resample both arms
        off = prior[resampling.inverse_cdf(points, w)]
        on = moved.particles[resampling.inverse_cdf(points, moved.weights)]
        state = rng.bit_generator.state
        off = model.propagate(off, k + 1, rng)
        rng.bit_generator.state = state                   # the same numbers propagate both arms
        on = model.propagate(on, k + 1, rng)
        return _Arms(k, off, on)
