"""PS policies: from the degradation forecast to the degree factor PS.

A policy is a plain object with one verb, ``decide``::

    from dtpf.system import policy
    ps_policy = policy.get("rule", ps=0.81, max_change=0.25)
    decision = ps_policy.decide(step, forecast)     # forecast: dtpf.system.predict.Forecast
    decision.ps, decision.reason, decision.predicted

The decision made at step k applies from step k + 1 on (step k's set is
being resampled while the decision is made). Every policy keeps PS in [0, 1]; the adaptive ones move it by
at most ``max_change`` per step and say why in ``reason``, with the figures
they decided on in ``predicted`` (they go on the PS topic and so into the log).

Policies (:data:`POLICIES`):

- ``fixed``: PS never changes (the paper's 0.81).
- ``rule``: thresholds with hysteresis on the predicted degradation. It
  enters the *degraded* state when the forecast ESS/N, the forecast distinct
  ancestors / N or the surprise crosses its entry threshold, and leaves it
  only when all three are back past their (stricter) exit thresholds, so a
  figure hovering at a threshold does not make PS flap. Degraded, PS moves
  towards ``degraded_ps`` (default 0: every processed particle takes the
  plain branch of Eq. 30, which scatters it twice as widely around its
  large partner, mean |x_tilde - x_m| = |x_l| / 2 against |x_l| / 4 on the
  mixed branch: more diversity); healthy, towards ``ps``.
- ``predictive``: tries PS - max_change, PS and PS + max_change (clipped to
  [0, 1]) on the twin's simulated next steps (:meth:`Forecast.what_if`) and
  moves to the candidate with the lowest predicted estimation error, but
  only if it beats the current PS by more than ``confidence`` standard
  errors of the paired difference over the simulated scenarios; otherwise
  PS stays.
- ``guard``: decides whether to preprocess at all. Each step it tries, on the
  same simulated scenarios, "off" (the set resampled as it is) and PS, and
  turns the preprocessing on for the next step only if PS is predicted to
  lower the error against off with one-sided confidence 95% (the paired
  mean difference below -t SE, t = 1.895, the 95% quantile of Student's t
  with S - 1 = 7 degrees of freedom for the S = 8 scenarios); otherwise
  off. With no particle set to simulate it decides off. It starts off: the
  first step is never preprocessed.
- ``guard-observed``: decides the same, from the real observations instead
  of simulated ones (:mod:`dtpf.system.evidence`): on while, over the last 20
  steps, preprocessing predicted them better than not by a log Bayes factor
  above log 19 (odds of 19 to 1). It starts off; the first difference comes
  at step 3 (each takes two steps), and until 20 are in, the sum is over
  those there are. It needs no ``sample_observation``.

- ``choose``: puts one of several moves in force, the *arms* (:data:`dtpf.information.layer.ARMS`:
  plain resampling, the relative DT rule at PS 0 with likelihood weights, the paper's DT rule at
  PS 0.81, roughening, the regularised kernel), from the evidence of the real observations
  (:mod:`dtpf.system.choose`): each arm's windowed log Bayes factor against the *base* arm over the
  last 20 steps. The base (``base``, default roughening) is in force when no other arm has the
  evidence; below, "plain" stands for it. From plain it switches to the arm with the largest evidence
  only when that exceeds ``enter`` (default log 999 with a cure as the base, log 99 with plain,
  odds of 999 or 99 to 1) and the window's per-step differences are steady (their
  mean at least ``steady`` standard errors above 0, default 2: on the video a difference of about
  1 nat a step either way sums past log 99 by chance); it keeps a chosen arm while its evidence against
  plain stays above ``leave`` (default log 3: the hysteresis), moves to another arm whose evidence
  beats the chosen one's by ``enter``, and goes back to plain when the chosen arm's evidence fades
  (unless another arm's exceeds ``enter``). It starts on the base; the first evidence comes at step 2.
  With ``veto`` (the default) a second evidence must agree: the log-likelihood of the
  observations at each copy's predicted *mean*, summed against plain's over the same window. An
  arm is entered only while that sum is at least 0 and at least the arm in force's (its estimate
  predicts the observations no worse than plain's and the chosen arm's), and left when it falls
  below ``-leave``: a move that spreads the cloud wide
  enough to hold the truth predicts better than a collapsed cloud, yet its estimate can be far
  worse.

A policy that needs the twin's simulation sets :attr:`PSPolicy.simulates`;
the system layer then gives its predictor the particle set of each step.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from dtpf.messages.arrays import check_probability
from dtpf.messages.names import DEFAULT_CHOOSE_BASE
from dtpf.system.predict import Forecast

__all__ = ["PSDecision", "PSPolicy", "FixedPS", "RulePS", "PredictivePS", "GuardPS", "GuardObservedPS", "ChoosePS",
           "POLICIES", "get", "limit"]

#: PS of the paper's experiments (section 4.1).
PAPER_PS = 0.81
#: Default largest change of PS per step of the adaptive policies.
MAX_CHANGE = 0.25

#: PSCommand field of each figure a decision may carry in ``predicted``.
COMMAND_FIELDS = {
    "ess_ratio": "predicted_ess_ratio",
    "distinct_ratio": "predicted_distinct_ratio",
    "spread": "predicted_spread",
    "error": "predicted_error",
    "evidence": "evidence",
    "surprise": "surprise",
}


@dataclass(frozen=True)
class PSDecision:
    """The PS to use from ``applies_from_step`` on, and why.

    ``predicted`` holds the figures the policy based its choice on, by the
    names of :data:`COMMAND_FIELDS` (for example ``{"ess_ratio": 0.3}``);
    empty for a fixed policy.
    """

    ps: float
    applies_from_step: int
    policy: str
    reason: str
    predicted: dict[str, float] = field(default_factory=dict)
    #: False: no preprocessing from ``applies_from_step`` on (the decision "off"); PS is kept for later.
    preprocess: bool = True
    #: The chosen arm in force from ``applies_from_step`` on (the choosing policy; None for the others).
    arm: str | None = None

    def command_fields(self) -> dict:
        """The fields of the :class:`~dtpf.messages.models.PSCommand` that carries this decision."""
        fields = dict(ps=self.ps, applies_from_step=self.applies_from_step, policy=self.policy, reason=self.reason,
                      preprocess=self.preprocess, arm=self.arm)
        for name, command_field in COMMAND_FIELDS.items():
            fields[command_field] = self.predicted.get(name)
        return fields


def limit(current: float, target: float, max_change: float) -> float:
    """``target`` clipped to [0, 1] and to at most ``max_change`` away from ``current``."""
    step = min(max(target - current, -max_change), max_change)
    return min(1.0, max(0.0, round(current + step, 12)))


def _figures(forecast: Forecast, **extra) -> dict[str, float]:
    """The forecast's predicted figures that exist and are finite, by :data:`COMMAND_FIELDS` name."""
    values = {"ess_ratio": forecast.predicted_ess_ratio, "distinct_ratio": forecast.predicted_distinct_ratio,
              "spread": forecast.predicted_spread, "surprise": forecast.surprise, **extra}
    return {name: float(v) for name, v in values.items() if v is not None and math.isfinite(v)}


