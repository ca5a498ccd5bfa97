"""A PS policy of your own: a subclass of PSPolicy with ``initial_ps`` and ``decide``.

    dtpf run --policy docs/examples/components/policy.py:LowEssPS
"""
from dtpf import PSDecision, PSPolicy


class LowEssPS(PSPolicy):
    """PS 0 (the wider branch of Eq. 30) while the mirrored ESS/N is below one half, else the run's PS."""

    def __init__(self, ps: float = 0.81, max_change: float | None = None, below: float = 0.5):
        self.ps, self.below = float(ps), float(below)

    @property
    def initial_ps(self) -> float:
        return self.ps

    def decide(self, step, forecast) -> PSDecision:
        low = forecast.ess_ratio < self.below
        ps = 0.0 if low else self.ps
        reason = f"ESS/N {forecast.ess_ratio:.3f} {'<' if low else '>='} {self.below:g}: PS {ps:g}"
        return PSDecision(ps, step + 1, self.name, reason)
