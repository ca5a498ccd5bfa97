"""``choose``: puts one of several moves in force, the *arms* (:data:`dtpf.information.layer.ARMS`:
plain resampling, the relative DT rule at PS 0 with likelihood weights, the paper's DT rule at
PS 0.81, roughening, the regularised kernel), from the evidence of the real observations
(:mod:`dtpf.system.choose`): each arm's windowed log Bayes factor against the *base* arm over the
last 20 steps. The base (``base``, default roughening) is in force when no other arm has the
evidence; below, "plain" stands for it. From plain it switches to the arm with the largest evidence
only when that exceeds ``enter`` (default log 999 with a cure as the base, log 99 with plain,
odds of 999 or 99 to 1) and the window's per-step differences are steady (their
mean at least ``steady`` standard errors above 0, default 2: on the video a difference of about
1 nat a step either way sums past log 99 by chance); it keeps a chosen arm while its evidence against
plain stays above ``leave`` (default log 3: the hysteresis), moves to another arm whose evidence
beats the chosen one's by ``enter``, and goes back to plain when the chosen arm's evidence fades
(unless another arm's exceeds ``enter``). It starts on the base; the first evidence comes at step 2.
With ``veto`` (the default) a second evidence must agree: the log-likelihood of the
observations at each copy's predicted *mean*, summed against plain's over the same window. An
arm is entered only while that sum is at least 0 and at least the arm in force's (its estimate
predicts the observations no worse than plain's and the chosen arm's), and left when it falls
below ``-leave``: a move that spreads the cloud wide
enough to hold the truth predicts better than a collapsed cloud, yet its estimate can be far
worse.
"""
from __future__ import annotations

import math

import numpy as np

from dtpf.messages.names import DEFAULT_CHOOSE_BASE
from dtpf.system.policies.base import POLICIES, PSDecision, PSPolicy, non_negative
from dtpf.system.predict import Forecast

__all__ = ["ChoosePS"]


