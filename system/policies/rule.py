"""``rule``: thresholds with hysteresis on the predicted degradation. It
enters the *degraded* state when the forecast ESS/N, the forecast distinct
ancestors / N or the surprise crosses its entry threshold, and leaves it
only when all three are back past their (stricter) exit thresholds, so a
figure hovering at a threshold does not make PS flap. Degraded, PS moves
towards ``degraded_ps`` (default 0: every processed particle takes the
plain branch of Eq. 30, which scatters it twice as widely around its
large partner, mean |x_tilde - x_m| = |x_l| / 2 against |x_l| / 4 on the
mixed branch: more diversity); healthy, towards ``ps``.
"""
from __future__ import annotations

from dtpf.messages.arrays import check_probability
from dtpf.system.policies.base import MAX_CHANGE, PAPER_PS, POLICIES, Adaptive, PSDecision, change, forecast_figures
from dtpf.system.predict import Forecast

__all__ = ["RulePS"]


@POLICIES.builtin("rule")
class RulePS(Adaptive):
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
        reason = f"rule: {state} [{figures}]: {change(old, new)}"
        if new != target:
            reason += f" (towards {target:g}, at most {self.max_change:g} per step)"
        return PSDecision(new, step + 1, self.name, reason, forecast_figures(forecast))
