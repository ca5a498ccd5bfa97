"""Degradation prediction: what the system layer expects of the next filter step.

The paper's system layer predicts particle degradation through "the
detection of the weights distribution" and "the simulation of the results"
(section 3). :class:`Predictor` does both, once per filter step k:

1. **From the mirrored weight state and its history** (the information
   layer's :class:`~dtpf.information.mirror.WeightSummary` of every step): ESS/N
   now and its least-squares trend over the last ``window`` steps (weight
   collapse), and the distinct ancestors of the last resampling over N
   (impoverishment).
2. **From the twin's own one-step simulation**, when the system layer has the
   particle set (a :class:`Snapshot`: the preprocessed set of step k, which is
   what the entity resamples). The predictor draws M = min(N, ``particles``)
   particles from it (systematic points), propagates them through the
   scenario's model to k + 1, and draws S = ``scenarios`` plausible next
   states (each an independent propagation of a drawn particle) with their
   observations. Weighting the propagated particles by each simulated
   observation forecasts the next ESS/N, the distinct ancestors the entity's
   resampler keeps (its own resampling of each simulated set) and the
   posterior spread (weighted standard deviation), averaged over the S
   scenarios.
3. **Surprise**: when z_(k+1) arrives, the simulation of step k scores it: its
   predictive log-likelihood log p(z_(k+1) | z_(1:k)) ~ log mean_j
   p(z_(k+1) | x_j) over the twin's propagated particles, and the surprise,
   the mean predictive log-likelihood of the S simulated observations minus
   that of the real one (nats; about 0 for a typical observation, large
   when the observation lands where the particles did not expect it, which
   is when weights collapse).

The simulation also answers "what if PS were c at step k + 1?"
(:meth:`Forecast.what_if`; c = None: "what if the preprocessing were off?"):
for each scenario it applies the preprocessing rules (Eq. 28-30, or the
run's move rule) with PS = c to the simulated weighted set (none for off), scores the
weighted mean against the scenario's simulated true state, then resamples,
propagates to k + 2 and scores the next estimate against the scenario's
state there. Every candidate sees the same random numbers (common random
numbers), so differences between candidates are due to PS alone.

Every random number comes from the generator the caller passes (the system
layer passes ``stream(seed, twin, k, "system")``), in a fixed order, so the
same inputs give the same forecast in any process::

    from dtpf.entity import models
    from dtpf.system.predict import Predictor, Snapshot
    predictor = Predictor(models.get("ungm"))
    forecast = predictor.forecast(step, summary, Snapshot(x, w, z), rng)
    forecast.predicted_ess_ratio, forecast.surprise
    [o.error for o in forecast.what_if([0.5, 0.81])]

Limits: the simulation trusts the model and the filter's own posterior (a
filter locked on the wrong mode of the growth model forecasts from that mode);
it assumes the next step resamples (true unless ``resample_below`` is set).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from dtpf.entity import resampling
from dtpf.entity.models import StateSpaceModel
from dtpf.information import rules
from dtpf.information.mirror import WeightSummary
from dtpf.messages.arrays import check_particles, check_weights

__all__ = ["Snapshot", "Forecast", "Outcome", "Predictor"]


@dataclass(frozen=True)
class Snapshot:
    """The particle set the system layer simulates from.

    Attributes
    ----------
    particles : (N, d) ndarray
    weights : (N,) ndarray, normalised
    observation : (m,) ndarray
        z_k, the observation the weights carry.
    """

    particles: np.ndarray
    weights: np.ndarray
    observation: np.ndarray

    @classmethod
    def of(cls, particles, weights, observation) -> "Snapshot":
        """A validated snapshot (ValueError naming a bad array)."""
        w = check_weights(weights)
        x = check_particles(particles, n=w.size)
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
        if not np.isfinite(z).all():
            raise ValueError("observation contains non-finite values")
        return cls(x, w, z)


@dataclass(frozen=True)
class Outcome:
    """Predicted result of one candidate PS on the simulated next steps.

    Attributes
    ----------
    ps : float or None
        The candidate; None: no preprocessing (the decision "off").
    error : float
        Mean over the S scenarios of the squared error of the estimate at
        k + 1 (after preprocessing with ``ps``) plus that at k + 2 (the
        filter continued from the preprocessed set), per state dimension.
    errors : (S,) ndarray
        The same, per scenario (paired across candidates).
    ess_ratio : float
        Mean ESS/M at k + 2.
    """

    ps: float | None
    error: float
    errors: np.ndarray = field(repr=False, compare=False)
    ess_ratio: float


def _logmeanexp(values: np.ndarray) -> np.ndarray:
    """log mean exp along the last axis, shifted by the maximum (no overflow)."""
    top = values.max(axis=-1, keepdims=True)
    return (top + np.log(np.mean(np.exp(values - top), axis=-1, keepdims=True)))[..., 0]


def _normalise_rows(log_weights: np.ndarray) -> np.ndarray:
    """Normalised weights of each row of log-weights (S, M)."""
    weights = np.exp(log_weights - log_weights.max(axis=-1, keepdims=True))
    weights /= weights.sum(axis=-1, keepdims=True)
    return weights


def _distinct(ancestors: np.ndarray) -> int:
    """Distinct entries of sorted ancestor indices."""
    return 1 + int(np.count_nonzero(ancestors[1:] != ancestors[:-1]))


class _Simulation:
    """The twin's simulation of steps k + 1 and k + 2 from the set of step k."""

    def __init__(self, predictor: "Predictor", step: int, snapshot: Snapshot, rng: np.random.Generator):
        model = predictor.model
        self.model = model
        self.predictor = predictor
        self.step = k = step
        n = snapshot.weights.size
        m = self.m = min(n, predictor.particles)
        s = predictor.scenarios
        # Draws, in this order: systematic points, propagation, scenario particles and their
        # paths and observations, resampling of each scenario, the seed of the what-if runs.
        points = (rng.random() + np.arange(m)) / m
        start = snapshot.particles[resampling.inverse_cdf(points, snapshot.weights)]
        self.particles = model.propagate(start, k + 1, rng)
        chosen = rng.integers(0, m, size=s)
        self.truth1 = model.propagate(start[chosen], k + 1, rng)
        self.z1 = model.sample_observation(self.truth1, k + 1, rng)
        self.truth2 = model.propagate(self.truth1, k + 2, rng)
        self.z2 = model.sample_observation(self.truth2, k + 2, rng)
        log_likelihoods = self._log_likelihoods(np.broadcast_to(self.particles, (s, *self.particles.shape)), self.z1, k + 1)
        self.weights = _normalise_rows(log_likelihoods)
        self.log_predictive = _logmeanexp(log_likelihoods)
        self.ess = 1.0 / np.einsum("ij,ij->i", self.weights, self.weights)
        self.resample = resampling.get(predictor.resampler)
        self.distinct = np.array([_distinct(self.resample(w, rng)) for w in self.weights])
        means = np.einsum("sm,md->sd", self.weights, self.particles)
        centred = self.particles[None, :, :] - means[:, None, :]                  # (S, M, d)
        self.spread = np.sqrt(np.einsum("sm,smd->s", self.weights, centred * centred))
        self.seed = int(rng.integers(0, 2 ** 63))  # of the what-if runs
        self._outcomes: dict[float, Outcome] = {}

    def score(self, observation: np.ndarray) -> tuple[float, float]:
        """(log predictive likelihood, surprise) of the real observation of step k + 1."""
        lp = float(_logmeanexp(self.model.log_likelihood(self.particles, observation, self.step + 1)))
        return lp, float(self.log_predictive.mean()) - lp

    def outcomes(self, ps_values: list[float]) -> list[Outcome]:
        """The outcome of each candidate, computed together (same random numbers for all)."""
        todo = [ps for ps in dict.fromkeys(ps_values) if ps not in self._outcomes]
        if todo:
            errors, ess = self._run(todo)
            for j, ps in enumerate(todo):
                self._outcomes[ps] = Outcome(ps, float(errors[:, j].mean()), errors[:, j], float(ess[:, j].mean()))
        return [self._outcomes[ps] for ps in ps_values]

    def _run(self, candidates: list) -> tuple[np.ndarray, np.ndarray]:
        # The rules' own random numbers (partner, r, u per small particle; rules.draws) are
        # drawn once per scenario and serve every candidate (rules.apply_rules), so candidates
        # differ only in the branch of Eq. 30 that u <= PS picks. Resampling and propagation to
        # k + 2 also reuse their numbers across candidates.
        p, model, k, x = self.predictor, self.model, self.step, self.particles
        s, (m, d) = len(self.z1), x.shape
        inherit = p.weight_rule == "inherit"
        rng = np.random.Generator(np.random.PCG64(self.seed))
        flat = x[None].repeat(s, axis=0).reshape(s * m, d)   # the S weighted sets, one after another
        small, partner, r, u = [], [], [], []
        shared_ancestors = np.empty((s, m), dtype=np.int64)
        resample_states = []
        for i, w in enumerate(self.weights):
            limit = rules.threshold(w, p.threshold_rule)
            large_i = np.flatnonzero(w > limit)
            small_i = np.flatnonzero(w <= limit)
            if large_i.size and small_i.size:
                partners, r_i, u_i = rules.draws(rng, small_i.size, large_i.size)
                small.append(i * m + small_i)
                partner.append(i * m + large_i[partners])
                r.append(r_i)
                u.append(u_i)
            resample_states.append(rng.bit_generator.state)
            if inherit:
                shared_ancestors[i] = self.resample(w, rng)
        propagate_state = rng.bit_generator.state
        small, partner, r, u = (np.concatenate(a) if a else np.empty(0) for a in (small, partner, r, u))
        small, partner = small.astype(np.int64), partner.astype(np.int64)
        is_small = np.zeros(s * m, dtype=bool)
        is_small[small] = True
        is_small = is_small.reshape(s, m)
        if not inherit:  # as dtpf.information.rules: w <- w p(z | new) / p(z | old) for the small particles
            with np.errstate(divide="ignore"):
                log_w = np.log(self.weights)
            old = self._log_likelihoods(np.broadcast_to(x, (s, m, d)), self.z1, k + 1)
        if p.move_rule == "relative":  # each small particle's cap: the spread of its scenario's weighted set
            sigma = np.stack([rules.spread(x, w) for w in self.weights])[small // m]
        errors = np.empty((s, len(candidates)))
        ess = np.empty((s, len(candidates)))
        for j, ps in enumerate(candidates):
            moved = flat.copy()
            if ps is None:  # off: the set as it is, resampled plainly
                pass
            elif p.move_rule == "relative":
                moved[small] = rules.apply_relative(flat[partner], flat[small], r, u, float(ps), sigma)
            else:
                moved[small] = rules.apply_rules(flat[partner], flat[small], r, u, float(ps))
            moved = moved.reshape(s, m, d)
            if inherit:
                weights, ancestors = self.weights, shared_ancestors
            elif ps is None:
                weights = self.weights
                ancestors = np.empty((s, m), dtype=np.int64)
                for i in range(s):
                    rng.bit_generator.state = resample_states[i]
                    ancestors[i] = self.resample(weights[i], rng)
            else:
                delta = np.where(is_small, self._log_likelihoods(moved, self.z1, k + 1) - old, 0.0)
                weights = _normalise_rows(np.where(np.isneginf(log_w), -np.inf, log_w + delta))
                ancestors = np.empty((s, m), dtype=np.int64)
                for i in range(s):
                    rng.bit_generator.state = resample_states[i]
                    ancestors[i] = self.resample(weights[i], rng)
            mean1 = np.einsum("sm,smd->sd", weights, moved)
            rng.bit_generator.state = propagate_state
            resampled = np.take_along_axis(moved, ancestors[..., None], axis=1).reshape(s * m, d)
            following = model.propagate(resampled, k + 2, rng).reshape(s, m, d)
            w2 = _normalise_rows(self._log_likelihoods(following, self.z2, k + 2))
            mean2 = np.einsum("sm,smd->sd", w2, following)
            errors[:, j] = (np.sum((mean1 - self.truth1) ** 2, axis=1) + np.sum((mean2 - self.truth2) ** 2, axis=1)) / d
            ess[:, j] = 1.0 / np.einsum("sm,sm->s", w2, w2) / m
        return errors, ess

    def _log_likelihoods(self, particles: np.ndarray, observations: np.ndarray, k: int) -> np.ndarray:
        """(S, M) log p(z_s | x_sm) for particle sets (S, M, d) and observations (S, m)."""
        return np.stack([self.model.log_likelihood(particles[i], observations[i], k) for i in range(len(observations))])


@dataclass(frozen=True)
class Forecast:
    """What the predictor expects of step k + 1, from the state of step k.

    Attributes
    ----------
    step : int
        k, the step whose state the forecast starts from.
    n : int
        N.
    ess_ratio : float
        Observed ESS/N at k.
    ess_trend : float
        Least-squares slope of ESS/N per step over the last ``window`` steps
        (0 with fewer than two).
    distinct_ratio : float
        Observed distinct ancestors of the last resampling / N.
    log_predictive, surprise : float or None
        Predictive log-likelihood of z_k under the simulation of step k - 1,
        and the surprise (nats; see the module docstring). None without that
        simulation.
    predicted_ess_ratio, predicted_distinct_ratio, predicted_spread : float or None
        The simulation's forecast of ESS/N at k + 1, of the distinct
        ancestors / N the resampling of k + 1 keeps, and of the posterior
        standard deviation at k + 1 (root of the summed variances). None
        without a simulation.
    evidence : float or None
        With a predictor that gathers :mod:`dtpf.system.evidence`: the sum of the
        last ``evidence_steps`` differences of predictive log-likelihood of
        the real observations, preprocessing on minus off (nats).
    """

    step: int
    n: int
    ess_ratio: float
    ess_trend: float
    distinct_ratio: float
    log_predictive: float | None = None
    surprise: float | None = None
    predicted_ess_ratio: float | None = None
    predicted_distinct_ratio: float | None = None
    predicted_spread: float | None = None
    simulation: _Simulation | None = field(default=None, repr=False, compare=False)
    evidence: float | None = None
    evidence_steps: int = 0
    #: With a predictor that gathers :mod:`dtpf.system.choose`: each arm's summed differences of
    #: predictive log-likelihood against plain resampling over the last ``evidence_steps`` steps (nats).
    arm_evidence: dict[str, float] | None = field(default=None, compare=False)
    #: The same over the copies' predicted means: log p(z | mean) against plain's (nats).
    arm_point_evidence: dict[str, float] | None = field(default=None, compare=False)
    #: The window's differences themselves, one {arm: d_a(k)} per step, oldest first.
    arm_differences: tuple[dict[str, float], ...] | None = field(default=None, compare=False, repr=False)

    @property
    def next_ess_ratio(self) -> float:
        """The simulated ESS/N of k + 1, else the trend's extrapolation (clipped to [0, 1])."""
        if self.predicted_ess_ratio is not None:
            return self.predicted_ess_ratio
        return min(1.0, max(0.0, self.ess_ratio + self.ess_trend))

    @property
    def next_distinct_ratio(self) -> float:
        """The simulated distinct ratio of k + 1, else the observed one."""
        return self.predicted_distinct_ratio if self.predicted_distinct_ratio is not None else self.distinct_ratio

    def what_if(self, ps_values) -> list[Outcome]:
        """The predicted :class:`Outcome` of each candidate PS, None meaning no preprocessing
        (ValueError without a simulation)."""
        if self.simulation is None:
            raise ValueError(f"step {self.step}: no simulation to try PS values on (no particle set)")
        return self.simulation.outcomes([None if ps is None else float(ps) for ps in ps_values])


class Predictor:
    """Forecasts degradation at the next step from the weight state and the twin's simulation.

    Parameters
    ----------
    model : StateSpaceModel or None
        The scenario's model; None: no simulation, only the figures of the
        weight-state history.
    resampler, threshold_rule, weight_rule, move_rule :
        The run's traditional resampler and preprocessing options, which the
        simulation replays.
    particles : int
        M, at most this many particles are simulated (the ratios ESS/M and
        distinct/M stand for ESS/N and distinct/N).
    scenarios : int
        S, simulated next states and observations per step.
    window : int
        Steps in the ESS/N trend.
    scenario_simulation : bool
        Run the what-if simulation (needs ``sample_observation``); False
        for a policy that reads only the evidence.
    evidence : dtpf.system.evidence.Evidence, optional
        Gathers the on-against-off evidence of the real observations each step.
    """

    def __init__(self, model: StateSpaceModel | None = None, *, resampler: str = "systematic",
                 threshold_rule: str | float = "neff", weight_rule: str = "inherit", particles: int = 1000,
                 scenarios: int = 8, window: int = 5, move_rule: str = "paper", scenario_simulation: bool = True,
                 evidence=None):
        resampling.get(resampler)
        if weight_rule not in rules.WEIGHT_RULES:
            raise ValueError(f"unknown weight rule {weight_rule!r}; expected one of {', '.join(rules.WEIGHT_RULES)}")
        if move_rule not in rules.MOVE_RULES:
            raise ValueError(f"unknown move rule {move_rule!r}; expected one of {', '.join(rules.MOVE_RULES)}")
        if int(particles) < 2:
            raise ValueError(f"particles must be at least 2, got {particles!r}")
        if int(scenarios) < 2:
            raise ValueError(f"scenarios must be at least 2, got {scenarios!r}")
        if int(window) < 2:
            raise ValueError(f"window must be at least 2, got {window!r}")
        self.model = model
        self.resampler = resampler
        self.threshold_rule = threshold_rule
        self.weight_rule = weight_rule
        self.move_rule = move_rule
        self.particles = int(particles)
        self.scenarios = int(scenarios)
        self.window = int(window)
        self.scenario_simulation = bool(scenario_simulation)
        self.evidence = evidence
        self.history: deque[tuple[int, float]] = deque(maxlen=self.window)
        self._last: _Simulation | None = None

    @property
    def simulates(self) -> bool:
        """Whether a snapshot is simulated (a model was given)."""
        return self.model is not None

    def trend(self) -> float:
        """Least-squares slope of ESS/N per step over the history window."""
        if len(self.history) < 2:
            return 0.0
        steps = np.array([s for s, _ in self.history], dtype=np.float64)
        ratios = np.array([r for _, r in self.history])
        steps -= steps.mean()
        return float(np.dot(steps, ratios - ratios.mean()) / np.dot(steps, steps))

    def forecast(self, step: int, summary: WeightSummary, snapshot: Snapshot | None = None,
                 rng: np.random.Generator | None = None) -> Forecast:
        """The :class:`Forecast` after the weight state (and particle set) of ``step``.

        Call once per step, in order: the history and the previous simulation
        (for the surprise) are kept between calls. ``snapshot`` and ``rng``
        are needed for the simulation; without them only the history figures
        are filled.
        """
        self.history.append((int(step), float(summary.ess_ratio)))
        figures = dict(step=int(step), n=summary.n, ess_ratio=float(summary.ess_ratio), ess_trend=self.trend(),
                       distinct_ratio=summary.distinct / summary.n)
        previous, self._last = self._last, None
        if snapshot is None or self.model is None:
            return Forecast(**figures)
        if rng is None:
            raise ValueError("the simulation needs a random generator (rng)")
        if previous is not None and previous.step == step - 1:
            figures["log_predictive"], figures["surprise"] = previous.score(snapshot.observation)
        if self.scenario_simulation:
            simulation = self._last = _Simulation(self, int(step), snapshot, rng)
            figures.update(predicted_ess_ratio=float(simulation.ess.mean()) / simulation.m,
                           predicted_distinct_ratio=float(simulation.distinct.mean()) / simulation.m,
                           predicted_spread=float(simulation.spread.mean()), simulation=simulation)
        if self.evidence is not None and hasattr(self.evidence, "totals"):  # the evidence per arm
            self.evidence.observe(step, snapshot.particles, snapshot.weights, snapshot.observation, rng)
            figures.update(arm_evidence=self.evidence.totals(), arm_point_evidence=self.evidence.point_totals(),
                           arm_differences=tuple(self.evidence.differences), evidence_steps=self.evidence.steps)
        elif self.evidence is not None:  # after the simulation's draws, so they do not change
            self.evidence.observe(step, snapshot.particles, snapshot.weights, snapshot.observation, rng)
            figures.update(evidence=self.evidence.total, evidence_steps=len(self.evidence.differences))
        return Forecast(**figures)