@POLICIES.builtin("choose")
class ChoosePS(PSPolicy):
    """Puts in force the arm whose moves predict the real observations best (see the module docstring).

    Parameters
    ----------
    ps, max_change : optional
        Accepted and unused: each arm has its own PS (:data:`dtpf.information.layer.ARMS`).
    arms : sequence of str
        The arms to choose from (plain is always one); default all of them.
    enter : float, optional
        Log odds an arm's evidence must exceed to replace the base arm, or to beat the arm in force by (nats;
        default log 99 with plain as the base, log 999 with a cure as the base: leaving a cure the evaluation
        found never worse than plain asks for ten times the odds).
    leave : float
        The arm in force stays while its evidence against the base exceeds this (default log 3; at most
        ``enter``).
    window : int
        Steps of evidence summed per arm (default 20).
    particles : int
        M, the twin's copy of the entity's set (default 1000).
    steady : float
        Enter an arm (or replace the arm in force) only when the window's per-step differences have a mean
        at least this many standard errors above 0 (default 2; 0: the sum alone decides).
    veto : bool
        Enter an arm only while its predicted means' evidence against the base's is at least 0 and at least
        the arm in force's, and leave
        it when that falls below ``-leave`` (default True; False: the predictive evidence alone).
    base : str
        The arm in force when no other has the evidence (default roughening,
        :data:`dtpf.messages.names.DEFAULT_CHOOSE_BASE`); every threshold above is against this arm's copy.
        A run's ``choose_base`` "rehearse" has the system layer choose it before the run
        (:mod:`dtpf.system.rehearse`) and set :attr:`rehearsal`.
    move : str
        The run's own move after resampling: a user's (``--move file.py:NAME``) is one more arm, "own"
        (:func:`dtpf.information.layer.arms_for`).
    """

    simulates = True
    uses_evidence = True
    initial_preprocess = False
    chooses_arms = True

    def __init__(self, ps: float | None = None, *, max_change: float | None = None, arms=None,
                 enter: float | None = None, leave: float = math.log(3.0), window: int = 20,
                 particles: int = 1000, veto: bool = True, steady: float = 2.0, base: str = DEFAULT_CHOOSE_BASE,
                 move: str = "none"):
        from dtpf.information.layer import arms_for
        table = arms_for(move)
        chosen = tuple(table) if arms is None else tuple(arms)
        unknown = [a for a in (*chosen, base) if a not in table]
        if unknown:
            raise ValueError(f"unknown arm {unknown[0]!r}; expected some of {', '.join(table)}")
        self.arms = tuple(dict.fromkeys(("plain", *chosen, base)))
        self.base = base
        if enter is None:
            enter = math.log(99.0) if base == "plain" else math.log(999.0)
        self.enter = non_negative(enter, "enter")
        self.leave = float(leave)
        if not self.leave <= self.enter:
            raise ValueError(f"leave must be at most enter (hysteresis), got {leave!r} > {enter!r}")
        if int(window) < 1 or int(particles) < 1:
            raise ValueError(f"window and particles must be at least 1, got {window!r}, {particles!r}")
        self.window, self.particles = int(window), int(particles)
        self.veto = bool(veto)
        self.steady = float(steady)
        self._table = table
        #: The run's own move after resampling (the arm "own" when it is a user's).
        self.move = move
        #: The arm in force (the latest decision's; the arm the entity applies at the step being decided).
        self.arm = self.initial_arm = base
        #: The rehearsal that chose the base (:mod:`dtpf.system.rehearse`), or None. With one, the layers start on
        #: the default base and the first decision puts the rehearsed base in force.
        self.rehearsal = None

    @property
    def initial_ps(self) -> float:
        return self._table[self.initial_arm].ps

    def _decision(self, step: int, arm: str, reason: str, figures: dict) -> PSDecision:
        self.arm = arm
        chosen = self._table[arm]
        return PSDecision(chosen.ps, step + 1, self.name, reason, figures, preprocess=chosen.preprocess, arm=arm)

    def _beats(self, forecast: Forecast, arm: str, other: str) -> bool:
        """Whether ``arm``'s evidence exceeds ``other``'s by ``enter`` nats, and steadily: the mean of the
        window's per-step differences at least ``steady`` standard errors above 0."""
        evidence = forecast.arm_evidence
        if not evidence[arm] - evidence.get(other, 0.0) > self.enter:
            return False
        steps = forecast.arm_differences
        if not steps or self.steady <= 0:
            return True
        d = np.array([s.get(arm, 0.0) - s.get(other, 0.0) for s in steps])
        if d.size < 2:
            return False
        spread = float(np.std(d, ddof=1))
        return spread == 0.0 or float(np.mean(d)) / (spread / math.sqrt(d.size)) > self.steady

    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        if self.arm == self.initial_arm != self.base and not forecast.evidence_steps:
            # the rehearsed base, from the first decision on
            return self._decision(step, self.base, f"choose: {self.rehearsal.summary()}"
                                  if self.rehearsal is not None else f"choose: base {self.base}", {})
        if not forecast.arm_evidence:
            return self._decision(step, self.arm, f"choose: no evidence yet: {self.arm} kept", {})
        base = self.base
        # Evidence against the base arm's copy (the sums are against plain's: a difference of two sums).
        evidence = {a: e - forecast.arm_evidence.get(base, 0.0) for a, e in forecast.arm_evidence.items()}
        points = {} if not self.veto else {a: e - (forecast.arm_point_evidence or {}).get(base, 0.0)
                                           for a, e in (forecast.arm_point_evidence or {}).items()}
        current = self.arm
        floor = max(0.0, points.get(current, 0.0))  # an arm's estimate must predict no worse than the base's
        others = [a for a in self.arms                # and the arm in force's
                  if a != current and a != base and a in evidence and points.get(a, 0.0) >= floor]
        best = max(others, key=lambda a: evidence[a]) if others else None
        now = evidence.get(current, 0.0)
        vetoed = current != base and points.get(current, 0.0) < -self.leave
        if vetoed and best is not None and self._beats(forecast, best, base):
            arm, verdict = best, (f"{current}'s estimate predicts worse than {base}'s ({points[current]:.3g} < "
                                  f"{-self.leave:.3g} nats), {best} beats {base} by {evidence[best]:.3g} > "
                                  f"{self.enter:.3g}")
        elif vetoed:
            arm, verdict = base, (f"{current}'s estimate predicts worse than {base}'s ({points[current]:.3g} < "
                                  f"{-self.leave:.3g} nats)")
        elif current == base:
            if best is not None and self._beats(forecast, best, base):
                arm, verdict = best, f"{best} beats {base} by {evidence[best]:.3g} > {self.enter:.3g} nats"
            else:
                arm, verdict = base, f"no arm beats {base} by more than {self.enter:.3g} nats steadily"
        elif best is not None and self._beats(forecast, best, current):
            arm, verdict = best, f"{best} beats {current} by {evidence[best] - now:.3g} > {self.enter:.3g} nats"
        elif now > self.leave:
            arm, verdict = current, f"{current} still beats {base} by {now:.3g} > {self.leave:.3g} nats"
        elif best is not None and self._beats(forecast, best, base):
            arm, verdict = best, (f"{current} faded ({now:.3g} <= {self.leave:.3g} nats), {best} beats {base} by "
                                  f"{evidence[best]:.3g} > {self.enter:.3g}")
        else:
            arm, verdict = base, f"{current} faded ({now:.3g} <= {self.leave:.3g} nats against {base})"
        tried = ", ".join(f"{a} {evidence[a]:.3g}" + (f" (mean {points[a]:.3g})" if a in points else "")
                          for a in self.arms if a != base and a in evidence)
        reason = (f"choose: evidence against {base} over the last {forecast.evidence_steps} observations "
                  f"({tried}); {verdict}: {arm}")
        return self._decision(step, arm, reason, {"evidence": float(evidence.get(arm, 0.0))})
