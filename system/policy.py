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

Policies (:data:`POLICIES`; each is a module of :mod:`dtpf.system.policies`, whose
:mod:`~dtpf.system.policies.base` states the contract once; :func:`get` also takes a user's
policy class by reference, ``path/to/file.py:MyPolicy``, or by the name an installed package
registers in the entry-point group ``dtpf.policies``):

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

from dtpf.messages.family import POLICIES as FAMILY
from dtpf.system.policies.base import (
    COMMAND_FIELDS, MAX_CHANGE, PAPER_PS, PSDecision, PSPolicy, limit,
)
from dtpf.system.policies.choose import ChoosePS
from dtpf.system.policies.fixed import FixedPS
from dtpf.system.policies.guard import GuardPS
from dtpf.system.policies.guard_observed import GuardObservedPS
from dtpf.system.policies.predictive import PredictivePS
from dtpf.system.policies.rule import RulePS

__all__ = ["PSDecision", "PSPolicy", "FixedPS", "RulePS", "PredictivePS", "GuardPS", "GuardObservedPS", "ChoosePS",
           "POLICIES", "get", "policy_class", "limit", "PAPER_PS", "MAX_CHANGE", "COMMAND_FIELDS"]

#: The built-in policy classes by name (every module of :mod:`dtpf.system.policies`).
POLICIES: dict[str, type[PSPolicy]] = FAMILY.builtins()


def policy_class(name: str) -> type[PSPolicy]:
    """The class ``name`` names: a built-in, an installed package's, or a user's reference (checked)."""
    return FAMILY.get(name)


def get(name: str, **options) -> PSPolicy:
    """A new policy ``name`` built with ``options``, or a ValueError listing the names."""
    return policy_class(name)(**options)
