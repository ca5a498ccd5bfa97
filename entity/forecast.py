"""Forecast: a weighted particle set propagated H steps ahead without observations.

The particle set of step k (its states and normalised weights, the set the
estimate of step k is made from) is propagated by the model's state equation
to steps k + 1 .. k + H; the weights stay as they are, since no observation
reweighs them. Each step gives the weighted mean and variance per component
and a 95% band: the 2.5% and 97.5% weighted quantiles of each component (an
interval of the predictive distribution itself, which a many-peaked forecast
such as the growth model's does not fit to mean +- 1.96 sd)::

    from dtpf.entity.forecast import forecast
    ahead = forecast(model, particles, weights, step=12, horizon=5, seed=7, twin="ungm-1")
    ahead.mean[4], ahead.lower[4], ahead.upper[4]     # step 17

Random numbers: step k + h draws from :func:`forecast_stream` (seed, twin, k,
h), the SeedSequence of the entity's stream of step k (:mod:`dtpf.messages.streams`)
spawned under the key (:data:`FORECAST_KEY`, h). A spawned sequence mixes more
words than any stream of the run, so a forecast draws none of the numbers a
run draws and every run keeps its numbers; the same set, seed, twin and step
give the same forecast, and a longer horizon begins with the shorter one.

A driven model (:mod:`dtpf.entity.base`) gets ``dt`` seconds a step (one value, or
one a step) and the ``control`` held over the horizon (zeros when none is given):
a what-if. A horizon in seconds is steps of ``dt`` (:func:`seconds_steps`: the
last one shorter, so that they add up to it)::

    ahead = forecast(model, particles, weights, 12, *seconds_steps(2.0, 0.3), seed=7, twin="robot-1")
    ahead.seconds[-1]     # 2.0: the horizon reached
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from dtpf.entity.calls import ModelCalls
from dtpf.messages.arrays import check_particles, check_set
from dtpf.messages.errors import DtpfError
from dtpf.messages.streams import seed_sequence

__all__ = ["Forecast", "ForecastError", "forecast", "forecast_stream", "seconds_steps", "FORECAST_KEY", "BAND",
           "MAX_SECONDS_STEPS"]

#: The first word of every forecast stream's spawn key: 32 bits of the label "forecast".
FORECAST_KEY = int.from_bytes(hashlib.blake2b(b"forecast", digest_size=4).digest(), "little")
#: The probabilities of the band's ends.
BAND = (0.025, 0.975)
#: Most steps a horizon in seconds may take.
MAX_SECONDS_STEPS = 1000


class ForecastError(DtpfError, ValueError):
    """A forecast that cannot be made as asked (a horizon, a driven model without dt, a model that fails)."""


def forecast_stream(seed: int, twin: str, step: int, h: int) -> np.random.Generator:
    """The generator of forecast step ``step + h`` from the set of ``step`` (module docstring)."""
    entity = seed_sequence(seed, twin, step, "entity")
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(entity.entropy,
                                                                      spawn_key=(FORECAST_KEY, int(h)))))


def seconds_steps(seconds: float, dt: float) -> tuple[int, list[float]]:
    """(H, the dt of each step) of a horizon of ``seconds`` in steps of ``dt``: ceil(seconds / dt) steps, the
    last one shorter when ``dt`` does not divide ``seconds``; ForecastError for values out of bounds."""
    seconds, dt = float(seconds), float(dt)
    if not (np.isfinite(seconds) and seconds > 0):
        raise ForecastError(f"a horizon in seconds must be > 0, got {seconds!r}")
    if not (np.isfinite(dt) and dt > 0):
        raise ForecastError(f"a horizon in seconds needs dt > 0 (seconds a step), got {dt!r}")
    steps = int(np.ceil(seconds / dt - 1e-9))
    if steps > MAX_SECONDS_STEPS:
        raise ForecastError(f"a horizon of {seconds:g} s in steps of {dt:g} s is {steps} steps; at most "
                            f"{MAX_SECONDS_STEPS}: raise dt or shorten the horizon")
    dts = [dt] * steps
    dts[-1] = seconds - dt * (steps - 1)
    return steps, dts


@dataclass(frozen=True)
class Forecast:
    """Steps ``steps`` (k + 1 .. k + H) of a forecast from the set of step ``step``: (H, d) moments and band;
    ``particles``: the propagated set of the last step, (N, d), with the set's ``weights``."""

    step: int
    steps: np.ndarray
    mean: np.ndarray
    var: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    particles: np.ndarray
    weights: np.ndarray
    #: (H,) seconds from step k to each step (a driven model's dt summed), None for a model without dt.
    seconds: np.ndarray | None = None

    def points(self) -> list[dict]:
        """One dict a step: step, mean, var, lower, upper (and seconds, when the steps have a length)."""
        out = [{"step": int(k), "mean": m.tolist(), "var": v.tolist(), "lower": lo.tolist(), "upper": up.tolist()}
               for k, m, v, lo, up in zip(self.steps, self.mean, self.var, self.lower, self.upper)]
        if self.seconds is not None:
            for point, t in zip(out, self.seconds.tolist()):
                point["seconds"] = t
        return out

    def points_of_message(self) -> list[dict]:
        """The points a :class:`~dtpf.messages.models.ForecastBand` carries (step, mean, var, lower, upper)."""
        return [{name: point[name] for name in ("step", "mean", "var", "lower", "upper")} for point in self.points()]

    def as_json(self, particles: bool = False) -> dict:
        """Plain JSON values: one entry a step (step, mean, var, lower, upper); the last set on request."""
        out = {"from_step": self.step, "horizon": len(self.steps), "band": list(BAND), "steps": self.points()}
        if particles:
            out["particles"] = self.particles.tolist()
            out["weights"] = self.weights.tolist()
        return out