class PSPolicy(ABC):
    """Turns the degradation forecast of step k into the PS for step k + 1."""

    name: str
    #: True if :meth:`decide` uses the twin's simulation (predicted figures, ``what_if``).
    simulates: bool = False

    @property
    @abstractmethod
    def initial_ps(self) -> float:
        """PS in force before the first decision."""

    #: True if the simulation draws observations (``sample_observation``: the what-if).
    samples_observations: bool = False
    #: True if :meth:`decide` reads the evidence of the real observations (:mod:`dtpf.system.evidence`).
    uses_evidence: bool = False
    #: Whether the preprocessing runs before the first decision.
    initial_preprocess: bool = True
    #: True if every decision is the initial PS with preprocessing on (the information layer need not wait).
    constant: bool = False

    @abstractmethod
    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        """The decision after the forecast made at ``step``."""


class FixedPS(PSPolicy):
    """PS never changes (the paper's setting, PS = 0.81). ``max_change`` is accepted and unused."""

    name = "fixed"
    constant = True

    def __init__(self, ps: float = PAPER_PS, max_change: float | None = None):
        self.ps = check_probability(ps, "PS")

    @property
    def initial_ps(self) -> float:
        return self.ps

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        return PSDecision(self.ps, step + 1, self.name, f"fixed policy: PS = {self.ps:g}")


class _Adaptive(PSPolicy):
    simulates = True
    samples_observations = True

    def __init__(self, ps: float, max_change: float):
        self.ps = check_probability(ps, "PS")
        if not 0.0 < float(max_change) <= 1.0:
            raise ValueError(f"max_change must be in (0, 1], got {max_change!r}")
        self.max_change = float(max_change)
        self._initial = self.ps

    @property
    def initial_ps(self) -> float:
        return self._initial

    def _move(self, target: float) -> tuple[float, float]:
        """(old, new) PS after a rate-limited move towards ``target``."""
        old = self.ps
        self.ps = limit(old, target, self.max_change)
        return old, self.ps


