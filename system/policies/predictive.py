"""``predictive``: tries PS - max_change, PS and PS + max_change (clipped to
[0, 1]) on the twin's simulated next steps (:meth:`Forecast.what_if`) and
moves to the candidate with the lowest predicted estimation error, but
only if it beats the current PS by more than ``confidence`` standard
errors of the paired difference over the simulated scenarios; otherwise
PS stays.
"""
from __future__ import annotations

import math

import numpy as np

from dtpf.system.policies.base import MAX_CHANGE, PAPER_PS, POLICIES, Adaptive, PSDecision, change, forecast_figures, limit, non_negative
from dtpf.system.predict import Forecast

__all__ = ["PredictivePS"]


@POLICIES.builtin("predictive")
class PredictivePS(Adaptive):
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


    def __init__(self, ps: float = PAPER_PS, *, max_change: float = MAX_CHANGE, candidates: int = 3,
                 confidence: float = 1.0):
        super().__init__(ps, max_change)
        if int(candidates) < 3 or int(candidates) % 2 == 0:
            raise ValueError(f"candidates must be odd and at least 3, got {candidates!r}")
        self.candidates = int(candidates)
        self.confidence = non_negative(confidence, "confidence")

    def candidate_values(self) -> list[float]:
        """The PS values tried at the next decision (the current PS included)."""
        offsets = np.linspace(-self.max_change, self.max_change, self.candidates)
        return sorted({self.ps} | {limit(self.ps, self.ps + float(o), self.max_change) for o in offsets if o != 0})

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        if forecast.simulation is None:
            return PSDecision(self.ps, step + 1, self.name,
                              f"predictive: no particle set to simulate, PS {self.ps:g} kept", forecast_figures(forecast))
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
                  f"{diff.size} simulated steps; {verdict}: {change(old, new)}")
        return PSDecision(new, step + 1, self.name, reason, forecast_figures(forecast, error=chosen.error))
