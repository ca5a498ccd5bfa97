"""``fixed``: PS never changes (the paper's 0.81).
"""
from __future__ import annotations

from dtpf.messages.arrays import check_probability
from dtpf.system.policies.base import PAPER_PS, POLICIES, PSDecision, PSPolicy
from dtpf.system.predict import Forecast

__all__ = ["FixedPS"]


@POLICIES.builtin("fixed")
class FixedPS(PSPolicy):
    """PS never changes (the paper's setting, PS = 0.81). ``max_change`` is accepted and unused."""

    constant = True

    def __init__(self, ps: float = PAPER_PS, max_change: float | None = None):
        self.ps = check_probability(ps, "PS")

    @property
    def initial_ps(self) -> float:
        return self.ps

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        return PSDecision(self.ps, step + 1, self.name, f"fixed policy: PS = {self.ps:g}")
