"""What a live entity answers: its state now and its forecast, off the filter's path.

The entity keeps its latest finished step (:meth:`LiveAnswers.keep`: references,
no copy, no encoding: the filter never writes a finished step's arrays again)
and two queryables answer from it on workers of their own
(:mod:`dtpf.shell.queries`), so a question never delays a step and is answered
at once, also while a live twin waits for its next observation::

    dtpf/<twin>/entity/state?particles=true     {"twin", "step", "service", "estimate": <Estimate>, ...}
    dtpf/<twin>/entity/forecast?horizon=20      {"twin", "seed", "from_step", "steps": [{step, mean, var, ...}]}

The estimate is the message the entity publishes (the JSON a log holds); the
particle set is the weighted set it was made from (before resampling), the set
the forecast propagates with the twin's own model and the streams of
:func:`dtpf.entity.forecast.forecast_stream`. Selectors and bounds:
:mod:`dtpf.messages.queries`.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass

import numpy as np

from dtpf.entity.forecast import forecast
from dtpf.messages import queries
from dtpf.messages.codec import encode
from dtpf.messages.models import Estimate, Time
from dtpf.shell.queries import Queryable, worker

__all__ = ["LiveAnswers", "live_answers", "STATE_RATE", "FORECAST_RATE"]

#: State questions a second a twin answers (``burst`` at once); forecasts, which propagate the whole set.
STATE_RATE, STATE_BURST = 100.0, 200
FORECAST_RATE, FORECAST_BURST = 10.0, 20


@dataclass(frozen=True)
class _Latest:
    step: int
    estimate: dict
    made_ns: int
    particles: np.ndarray
    weights: np.ndarray


class LiveAnswers:
    """The state and forecast queryables of one twin, answered from the step :meth:`keep` was last given."""

    def __init__(self, shell, config, model):
        self.shell, self.config, self.model = shell, config, model
        self.latest: _Latest | None = None
        twin = config.twin
        self.queryables: list[Queryable] = []
        try:
            self.queryables.append(Queryable(shell.session, queries.key(twin, "state"), self.answer_state,
                                             on=worker("state"), rate=STATE_RATE, burst=STATE_BURST, log=shell.log))
            self.queryables.append(Queryable(shell.session, queries.key(twin, "forecast"), self.answer_forecast,
                                             on=worker("forecast"), rate=FORECAST_RATE, burst=FORECAST_BURST,
                                             log=shell.log))
        except Exception as error:  # zenoh.ZError: a session that refuses the declaration
            shell.log.warning("twin %s answers no questions: %s", twin, error)

    def keep(self, step, estimate: dict) -> None:
        """The filter's finished ``step`` (a :class:`~dtpf.entity.filter.FilterStep`) and the fields of the
        estimate it publishes: the latest, replacing the one before (one reference swap)."""
        self.latest = _Latest(int(step.step), estimate, time.time_ns(), step.particles, step.weights)

    def _latest(self) -> _Latest:
        latest = self.latest
        if latest is None:
            raise queries.SelectorError(f"twin {self.config.twin} has no estimate yet: its first step has not "
                                        f"finished")
        return latest

    def answer_state(self, key: str, text: str) -> bytes:
        selector = queries.parse("state", text)
        latest = self._latest()
        fields = dict(latest.estimate)
        fields.setdefault("stamp", Time.from_ns(latest.made_ns))
        head = {"twin": self.config.twin, "step": latest.step, "service": self.shell.state.value}
        if self.shell.detail:
            head["detail"] = self.shell.detail
        if selector.particles:
            head["particles"] = latest.particles.tolist()
            head["weights"] = latest.weights.tolist()
        return queries.check_size(_with_message(head, "estimate", encode(Estimate(**fields))), selector.max_bytes)

    def answer_forecast(self, key: str, text: str) -> bytes:
        selector = queries.parse("forecast", text)
        latest = self._latest()
        n = latest.particles.shape[0]
        if n * selector.horizon > queries.MAX_FORECAST_WORK:
            raise queries.SelectorError(f"horizon={selector.horizon} with N = {n} particles is more than "
                                        f"{queries.MAX_FORECAST_WORK} particle-steps; at most horizon="
                                        f"{max(1, queries.MAX_FORECAST_WORK // n)}")
        ahead = forecast(self.model, latest.particles, latest.weights, latest.step, selector.horizon,
                         seed=self.config.seed, twin=self.config.twin, dt=selector.dt, control=selector.control)
        body = {"twin": self.config.twin, "seed": self.config.seed, **ahead.as_json(particles=selector.particles)}
        return queries.check_size(json.dumps(body).encode(), selector.max_bytes)

    def close(self) -> None:
        for queryable in self.queryables:
            queryable.close()


def _with_message(head: dict, name: str, message: bytes) -> bytes:
    """``head`` as a JSON object with the encoded message (JSON bytes) as its field ``name``."""
    text = json.dumps(head)
    return f'{text[:-1]}{", " if len(text) > 2 else ""}"{name}": '.encode() + message + b"}"


def live_answers(shell, config, model) -> LiveAnswers:
    """The answers of a twin on ``shell``'s session (the entity service's one hook). If Zenoh refuses a
    queryable the twin runs without it (said once in the log) rather than not at all."""
    return LiveAnswers(shell, config, model)
