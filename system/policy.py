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

The policies are :data:`POLICIES`, one module each in :mod:`dtpf.system.policies` whose docstring says
what the policy does (``help(dtpf.system.policies.guard)``; ``dtpf run --help`` lists them with a line
each); :mod:`~dtpf.system.policies.base` states the contract once. :func:`get` also takes a user's policy
class by reference, ``path/to/file.py:MyPolicy``, or by the name an installed package registers in the
entry-point group ``dtpf.policies``.

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
