"""The contract of a PS policy: from the degradation forecast to the degree factor PS.

A policy is a class deriving from :class:`PSPolicy`, with one verb, ``decide``::

    decision = policy.decide(step, forecast)     # forecast: dtpf.system.predict.Forecast
    decision.ps, decision.reason, decision.predicted

The decision made at step k applies from step k + 1 on (step k's set is being resampled while the decision is
made). Every policy keeps PS in [0, 1] and says why in ``reason``, with the figures it decided on in
``predicted`` (they go on the PS topic and so into the log).

The class is built with the run's options as keyword arguments: ``ps`` (the run's PS), ``max_change`` (its
``--ps-rate``), and any more its own ``__init__`` accepts with defaults. What the other layers need to know
of a policy are class attributes, its traits: :attr:`PSPolicy.simulates`, :attr:`PSPolicy.samples_observations`,
:attr:`PSPolicy.uses_evidence`, :attr:`PSPolicy.initial_preprocess` and :attr:`PSPolicy.constant`.

A built-in is a module of this package that registers its class with ``@POLICIES.builtin(name)``
(:mod:`dtpf.messages.family`); a user's policy is a subclass of :class:`PSPolicy` named by reference
(``--policy path/to/file.py:MyPolicy``), built on a small case before a run (:func:`adapt`).
"""
from __future__ import annotations

import inspect
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

from dtpf.messages.arrays import check_probability
from dtpf.messages.family import POLICIES
from dtpf.messages.references import ReferenceLoadError, a
from dtpf.system.predict import Forecast

__all__ = ["POLICIES", "PSDecision", "PSPolicy", "PAPER_PS", "MAX_CHANGE", "COMMAND_FIELDS", "limit", "forecast_figures",
           "change", "non_negative", "adapt"]

#: PS of the paper's experiments (section 4.1).
PAPER_PS = 0.81
#: Default largest change of PS per step of the adaptive policies.
MAX_CHANGE = 0.25

#: PSCommand field of each figure a decision may carry in ``predicted``.
COMMAND_FIELDS = {
    "ess_ratio": "predicted_ess_ratio",
    "distinct_ratio": "predicted_distinct_ratio",
    "spread": "predicted_spread",
    "error": "predicted_error",
    "evidence": "evidence",
    "surprise": "surprise",
}


@dataclass(frozen=True)
class PSDecision:
    """The PS to use from ``applies_from_step`` on, and why.

    ``predicted`` holds the figures the policy based its choice on, by the
    names of :data:`COMMAND_FIELDS` (for example ``{"ess_ratio": 0.3}``);
    empty for a fixed policy.
    """

    ps: float
    applies_from_step: int
    policy: str
    reason: str
    predicted: dict[str, float] = field(default_factory=dict)
    #: False: no preprocessing from ``applies_from_step`` on (the decision "off"); PS is kept for later.
    preprocess: bool = True
    #: The chosen arm in force from ``applies_from_step`` on (the choosing policy; None for the others).
    arm: str | None = None

    def command_fields(self) -> dict:
        """The fields of the :class:`~dtpf.messages.models.PSCommand` that carries this decision."""
        fields = dict(ps=self.ps, applies_from_step=self.applies_from_step, policy=self.policy, reason=self.reason,
                      preprocess=self.preprocess, arm=self.arm)
        for name, command_field in COMMAND_FIELDS.items():
            fields[command_field] = self.predicted.get(name)
        return fields


def limit(current: float, target: float, max_change: float) -> float:
    """``target`` clipped to [0, 1] and to at most ``max_change`` away from ``current``."""
    step = min(max(target - current, -max_change), max_change)
    return min(1.0, max(0.0, round(current + step, 12)))


def forecast_figures(forecast: Forecast, **extra) -> dict[str, float]:
    """The forecast's predicted figures that exist and are finite, by :data:`COMMAND_FIELDS` name."""
    values = {"ess_ratio": forecast.predicted_ess_ratio, "distinct_ratio": forecast.predicted_distinct_ratio,
              "spread": forecast.predicted_spread, "surprise": forecast.surprise, **extra}
    return {name: float(v) for name, v in values.items() if v is not None and math.isfinite(v)}


