"""The system layer, without transport: predicts degradation at the next step
and asks its PS policy for the PS of the next step.

Each step k it receives the information layer's weight-state summary and,
when its policy simulates, the preprocessed particle set of k (a
:class:`~dtpf.system.predict.Snapshot`: particles, weights, observation; over
Zenoh, the message on ``dtpf/<twin>/information/preprocessed``). The
:class:`~dtpf.system.predict.Predictor` turns them into a
:class:`~dtpf.system.predict.Forecast`, the policy into a decision::

    layer = SystemLayer.from_config(config)
    decision = layer.observe(step, summary, Snapshot.of(particles, weights, z))

The simulation draws from ``stream(seed, twin, k, "system")``, so the Zenoh
service, the in-process pipeline and ``dtpf verify`` decide identically.

A driven twin's steps come from several sensors at uneven times: ``observe``
takes the step's ``sensor`` and ``drive``, and the evidence and the
simulation see the model through :class:`~dtpf.entity.calls.StepModel`, so
the step's observation is weighed by its own sensor's likelihood and the
next step is forecast over an interval like the last.
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import replace

import numpy as np

from dtpf.information.mirror import WeightSummary, summarise
from dtpf.messages.names import DEFAULT_CHOOSE_BASE, REHEARSE
from dtpf.messages.streams import stream
from dtpf.system.policy import PSDecision, PSPolicy
from dtpf.system.predict import Forecast, Predictor, Snapshot

__all__ = ["SystemLayer"]

#: The reasons a rehearsal could not run that this process has logged (each once).
_SAID: set[str] = set()


def _rehearsed(policy: PSPolicy, config, model, policy_options: dict | None) -> PSPolicy:
    """The choosing ``policy`` of a run whose ``choose_base`` is "rehearse": on the base its rehearsal of ``model``
    chose (:mod:`dtpf.system.rehearse`), without the arms it dropped, starting on the default base (the layers
    do; its first decision puts the base in force). A model that cannot be rehearsed keeps ``policy`` as it is,
    on the default base, and the reason is logged once a process."""
    from dtpf.system.rehearse import rehearse, why_not

    reason = why_not(model)
    if reason is not None:
        if reason not in _SAID:
            _SAID.add(reason)
            logging.getLogger(__name__).warning("choose_base rehearse: %s; the base is %s", reason,
                                                DEFAULT_CHOOSE_BASE)
        return policy
    try:
        rehearsal = rehearse(model, policy.arms, n=config.particles, steps=config.steps,
                             threshold_rule=config.threshold, move=config.jitter, particles=policy.particles)
    except Exception as error:  # noqa: BLE001 - a user's model may raise anything; the run itself will say it
        reason = f"the rehearsal failed: {type(error).__name__}: {str(error)[:300]}"
        if reason not in _SAID:
            _SAID.add(reason)
            logging.getLogger(__name__).warning("choose_base rehearse: %s; the base is %s", reason,
                                                DEFAULT_CHOOSE_BASE)
        return policy
    options = dict(policy_options or {})
    options.setdefault("arms", tuple(a for a in policy.arms if a not in rehearsal.dropped))
    chosen = type(policy)(ps=config.ps, max_change=config.ps_rate, base=rehearsal.arm, move=config.jitter, **options)
    chosen.arm = chosen.initial_arm = DEFAULT_CHOOSE_BASE
    chosen.rehearsal = rehearsal
    return chosen


class SystemLayer:
    """Degradation prediction and PS control for one twin.

    Parameters
    ----------
    policy : PSPolicy
    predictor : Predictor, optional
        Default: one without a model (history figures only).
    seed, twin :
        Key of the random streams: step k draws from ``stream(seed, twin, k, "system")``.
    keep : int, optional
        Keep only the last ``keep`` summaries, forecasts and decisions (a service
        on a long run); None keeps all (the experiments read them).
    """

    def __init__(self, policy: PSPolicy, predictor: Predictor | None = None, *, seed: int = 0, twin: str = "twin",
                 keep: int | None = None, view=None):
        self.policy = policy
        #: The driven model's :class:`~dtpf.entity.calls.StepModel` the predictor uses, or None.
        self.view = view
        self.predictor = predictor if predictor is not None else Predictor()
        self.seed = int(seed)
        self.twin = twin
        self.history: deque[tuple[int, WeightSummary]] = deque(maxlen=keep)
        self.forecasts: deque[Forecast] = deque(maxlen=keep)
        self.decisions: deque[PSDecision] = deque(maxlen=keep)
        #: Steps whose forecast the model failed (:meth:`_model_failed`).
        self.model_failures = 0

    @classmethod
    def from_config(cls, config, twin: str | None = None, model=None, keep: int | None = None,
                    policy_options: dict | None = None) -> "SystemLayer":
        """The system layer of a :class:`~dtpf.messages.config.RunConfig` (``twin`` overrides its twin id;
        ``policy_options``: more keyword arguments of the policy's class, e.g. ``ChoosePS(window=50)``).

        A simulating policy gets a predictor over the run's model (``model``, or
        the one the configuration names), resampler and preprocessing options;
        the fixed policy one without a model.
        """
        from dtpf.entity import model_ref
        from dtpf.system import policy as ps_policy
        from dtpf.system.evidence import Evidence

        cls_ = ps_policy.policy_class(config.policy)
        rehearsing = cls_.chooses_arms and config.choose_base == REHEARSE
        base = {"base": config.choose_base} if cls_.chooses_arms and config.choose_base and not rehearsing else {}
        if cls_.chooses_arms:
            base["move"] = config.jitter
        policy = cls_(ps=config.ps, max_change=config.ps_rate, **base, **(policy_options or {}))
        if policy.simulates and model is None:
            model = model_ref.resolve(config.model_ref)
        if rehearsing:
            policy = _rehearsed(policy, config, model, policy_options)
        view = None
        if model is not None:
            from dtpf.entity.calls import ModelCalls, StepModel
            if ModelCalls(model).driven:
                model = view = StepModel(model)
        options = dict(threshold_rule=config.threshold, weight_rule=config.weight_rule, move_rule=config.move_rule)
        evidence = Evidence(model, config.ps, **options) if policy.uses_evidence else None
        if policy.chooses_arms:
            from dtpf.system.choose import ArmEvidence
            evidence = ArmEvidence(model, policy.arms, n=config.particles, threshold_rule=config.threshold,
                                   particles=policy.particles, window=policy.window, move=config.jitter)
        predictor = Predictor(model, resampler=config.resampler, **options,
                              scenario_simulation=policy.samples_observations, evidence=evidence) \
            if policy.simulates else Predictor()
        return cls(policy, predictor, seed=config.seed, twin=twin or config.twin, keep=keep, view=view)

    @property
    def needs_particles(self) -> bool:
        """Whether :meth:`observe` uses the particle set (the policy simulates and the predictor can)."""
        return self.policy.simulates and self.predictor.simulates

    @property
    def ps(self) -> float:
        """The PS of the latest decision (the policy's initial PS before any)."""
        return self.decisions[-1].ps if self.decisions else self.policy.initial_ps

    def observe(self, step: int, summary: WeightSummary, snapshot: Snapshot | None = None, *, sensor=None,
                drive=None) -> PSDecision:
        """Record the state of ``step`` and decide the PS from ``step + 1`` on.

        ``snapshot`` is used when :attr:`needs_particles`; without it the
        forecast holds the history figures only. ``sensor``, ``drive``: a
        driven step's (module docstring).
        """
        if self.view is not None:
            self.view.hold(sensor, drive)
        self.history.append((step, summary))
        forecast = None
        if self.needs_particles and snapshot is not None:
            try:
                forecast = self.predictor.forecast(step, summary, snapshot,
                                                   stream(self.seed, self.twin, step, "system"))
            except Exception as error:  # noqa: BLE001 - a user's model may raise anything; the entity says it too
                self._model_failed(step, error)
        if forecast is None:
            forecast = self.predictor.forecast(step, summary)
        decision = self.policy.decide(step, forecast)
        self.forecasts.append(replace(forecast, simulation=None))  # the figures; not the simulated sets
        self.decisions.append(decision)
        return decision

    def _model_failed(self, step: int, error: Exception) -> None:
        """A model call of the forecast (the what-if simulations, the arms' copies) raised at ``step``: logged once
        a twin, and the step's forecast holds the history figures only (the policy keeps what it has)."""
        self.predictor.history.pop()      # the figures of this step are appended again
        if not self.model_failures:
            logging.getLogger("dtpf.system").warning(
                "twin %s: the model raised %s: %s in the system layer's forecast at step %d; that step's forecast "
                "holds the weight history alone (further failures are counted)", self.twin, type(error).__name__,
                str(error)[:300], step)
        self.model_failures += 1


#: The configurations whose compiled kernels :func:`warm_up` has loaded in this process: numba compiles per
#: type of argument, not per twin, so a fleet's service warms up once per kind of twin.
_WARMED: set[tuple] = set()


def warm_up(config, model) -> None:
    """Run a throwaway system layer of ``config`` for four steps on a synthetic set of the size class of
    its N, read-only as a decoded set is, so that the compiled kernels its policy takes (the evidence's
    propagation and likelihood, the rules, the what-if simulations) are loaded before the first real step.

    On a cold cache, ``--policy guard-observed`` compiled for seconds at step 4, past the lockstep timeout
    (three steps degraded). Once per process and kind of twin; best effort: what the synthetic set cannot
    run (a model that refuses a zero observation) is left to the real steps. No state of a real twin is
    touched: the layer, its streams and its set are its own.
    """
    from dtpf.information.rules import size_class

    size = size_class(config.particles)
    key = (config.policy, config.model_ref, config.resampler, str(config.threshold), config.weight_rule,
           config.move_rule, size)
    if key in _WARMED:
        return
    _WARMED.add(key)
    layer = SystemLayer.from_config(config, twin="warm-up", model=model, keep=4)
    if not layer.needs_particles:
        return
    rng = np.random.default_rng(0)
    try:
        particles = np.asarray(model.initial_particles(size, rng), dtype=np.float64).reshape(size, -1)
        particles.flags.writeable = False
        from dtpf.entity.base import sensor_dims

        sensor, m = next(iter(sensor_dims(model).items()))  # a driven model's first sensor
        observation = np.zeros(m)
        for step in range(1, 5):
            weights = rng.random(size)
            weights /= weights.sum()
            weights.flags.writeable = False
            driven = {} if layer.view is None else {"sensor": sensor}
            layer.observe(step, summarise(particles, weights, config.threshold, size),
                          Snapshot.of(particles, weights, observation), **driven)
    except Exception as error:  # the real steps report what is wrong; this was only a warm-up
        logging.getLogger("dtpf.system").debug("warm-up stopped early: %s", error)
