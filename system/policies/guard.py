"""``guard``: decides whether to preprocess at all. Each step it tries, on the
same simulated scenarios, "off" (the set resampled as it is) and PS, and
turns the preprocessing on for the next step only if PS is predicted to
lower the error against off with one-sided confidence 95% (the paired
mean difference below -t SE, t = 1.895, the 95% quantile of Student's t
with S - 1 = 7 degrees of freedom for the S = 8 scenarios); otherwise
off. With no particle set to simulate it decides off. It starts off: the
first step is never preprocessed.
"""
from __future__ import annotations

import math

from dtpf.messages.arrays import check_probability
from dtpf.system.policies.base import PAPER_PS, POLICIES, PSDecision, PSPolicy, forecast_figures, non_negative
from dtpf.system.predict import Forecast

__all__ = ["Guard", "GuardPS"]


class Guard(PSPolicy):
    """A policy that decides only whether to preprocess, with a fixed PS; it starts off."""

    simulates = True
    initial_preprocess = False

    def __init__(self, ps: float):
        self.ps = check_probability(ps, "PS")

    @property
    def initial_ps(self) -> float:
        return self.ps


@POLICIES.builtin("guard")
class GuardPS(Guard):
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

    samples_observations = True
    #: One-sided 95% quantile of Student's t with 7 degrees of freedom.
    T95_7 = 1.895

    def __init__(self, ps: float = PAPER_PS, *, max_change: float | None = None, confidence: float = T95_7):
        super().__init__(ps)
        self.confidence = non_negative(confidence, "confidence")

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        if forecast.simulation is None:
            return PSDecision(self.ps, step + 1, self.name, "guard: no particle set to simulate: off",
                              forecast_figures(forecast), preprocess=False)
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
        return PSDecision(self.ps, step + 1, self.name, reason, forecast_figures(forecast, error=chosen.error),
                          preprocess=preprocess)
