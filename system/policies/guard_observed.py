"""``guard-observed``: decides the same, from the real observations instead
of simulated ones (:mod:`dtpf.system.evidence`): on while, over the last 20
steps, preprocessing predicted them better than not by a log Bayes factor
above log 19 (odds of 19 to 1). It starts off; the first difference comes
at step 3 (each takes two steps), and until 20 are in, the sum is over
those there are. It needs no ``sample_observation``.
"""
from __future__ import annotations

import math

from dtpf.system.policies.base import PAPER_PS, POLICIES, PSDecision, forecast_figures, non_negative
from dtpf.system.policies.guard import Guard
from dtpf.system.predict import Forecast

__all__ = ["GuardObservedPS"]


@POLICIES.builtin("guard-observed")
class GuardObservedPS(Guard):
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

    uses_evidence = True

    def __init__(self, ps: float = PAPER_PS, *, max_change: float | None = None, log_odds: float = math.log(19.0)):
        super().__init__(ps)
        self.log_odds = non_negative(log_odds, "log_odds")

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        figures = forecast_figures(forecast, evidence=forecast.evidence)
        if forecast.evidence is None:
            return PSDecision(self.ps, step + 1, self.name, "guard-observed: no particle set: off", figures,
                              preprocess=False)
        steps, total = forecast.evidence_steps, forecast.evidence
        preprocess = total > self.log_odds
        reason = (f"guard-observed: the last {steps} observations favour PS {self.ps:g} over off by "
                  f"{total:.3g} nats ({'>' if preprocess else '<='} log odds {self.log_odds:.3g}): "
                  f"{'on' if preprocess else 'off'}")
        return PSDecision(self.ps, step + 1, self.name, reason, figures, preprocess=preprocess)
