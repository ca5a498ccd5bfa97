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

With ``publish`` = H (the entity's ``--forecast H``) a thread of the twin's own
also publishes the forecast of each finished step H steps ahead as a
:class:`~dtpf.messages.models.ForecastBand` on ``dtpf/<twin>/entity/forecast_band``
(the numbers a ``forecast`` question of that step gets), so that Foxglove draws
the band ahead of the estimate. It never holds a step: a step that finishes
while the thread still works on an earlier one replaces the one waiting, and
the one replaced is skipped (counted in :attr:`ForecastPublisher.skipped`).
"""
from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass

import numpy as np

from dtpf.entity.calls import ModelCalls
from dtpf.entity.forecast import forecast, seconds_steps
from dtpf.messages import queries
from dtpf.messages.codec import encode
from dtpf.messages.models import MAX_FORECAST_HORIZON, Estimate, ForecastBand, Time
from dtpf.shell.queries import Queryable, worker

__all__ = ["LiveAnswers", "ForecastPublisher", "live_answers", "STATE_RATE", "FORECAST_RATE"]

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
    dt: float | None = None  #: seconds from the step before (a driven twin's step), else None


class LiveAnswers:
    """The state and forecast queryables of one twin, answered from the step :meth:`keep` was last given."""

    def __init__(self, shell, config, model, publish: int = 0):
        self.shell, self.config, self.model = shell, config, model
        self.latest: _Latest | None = None
        self.takes_dt = ModelCalls(model).takes_dt
        twin = config.twin
        #: The thread publishing each step's forecast (``publish`` > 0), else None.
        self.publisher = ForecastPublisher(shell, config, model, publish) if publish else None
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
        drive = getattr(step, "drive", None)
        self.latest = latest = _Latest(int(step.step), estimate, time.time_ns(), step.particles, step.weights,
                                       None if drive is None else drive.dt)
        if self.publisher is not None:
            self.publisher.offer(latest)

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
            queries.check_values(latest.particles.size + latest.weights.size, selector.max_bytes)
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
        if selector.particles:
            queries.check_values(latest.particles.size + latest.weights.size, selector.max_bytes)
        dts = None
        if selector.horizon_s is not None:
            if not self.takes_dt:
                raise queries.SelectorError(f"twin {self.config.twin}'s model takes no dt: its steps have no "
                                            f"length in seconds; ask horizon= (steps)")
            _, dts = seconds_steps(selector.horizon_s, selector.dt)
        ahead = forecast(self.model, latest.particles, latest.weights, latest.step, selector.horizon, dts,
                         seed=self.config.seed, twin=self.config.twin, dt=selector.dt, control=selector.control)
        body = {"twin": self.config.twin, "seed": self.config.seed, **ahead.as_json(particles=selector.particles)}
        return queries.check_size(json.dumps(body).encode(), selector.max_bytes)

    def close(self) -> None:
        for queryable in self.queryables:
            queryable.close()
        if self.publisher is not None:
            self.publisher.close()


class ForecastPublisher:
    """Publishes the forecast of each step it is offered, ``horizon`` steps ahead, on a thread of its own.

    One step waits at most: :meth:`offer` replaces a step still waiting (skipped, counted) and never blocks.
    A driven twin's forecast steps last as long as the step it starts from (its drive's dt; the last step
    with a dt above zero when two observations share a stamp) and hold zero control. A forecast that cannot
    be made (a model that fails) is said once in the log and skipped.
    """

    def __init__(self, shell, config, model, horizon: int):
        if not 1 <= int(horizon) <= MAX_FORECAST_HORIZON:
            raise ValueError(f"--forecast must be 1 .. {MAX_FORECAST_HORIZON} steps, got {horizon}")
        self.shell, self.config, self.model, self.horizon = shell, config, model, int(horizon)
        self.takes_dt = ModelCalls(model).takes_dt
        self.published = self.skipped = self.failed = 0
        #: The last step length above zero (a driven twin's), which the forecast steps take.
        self.dt: float | None = None
        self._waiting: _Latest | None = None
        self._closed = False
        self._ready = threading.Condition()
        self._thread = threading.Thread(target=self._run, name=f"forecast-{config.twin}", daemon=True)
        self._thread.start()

    def offer(self, latest: _Latest) -> None:
        """Hand over a finished step (the filter's thread): at once, never waiting."""
        with self._ready:
            if self._waiting is not None:
                self.skipped += 1
            self._waiting = latest
            self._ready.notify()

    def message(self, latest: _Latest) -> ForecastBand | None:
        """The ForecastBand of ``latest`` (None: a driven twin before a step with a dt above zero)."""
        if self.takes_dt and latest.dt:
            self.dt = latest.dt
        dt = self.dt if self.takes_dt else None
        if self.takes_dt and not dt:
            return None
        ahead = forecast(self.model, latest.particles, latest.weights, latest.step, self.horizon,
                         seed=self.config.seed, twin=self.config.twin, dt=dt)
        return ForecastBand(**self.shell.header(latest.step), ahead=ahead.points_of_message())

    def _run(self) -> None:
        while True:
            with self._ready:
                while self._waiting is None and not self._closed:
                    self._ready.wait()
                if self._closed:
                    return
                latest, self._waiting = self._waiting, None
            try:
                message = self.message(latest)
                if message is not None:
                    self.shell.publish(message)
                    self.published += 1
            except Exception as error:  # a model that fails, a session that closes: said once, the run goes on
                self.failed += 1
                if self.failed == 1 and not self._closed and not getattr(self.shell, "stopping", False):
                    self.shell.log.warning("twin %s: the forecast of step %d was not published (further ones "
                                           "are counted): %s: %s", self.config.twin, latest.step,
                                           type(error).__name__, error)

    def close(self) -> None:
        with self._ready:
            self._closed = True
            self._ready.notify()


def _with_message(head: dict, name: str, message: bytes) -> bytes:
    """``head`` as a JSON object with the encoded message (JSON bytes) as its field ``name``."""
    text = json.dumps(head)
    return f'{text[:-1]}{", " if len(text) > 2 else ""}"{name}": '.encode() + message + b"}"


def live_answers(shell, config, model, publish: int = 0) -> LiveAnswers:
    """The answers of a twin on ``shell``'s session (the entity service's one hook); ``publish`` > 0: also
    each step's forecast that many steps ahead. If Zenoh refuses a queryable the twin runs without it (said
    once in the log) rather than not at all."""
    return LiveAnswers(shell, config, model, publish)