def _change(old: float, new: float) -> str:
    return f"PS {old:g} -> {new:g}" if new != old else f"PS {new:g} kept"


class RulePS(_Adaptive):
    """Thresholds with hysteresis on the predicted degradation (see the module docstring).

    Parameters
    ----------
    ps : float
        PS when healthy, and the initial PS.
    degraded_ps : float
        PS aimed at while degradation is predicted.
    max_change : float
        Largest change of PS per step.
    ess_enter, ess_exit : float
        Degraded when the next ESS/N (simulated, else the trend's
        extrapolation) falls below ``ess_enter``; healthy again above
        ``ess_exit``.
    distinct_enter, distinct_exit : float
        The same for the next distinct ancestors / N (simulated, else the
        observed ratio).
    surprise_enter, surprise_exit : float
        The same for the surprise of the observation (nats), when known.
    """

    name = "rule"

    def __init__(self, ps: float = PAPER_PS, *, degraded_ps: float = 0.0, max_change: float = MAX_CHANGE,
                 ess_enter: float = 0.15, ess_exit: float = 0.25, distinct_enter: float = 0.2,
                 distinct_exit: float = 0.3, surprise_enter: float = 3.0, surprise_exit: float = 1.0):
        super().__init__(ps, max_change)
        self.healthy_ps = self._initial
        self.degraded_ps = check_probability(degraded_ps, "degraded PS")
        pairs = {"ess": (ess_enter, ess_exit), "distinct": (distinct_enter, distinct_exit)}
        for name, (enter, leave) in pairs.items():
            if not enter <= leave:
                raise ValueError(f"{name}_enter must be <= {name}_exit (hysteresis), got {enter!r} > {leave!r}")
        if not surprise_enter >= surprise_exit:
            raise ValueError(f"surprise_enter must be >= surprise_exit (hysteresis), "
                             f"got {surprise_enter!r} < {surprise_exit!r}")
        self.ess_enter, self.ess_exit = float(ess_enter), float(ess_exit)
        self.distinct_enter, self.distinct_exit = float(distinct_enter), float(distinct_exit)
        self.surprise_enter, self.surprise_exit = float(surprise_enter), float(surprise_exit)
        self.degraded = False

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        ess, distinct, surprise = forecast.next_ess_ratio, forecast.next_distinct_ratio, forecast.surprise
        if not self.degraded:
            triggers = []
            if ess < self.ess_enter:
                triggers.append(f"next ESS/N {ess:.3f} < {self.ess_enter:g}")
            if distinct < self.distinct_enter:
                triggers.append(f"next distinct/N {distinct:.3f} < {self.distinct_enter:g}")
            if surprise is not None and surprise > self.surprise_enter:
                triggers.append(f"surprise {surprise:.2f} > {self.surprise_enter:g} nats")
            self.degraded = bool(triggers)
            state = "degradation predicted (" + "; ".join(triggers) + ")" if triggers else "healthy"
        else:
            recovered = (ess > self.ess_exit and distinct > self.distinct_exit
                         and (surprise is None or surprise < self.surprise_exit))
            self.degraded = not recovered
            state = "recovered" if recovered else "still degraded"
        figures = f"next ESS/N {ess:.3f}, next distinct/N {distinct:.3f}" + (
            f", surprise {surprise:.2f}" if surprise is not None else "")
        target = self.degraded_ps if self.degraded else self.healthy_ps
        old, new = self._move(target)
        reason = f"rule: {state} [{figures}]: {_change(old, new)}"
        if new != target:
            reason += f" (towards {target:g}, at most {self.max_change:g} per step)"
        return PSDecision(new, step + 1, self.name, reason, _figures(forecast))