class PSPolicy(ABC):
    """Turns the degradation forecast of step k into the PS for step k + 1."""

    name: str
    #: True if :meth:`decide` uses the twin's simulation (predicted figures, ``what_if``).
    simulates: bool = False

    @property
    @abstractmethod
    def initial_ps(self) -> float:
        """PS in force before the first decision."""

    #: True if the simulation draws observations (``sample_observation``: the what-if).
    samples_observations: bool = False
    #: True if :meth:`decide` reads the evidence of the real observations (:mod:`dtpf.system.evidence`).
    uses_evidence: bool = False
    #: Whether the preprocessing runs before the first decision.
    initial_preprocess: bool = True
    #: True if every decision is the initial PS with preprocessing on (the information layer need not wait).
    constant: bool = False
    #: True if every decision names an *arm* (:data:`dtpf.information.layer.ARMS`) instead of a PS alone: the
    #: class takes ``base`` (the run's ``choose_base``), has ``arms``, ``particles`` and ``window``, and its
    #: predictor scores each arm on the real observations (:class:`dtpf.system.choose.ArmEvidence`).
    chooses_arms: bool = False

    @abstractmethod
    def decide(self, step: int, forecast: Forecast) -> PSDecision:
        """The decision after the forecast made at ``step``."""


class Adaptive(PSPolicy):
    """A policy that moves PS by at most ``max_change`` a step, on the twin's simulation."""

    simulates = True
    samples_observations = True

    def __init__(self, ps: float, max_change: float):
        self.ps = check_probability(ps, "PS")
        if not 0.0 < float(max_change) <= 1.0:
            raise ValueError(f"max_change must be in (0, 1], got {max_change!r}")
        self.max_change = float(max_change)
        self._initial = self.ps

    @property
    def initial_ps(self) -> float:
        return self._initial

    def _move(self, target: float) -> tuple[float, float]:
        """(old, new) PS after a rate-limited move towards ``target``."""
        old = self.ps
        self.ps = limit(old, target, self.max_change)
        return old, self.ps


def change(old: float, new: float) -> str:
    return f"PS {old:g} -> {new:g}" if new != old else f"PS {new:g} kept"


def non_negative(value: float, name: str) -> float:
    if not float(value) >= 0.0:
        raise ValueError(f"{name} must be non-negative, got {value!r}")
    return float(value)



def adapt(obj, where: str):
    """A user's policy class, checked: a concrete subclass of PSPolicy that can be built with ``ps`` and
    ``max_change``. Its ``name`` is the reference unless the class gives its own (set by the registry)."""
    if not (isinstance(obj, type) and issubclass(obj, PSPolicy)):
        raise ReferenceLoadError(f"{where}: expected a subclass of dtpf.system.policy.PSPolicy, got "
                                 f"{'the class ' + obj.__name__ if isinstance(obj, type) else a(obj)}")
    if inspect.isabstract(obj):
        missing = ", ".join(sorted(obj.__abstractmethods__))
        raise ReferenceLoadError(f"{where}: {obj.__name__} does not implement {missing}")
    try:
        policy = obj(ps=PAPER_PS, max_change=MAX_CHANGE)
    except TypeError as exc:
        raise ReferenceLoadError(f"{where}: {obj.__name__}(ps=..., max_change=...) failed: {exc}; accept both "
                                 f"keywords (and give every other parameter a default)") from exc
    except Exception as exc:
        raise ReferenceLoadError(f"{where}: {obj.__name__}(ps={PAPER_PS}, max_change={MAX_CHANGE}) raised "
                                 f"{type(exc).__name__}: {exc}") from exc
    ps = policy.initial_ps
    if not (isinstance(ps, (int, float)) and 0.0 <= float(ps) <= 1.0):
        raise ReferenceLoadError(f"{where}: initial_ps is {ps!r}, expected a number in [0, 1]")
    return obj
