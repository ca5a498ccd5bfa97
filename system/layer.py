"""The system layer, without transport: keeps the history of weight states
and asks its PS policy for the PS of the next step.

::

    layer = SystemLayer(policy.get("fixed", ps=0.81))
    decision = layer.observe(step, summary)
"""
from __future__ import annotations

from information.mirror import WeightSummary
from system.policy import PSDecision, PSPolicy

__all__ = ["SystemLayer"]


class SystemLayer:
    """Degradation prediction and PS control for one twin."""

    def __init__(self, policy: PSPolicy):
        self.policy = policy
        self.history: list[tuple[int, WeightSummary]] = []
        self.decisions: list[PSDecision] = []

    @property
    def ps(self) -> float:
        """The PS of the latest decision (the policy's initial PS before any)."""
        return self.decisions[-1].ps if self.decisions else self.policy.initial_ps

    def observe(self, step: int, summary: WeightSummary) -> PSDecision:
        """Record the weight state of ``step`` and decide the PS from ``step + 1`` on."""
        self.history.append((step, summary))
        decision = self.policy.decide(step, summary)
        self.decisions.append(decision)
        return decision