class PredictivePS(_Adaptive):
    """Tries candidate PS values on the twin's simulated next steps (see the module docstring).

    Parameters
    ----------
    ps : float
        Initial PS.
    max_change : float
        Largest change of PS per step; also the spacing of the candidates.
    candidates : int
        Candidates evenly spaced over [PS - max_change, PS + max_change]
        (clipped to [0, 1]); odd, so the current PS is one of them.
    confidence : float
        A candidate replaces the current PS only if its predicted error is
        lower by more than ``confidence`` standard errors of the paired
        difference (0: always the lowest).
    """

    name = "predictive"

    def __init__(self, ps: float = PAPER_PS, *, max_change: float = MAX_CHANGE, candidates: int = 3,
                 confidence: float = 1.0):
        super().__init__(ps, max_change)
        if int(candidates) < 3 or int(candidates) % 2 == 0:
            raise ValueError(f"candidates must be odd and at least 3, got {candidates!r}")
        self.candidates = int(candidates)
        self.confidence = _non_negative(confidence, "confidence")

    def candidate_values(self) -> list[float]:
        """The PS values tried at the next decision (the current PS included)."""
        offsets = np.linspace(-self.max_change, self.max_change, self.candidates)
        return sorted({self.ps} | {limit(self.ps, self.ps + float(o), self.max_change) for o in offsets if o != 0})

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        if forecast.simulation is None:
            return PSDecision(self.ps, step + 1, self.name,
                              f"predictive: no particle set to simulate, PS {self.ps:g} kept", _figures(forecast))
        outcomes = forecast.what_if(self.candidate_values())
        current = next(o for o in outcomes if o.ps == self.ps)
        best = min(outcomes, key=lambda o: (o.error, abs(o.ps - self.ps)))
        diff = best.errors - current.errors
        se = float(diff.std(ddof=1)) / math.sqrt(diff.size) if diff.size > 1 else 0.0
        tried = ", ".join(f"{o.ps:g}: {o.error:.4g}" for o in outcomes)
        if best.ps != current.ps and float(diff.mean()) < -self.confidence * se:
            old, new = self._move(best.ps)
            verdict = f"PS {best.ps:g} predicted better by {-diff.mean():.3g} (SE {se:.2g})"
            chosen = best
        else:
            old = new = self.ps
            verdict = "no candidate predicted better beyond the noise" if best.ps != current.ps else \
                "the current PS predicted best"
            chosen = current
        reason = (f"predictive: predicted error per candidate PS ({tried}) over "
                  f"{diff.size} simulated steps; {verdict}: {_change(old, new)}")
        return PSDecision(new, step + 1, self.name, reason, _figures(forecast, error=chosen.error))


def _non_negative(value: float, name: str) -> float:
    if not float(value) >= 0.0:
        raise ValueError(f"{name} must be non-negative, got {value!r}")
    return float(value)


class _Guard(PSPolicy):
    """A policy that decides only whether to preprocess, with a fixed PS; it starts off."""

    simulates = True
    initial_preprocess = False

    def __init__(self, ps: float):
        self.ps = check_probability(ps, "PS")

    @property
    def initial_ps(self) -> float:
        return self.ps


class GuardPS(_Guard):
    """Preprocess only where the twin's simulation predicts it helps (see the module docstring).

    Parameters
    ----------
    ps : float
        The PS used when the preprocessing is on.
    max_change : float, optional
        Accepted and unused (PS does not change).
    confidence : float
        The preprocessing is turned on only if its predicted error is lower
        than that of off by more than ``confidence`` standard errors of the
        paired difference (default 1.895: one-sided 95% for a t with 7
        degrees of freedom, S = 8 scenarios).
    """

    name = "guard"
    samples_observations = True
    #: One-sided 95% quantile of Student's t with 7 degrees of freedom.
    T95_7 = 1.895

    def __init__(self, ps: float = PAPER_PS, *, max_change: float | None = None, confidence: float = T95_7):
        super().__init__(ps)
        self.confidence = _non_negative(confidence, "confidence")

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        if forecast.simulation is None:
            return PSDecision(self.ps, step + 1, self.name, "guard: no particle set to simulate: off",
                              _figures(forecast), preprocess=False)
        off, on = forecast.what_if([None, self.ps])
        diff = on.errors - off.errors
        se = float(diff.std(ddof=1)) / math.sqrt(diff.size) if diff.size > 1 else 0.0
        gain = -float(diff.mean())
        preprocess = gain > self.confidence * se
        verdict = (f"PS {self.ps:g} predicted better by {gain:.3g} > {self.confidence:g} SE" if preprocess else
                   f"PS {self.ps:g} not predicted better beyond {self.confidence:g} SE")
        reason = (f"guard: predicted error off {off.error:.4g}, PS {self.ps:g} {on.error:.4g} over {diff.size} "
                  f"simulated steps (SE of the difference {se:.2g}); {verdict}: {'on' if preprocess else 'off'}")
        chosen = on if preprocess else off
        return PSDecision(self.ps, step + 1, self.name, reason, _figures(forecast, error=chosen.error),
                          preprocess=preprocess)


