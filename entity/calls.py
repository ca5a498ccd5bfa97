"""How to call a model's methods: which of ``dt``, ``control`` and ``sensor`` each one takes, read once.

A model written for one sensor and fixed steps has ``propagate(particles, k, rng, noise=None)`` and
``log_likelihood(particles, observation, k)``; a driven model with several sensors adds keyword arguments
(:mod:`dtpf.entity.base`). :class:`ModelCalls` reads the signatures once, when the model is loaded, and passes
each method only the arguments it names, so a model written without them is called exactly as before::

    calls = ModelCalls(model)
    calls.driven                                     # it takes dt or control, or declares controls or sensors
    x = calls.propagate(x, k, rng, dt=0.1, control=u)
    lw = calls.log_likelihood(x, z, k, sensor="gps")

Only a parameter named in the signature counts; a ``**kwargs`` catch-all does not (an old model that
forwards its keyword arguments keeps its old calls).
"""
from __future__ import annotations

import inspect

import numpy as np

from dtpf.entity.base import sensor_dims

__all__ = ["ModelCalls", "takes"]


def takes(method, name: str) -> bool:
    """Whether ``method``'s signature names a parameter ``name`` (not through ``**kwargs``)."""
    try:
        parameters = inspect.signature(method).parameters
    except (TypeError, ValueError):  # no signature (a builtin): the old calls
        return False
    parameter = parameters.get(name)
    return parameter is not None and parameter.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                                        inspect.Parameter.KEYWORD_ONLY)


class ModelCalls:
    """A model's methods called with the arguments each one takes (module docstring).

    Attributes
    ----------
    takes_dt, takes_control : bool
        ``propagate`` names ``dt`` / ``control``.
    takes_sensor : dict of str to bool
        For ``log_likelihood``, ``sample_observation`` and ``observation_moments``: whether it names ``sensor``.
    controls : tuple of str
        The model's control components (empty: not driven).
    sensors : dict
        Sensor name -> observation dimension (``{None: obs_dim}`` for a model of one unnamed sensor).
    """

    def __init__(self, model):
        self.model = model
        self.takes_dt = takes(model.propagate, "dt")
        self.takes_control = takes(model.propagate, "control")
        self.takes_sensor = {name: takes(getattr(model, name), "sensor")
                             for name in ("log_likelihood", "sample_observation", "observation_moments")}
        self.controls = tuple(str(c) for c in (getattr(model, "controls", None) or ()))
        self.sensors = sensor_dims(model)

    @property
    def driven(self) -> bool:
        """Whether the filter's steps need the observations' stamps, controls or sensor names."""
        return self.takes_dt or self.takes_control or bool(self.controls) or None not in self.sensors

    @property
    def named_sensors(self) -> bool:
        """Whether every observation must name its sensor (the model declares ``sensors``)."""
        return None not in self.sensors

    def propagate(self, particles, k, rng, noise=None, *, dt=None, control=None):
        """``model.propagate`` with ``noise`` when given, ``dt`` and ``control`` when it takes them."""
        kwargs = {}
        if noise is not None:
            kwargs["noise"] = noise
        if self.takes_dt:
            kwargs["dt"] = dt
        if self.takes_control:
            kwargs["control"] = control
        return self.model.propagate(particles, k, rng, **kwargs)

    def log_likelihood(self, particles, observation, k, *, sensor=None):
        if self.takes_sensor["log_likelihood"]:
            return self.model.log_likelihood(particles, observation, k, sensor=sensor)
        return self.model.log_likelihood(particles, observation, k)

    def sample_observation(self, states, k, rng, *, sensor=None):
        if self.takes_sensor["sample_observation"]:
            return self.model.sample_observation(states, k, rng, sensor=sensor)
        return self.model.sample_observation(states, k, rng)

    def observation_moments(self, particles, k, *, sensor=None):
        if self.takes_sensor["observation_moments"]:
            return self.model.observation_moments(particles, k, sensor=sensor)
        return self.model.observation_moments(particles, k)

    def advance(self, particles, k, rng, drive, noise=None):
        """Propagate ``particles`` to step k through every piece of ``drive`` (a
        :class:`~dtpf.entity.timeline.Drive`, or None: one plain call): the first piece gets ``noise``."""
        if drive is None or not len(drive.pieces):
            return self.propagate(particles, k, rng, noise)
        for i, (dt, control) in enumerate(drive.iter_pieces()):
            particles = self.propagate(particles, k, rng, noise if i == 0 else None, dt=dt, control=control)
            particles = np.asarray(particles) if i + 1 < len(drive.pieces) else particles
        return particles


class StepModel:
    """A driven model seen through the old contract at one step: its sensor and drive held, for code that
    calls ``propagate(x, k, rng)`` and ``log_likelihood(x, z, k)`` (the system layer's evidence and what-if
    simulations).

    :meth:`hold` sets the sensor and the drive of the step in hand; ``log_likelihood``,
    ``sample_observation`` and ``observation_moments`` then take that sensor, and ``propagate`` that drive
    (the last interval's dt and control: a forecast of step k + 1 assumes the next interval is like the
    last). Every other attribute is the model's.
    """

    def __init__(self, model):
        self._model = model
        self._calls = ModelCalls(model)
        self.sensor = None
        self.drive = None

    def hold(self, sensor, drive) -> None:
        """The sensor and drive of the step in hand (a drive of None keeps the last one)."""
        self.sensor = sensor
        if drive is not None:
            self.drive = drive

    def __getattr__(self, name):
        return getattr(self._model, name)

    def propagate(self, particles, k, rng, noise=None):
        return self._calls.advance(particles, k, rng, self.drive, noise)

    def log_likelihood(self, particles, observation, k):
        return self._calls.log_likelihood(particles, observation, k, sensor=self.sensor)

    def sample_observation(self, states, k, rng):
        return self._calls.sample_observation(states, k, rng, sensor=self.sensor)

    def observation_moments(self, particles, k):
        return self._calls.observation_moments(particles, k, sensor=self.sensor)