def weighted_quantiles(values: np.ndarray, weights: np.ndarray, probabilities) -> np.ndarray:
    """The weighted quantiles of each column of ``values`` (N, d): (len(probabilities), d); the inverse of the
    weighted empirical distribution function (the smallest value whose cumulative weight reaches p)."""
    order = np.argsort(values, axis=0, kind="stable")
    cumulative = np.cumsum(weights[order], axis=0)
    cumulative /= cumulative[-1]
    out = np.empty((len(probabilities), values.shape[1]))
    for j in range(values.shape[1]):
        index = np.searchsorted(cumulative[:, j], probabilities, side="left")
        out[:, j] = values[order[np.minimum(index, len(weights) - 1), j], j]
    return out


def forecast(model, particles, weights, step: int, horizon: int, dts=None, *, seed: int, twin: str,
             dt: float | None = None, control=None) -> Forecast:
    """Propagate the set (``particles`` (N, d), ``weights`` (N,) of step ``step``) ``horizon`` steps ahead.

    A driven model's steps last ``dt`` seconds each, or ``dts[h - 1]`` for step k + h (``horizon`` values,
    as :func:`seconds_steps` gives them).

    The set given is not changed (the model gets a copy). ForecastError names what is wrong: a horizon
    below 1, a driven model without ``dt`` or with a control of the wrong length, a model that fails or
    returns what is no particle set.
    """
    if int(horizon) < 1:
        raise ForecastError(f"horizon must be at least 1, got {horizon!r}")
    try:
        x, w = check_set(particles, weights)
    except ValueError as error:
        raise ForecastError(f"the particle set of step {step}: {error}") from None
    calls = ModelCalls(model)
    if dts is not None:
        dts = [float(value) for value in dts]
        if len(dts) != int(horizon):
            raise ForecastError(f"{len(dts)} step lengths for a horizon of {horizon} steps")
    elif dt is not None:
        dts = [float(dt)] * int(horizon)
    if calls.takes_dt and dts is None:
        raise ForecastError("the twin's model is driven: the forecast needs dt (seconds a step)")
    u = None
    if calls.controls or calls.takes_control:
        u = np.zeros(len(calls.controls)) if control is None else np.asarray(control, dtype=np.float64)
        if u.shape != (len(calls.controls),):
            raise ForecastError(f"control must hold {len(calls.controls)} values "
                                f"({', '.join(calls.controls)}), got {u.size}")
    elif control is not None:
        raise ForecastError("the twin's model takes no control")
    x = np.array(x, dtype=np.float64, copy=True)
    w = np.asarray(w, dtype=np.float64)
    n, d = x.shape
    means, variances = np.empty((horizon, d)), np.empty((horizon, d))
    lower, upper = np.empty((horizon, d)), np.empty((horizon, d))
    for h in range(1, horizon + 1):
        k = step + h
        try:
            x = check_particles(calls.propagate(x, k, forecast_stream(seed, twin, step, h),
                                                dt=None if dts is None else dts[h - 1], control=u), n=n)
        except Exception as error:
            raise ForecastError(f"the model's propagate failed at forecast step {k}: "
                                f"{type(error).__name__}: {error}") from None
        mean = w @ x
        centred = x - mean
        means[h - 1], variances[h - 1] = mean, w @ (centred * centred)
        lower[h - 1], upper[h - 1] = weighted_quantiles(x, w, BAND)
    seconds = np.cumsum(dts) if dts is not None and calls.takes_dt else None
    return Forecast(int(step), np.arange(step + 1, step + horizon + 1), means, variances, lower, upper, x, w,
                    seconds)
