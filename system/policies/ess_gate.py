"""``ess-gate``: preprocess only while the mirrored ESS/N is below a threshold (default 0.5), PS fixed at the
run's ``ps``; no simulation.

The gate reads the newest weight-state figure a decision sees without the twin's simulation:
:attr:`~dtpf.system.predict.Forecast.ess_ratio`, the ESS/N (Eq. 25, ESS = 1 / sum_i w_i^2) of step k's
weights as the information layer mirrors them (:class:`~dtpf.information.mirror.WeightSummary`). A
decision made at step k applies from step k + 1 on, so the gate follows ESS/N one step late:

    preprocess at k + 1  <=>  ESS_k / N < threshold

It starts off (no figure before the first decision: step 1 is never preprocessed). ``predicted`` stays
empty: the figure is observed, not forecast (the weight-state topic logs it); the reason names it.
"""
from __future__ import annotations

from dtpf.messages.arrays import check_probability
from dtpf.system.policies.base import PAPER_PS, POLICIES, PSDecision, PSPolicy, forecast_figures
from dtpf.system.predict import Forecast

__all__ = ["EssGatePS"]


@POLICIES.builtin("ess-gate")
class EssGatePS(PSPolicy):
    """Preprocess only while the mirrored ESS/N is below a threshold (default 0.5), PS fixed, no simulation.

    On for step k + 1 exactly when ESS/N of step k is below ``threshold`` (see the module docstring).

    Parameters
    ----------
    ps : float
        The PS used while the preprocessing is on.
    max_change : float, optional
        Accepted and unused (PS does not change).
    threshold : float
        On for step k + 1 when ESS/N of step k is below this, in (0, 1] (default 0.5).
    """

    simulates = False
    initial_preprocess = False

    def __init__(self, ps: float = PAPER_PS, *, max_change: float | None = None, threshold: float = 0.5):
        self.ps = check_probability(ps, "PS")
        if not 0.0 < float(threshold) <= 1.0:
            raise ValueError(f"the ESS/N threshold must be in (0, 1], got {threshold!r}")
        self.threshold = float(threshold)

    @property
    def initial_ps(self) -> float:
        return self.ps

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        ratio = forecast.ess_ratio
        preprocess = ratio < self.threshold
        reason = (f"ess-gate: ESS/N {ratio:.3f} at step {step} {'<' if preprocess else '>='} threshold "
                  f"{self.threshold:g}: {'on' if preprocess else 'off'} (PS {self.ps:g})")
        return PSDecision(self.ps, step + 1, self.name, reason, forecast_figures(forecast), preprocess=preprocess)