class GuardObservedPS(_Guard):
    """Preprocess only while the real observations favour it (see the module docstring).

    Parameters
    ----------
    ps : float
        The PS used when the preprocessing is on (and by the evidence's *on* arm).
    max_change : float, optional
        Accepted and unused.
    log_odds : float
        On when the windowed log Bayes factor of on against off exceeds this
        (default log 19: odds of 19 to 1).
    """

    name = "guard-observed"
    uses_evidence = True

    def __init__(self, ps: float = PAPER_PS, *, max_change: float | None = None, log_odds: float = math.log(19.0)):
        super().__init__(ps)
        self.log_odds = _non_negative(log_odds, "log_odds")

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        figures = _figures(forecast, evidence=forecast.evidence)
        if forecast.evidence is None:
            return PSDecision(self.ps, step + 1, self.name, "guard-observed: no particle set: off", figures,
                              preprocess=False)
        steps, total = forecast.evidence_steps, forecast.evidence
        preprocess = total > self.log_odds
        reason = (f"guard-observed: the last {steps} observations favour PS {self.ps:g} over off by "
                  f"{total:.3g} nats ({'>' if preprocess else '<='} log odds {self.log_odds:.3g}): "
                  f"{'on' if preprocess else 'off'}")
        return PSDecision(self.ps, step + 1, self.name, reason, figures, preprocess=preprocess)


