"""PS policies: from the mirrored weight state to the degree factor PS.

A policy is a plain object with one verb, ``decide``::

    from system import policy
    ps_policy = policy.get("fixed")            # PS = 0.81, the paper's value
    decision = ps_policy.decide(step, summary)
    decision.ps, decision.reason

The decision made at step k applies from step k + 1 on (DESIGN.md, "One
filter step"). The predictive and rule-based policies of the system layer
plug in behind the same interface.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

from information.mirror import WeightSummary
from messages.arrays import check_probability

__all__ = ["PSDecision", "PSPolicy", "FixedPS", "POLICIES", "get"]

#: PS of the paper's experiments (section 4.1).
PAPER_PS = 0.81


@dataclass(frozen=True)
class PSDecision:
    """The PS to use from ``applies_from_step`` on, and why.

    ``predicted`` holds the figures a predictive policy based its choice on
    (for example ``{"ess_ratio": 0.3}``); empty for a fixed policy.
    """

    ps: float
    applies_from_step: int
    policy: str
    reason: str
    predicted: dict[str, float] = field(default_factory=dict)


class PSPolicy(ABC):
    """Turns the weight state of step k into the PS for step k + 1."""

    name: str

    @property
    @abstractmethod
    def initial_ps(self) -> float:
        """PS in force before the first decision."""

    @abstractmethod
    def decide(self, step: int, summary: WeightSummary) -> PSDecision:
        """The decision after seeing the weight state of ``step``."""


class FixedPS(PSPolicy):
    """PS never changes (the paper's setting, PS = 0.81)."""

    name = "fixed"

    def __init__(self, ps: float = PAPER_PS):
        self.ps = check_probability(ps, "PS")

    @property
    def initial_ps(self) -> float:
        return self.ps

    def decide(self, step: int, summary: WeightSummary) -> PSDecision:
        return PSDecision(self.ps, step + 1, self.name, f"fixed policy: PS = {self.ps:g}")


#: Policy classes by name.
POLICIES: dict[str, type[PSPolicy]] = {"fixed": FixedPS}


def get(name: str, **options) -> PSPolicy:
    """A new policy ``name`` built with ``options``, or a ValueError listing the names."""
    try:
        cls = POLICIES[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown PS policy {name!r}; expected one of {', '.join(POLICIES)}") from None
    return cls(**options)