class ChoosePS(PSPolicy):
    """Puts in force the arm whose moves predict the real observations best (see the module docstring).

    Parameters
    ----------
    ps, max_change : optional
        Accepted and unused: each arm has its own PS (:data:`dtpf.information.layer.ARMS`).
    arms : sequence of str
        The arms to choose from (plain is always one); default all of them.
    enter : float, optional
        Log odds an arm's evidence must exceed to replace the base arm, or to beat the arm in force by (nats;
        default log 99 with plain as the base, log 999 with a cure as the base: leaving a cure the evaluation
        found never worse than plain asks for ten times the odds).
    leave : float
        The arm in force stays while its evidence against the base exceeds this (default log 3; at most
        ``enter``).
    window : int
        Steps of evidence summed per arm (default 20).
    particles : int
        M, the twin's copy of the entity's set (default 1000).
    steady : float
        Enter an arm (or replace the arm in force) only when the window's per-step differences have a mean
        at least this many standard errors above 0 (default 2; 0: the sum alone decides).
    veto : bool
        Enter an arm only while its predicted means' evidence against the base's is at least 0 and at least
        the arm in force's, and leave
        it when that falls below ``-leave`` (default True; False: the predictive evidence alone).
    base : str
        The arm in force when no other has the evidence (default roughening,
        :data:`dtpf.messages.names.DEFAULT_CHOOSE_BASE`); every threshold above is against this arm's copy.
    """

    name = "choose"
    simulates = True
    uses_evidence = True
    initial_preprocess = False

    def __init__(self, ps: float | None = None, *, max_change: float | None = None, arms=None,
                 enter: float | None = None, leave: float = math.log(3.0), window: int = 20,
                 particles: int = 1000, veto: bool = True, steady: float = 2.0, base: str = DEFAULT_CHOOSE_BASE):
        from dtpf.information.layer import ARMS
        chosen = tuple(ARMS) if arms is None else tuple(arms)
        unknown = [a for a in (*chosen, base) if a not in ARMS]
        if unknown:
            raise ValueError(f"unknown arm {unknown[0]!r}; expected some of {', '.join(ARMS)}")
        self.arms = tuple(dict.fromkeys(("plain", *chosen, base)))
        self.base = base
        if enter is None:
            enter = math.log(99.0) if base == "plain" else math.log(999.0)
        self.enter = _non_negative(enter, "enter")
        self.leave = float(leave)
        if not self.leave <= self.enter:
            raise ValueError(f"leave must be at most enter (hysteresis), got {leave!r} > {enter!r}")
        if int(window) < 1 or int(particles) < 1:
            raise ValueError(f"window and particles must be at least 1, got {window!r}, {particles!r}")
        self.window, self.particles = int(window), int(particles)
        self.veto = bool(veto)
        self.steady = float(steady)
        self._table = ARMS
        #: The arm in force (the latest decision's; the arm the entity applies at the step being decided).
        self.arm = self.initial_arm = base

    @property
    def initial_ps(self) -> float:
        return self._table[self.initial_arm].ps

    def _decision(self, step: int, arm: str, reason: str, figures: dict) -> PSDecision:
        self.arm = arm
        chosen = self._table[arm]
        return PSDecision(chosen.ps, step + 1, self.name, reason, figures, preprocess=chosen.preprocess, arm=arm)

    def _beats(self, forecast: Forecast, arm: str, other: str) -> bool:
        """Whether ``arm``'s evidence exceeds ``other``'s by ``enter`` nats, and steadily: the mean of the
        window's per-step differences at least ``steady`` standard errors above 0."""
        evidence = forecast.arm_evidence
        if not evidence[arm] - evidence.get(other, 0.0) > self.enter:
            return False
        steps = forecast.arm_differences
        if not steps or self.steady <= 0:
            return True
        d = np.array([s.get(arm, 0.0) - s.get(other, 0.0) for s in steps])
        if d.size < 2:
            return False
        spread = float(np.std(d, ddof=1))
        return spread == 0.0 or float(np.mean(d)) / (spread / math.sqrt(d.size)) > self.steady

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        if not forecast.arm_evidence:
            return self._decision(step, self.arm, f"choose: no evidence yet: {self.arm} kept", {})
        base = self.base
        # Evidence against the base arm's copy (the sums are against plain's: a difference of two sums).
        evidence = {a: e - forecast.arm_evidence.get(base, 0.0) for a, e in forecast.arm_evidence.items()}
        points = {} if not self.veto else {a: e - (forecast.arm_point_evidence or {}).get(base, 0.0)
                                           for a, e in (forecast.arm_point_evidence or {}).items()}
        current = self.arm
        floor = max(0.0, points.get(current, 0.0))  # an arm's estimate must predict no worse than the base's
        others = [a for a in self.arms                # and the arm in force's
                  if a != current and a != base and a in evidence and points.get(a, 0.0) >= floor]
        best = max(others, key=lambda a: evidence[a]) if others else None
        now = evidence.get(current, 0.0)
        vetoed = current != base and points.get(current, 0.0) < -self.leave
        if vetoed and best is not None and self._beats(forecast, best, base):
            arm, verdict = best, (f"{current}'s estimate predicts worse than {base}'s ({points[current]:.3g} < "
                                  f"{-self.leave:.3g} nats), {best} beats {base} by {evidence[best]:.3g} > "
                                  f"{self.enter:.3g}")
        elif vetoed:
            arm, verdict = base, (f"{current}'s estimate predicts worse than {base}'s ({points[current]:.3g} < "
                                  f"{-self.leave:.3g} nats)")
        elif current == base:
            if best is not None and self._beats(forecast, best, base):
                arm, verdict = best, f"{best} beats {base} by {evidence[best]:.3g} > {self.enter:.3g} nats"
            else:
                arm, verdict = base, f"no arm beats {base} by more than {self.enter:.3g} nats steadily"
        elif best is not None and self._beats(forecast, best, current):
            arm, verdict = best, f"{best} beats {current} by {evidence[best] - now:.3g} > {self.enter:.3g} nats"
        elif now > self.leave:
            arm, verdict = current, f"{current} still beats {base} by {now:.3g} > {self.leave:.3g} nats"
        elif best is not None and self._beats(forecast, best, base):
            arm, verdict = best, (f"{current} faded ({now:.3g} <= {self.leave:.3g} nats), {best} beats {base} by "
                                  f"{evidence[best]:.3g} > {self.enter:.3g}")
        else:
            arm, verdict = base, f"{current} faded ({now:.3g} <= {self.leave:.3g} nats against {base})"
        tried = ", ".join(f"{a} {evidence[a]:.3g}" + (f" (mean {points[a]:.3g})" if a in points else "")
                          for a in self.arms if a != base and a in evidence)
        reason = (f"choose: evidence against {base} over the last {forecast.evidence_steps} observations "
                  f"({tried}); {verdict}: {arm}")
        return self._decision(step, arm, reason, {"evidence": float(evidence.get(arm, 0.0))})


#: Policy classes by name.
POLICIES: dict[str, type[PSPolicy]] = {"fixed": FixedPS, "rule": RulePS, "predictive": PredictivePS,
                                       "guard": GuardPS, "guard-observed": GuardObservedPS, "choose": ChoosePS}


def get(name: str, **options) -> PSPolicy:
    """A new policy ``name`` built with ``options``, or a ValueError listing the names."""
    try:
        cls = POLICIES[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown PS policy {name!r}; expected one of {', '.join(POLICIES)}") from None
    return cls(**options)
