"""The contract every state-space model keeps (what the filter, the layers and ``--model`` rely on).

A model says how particles start (``initial_particles``), move
(``propagate``, the state equation) and are weighed (``log_likelihood``, the
observation density), how observations arise (``sample_observation``; the
system layer's one-step simulation draws them), can ``simulate`` a true path
with observations, and says what else the entity publishes at a step
(``step_messages``: the video scenario's frame). States are ``(N, d)`` arrays
of float64, observations ``(m,)`` per step. The built-in models are in
:mod:`dtpf.entity.models` and :mod:`dtpf.entity.tracking`.

A model of a driven machine seen by several sensors declares two more things
and takes them as keyword arguments (docs/guides/driven.md):

``controls``
    The names of the control input's components u = (u_0, .., u_(c-1)) (wheel
    odometry: ``("v", "omega")``); empty (the default): the model is not driven.
``sensors``
    Each sensor's name and the dimension of its observation
    (``{"gps": 2, "beacons": 3}``); empty (the default): one sensor of
    ``obs_dim`` values. ``obs_dim`` of a model with sensors is the largest of them.

``propagate(particles, k, rng, noise=None, *, dt=None, control=None)``
    ``dt``: the seconds from the previous filter step to this one, from the
    observations' stamps (0 when two observations share a stamp); ``control``:
    the ``(c,)`` control held over that time (zero-order hold; zeros before the
    first control). When the control changes inside the interval the filter
    calls ``propagate`` once per piece, each with its own ``dt`` and ``control``.
``log_likelihood(particles, observation, k, *, sensor=None)``, ``sample_observation(states, k, rng, *,
sensor=None)``, ``observation_moments(particles, k, *, sensor=None)``
    ``sensor``: the name of the sensor the observation is from (``observation``
    has ``sensors[sensor]`` values).

The filter passes ``dt``, ``control`` and ``sensor`` only to a method whose
signature names them (:class:`dtpf.entity.calls.ModelCalls` reads it once), so a
model written without them is called, and draws its random numbers, exactly as
before.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from types import MappingProxyType
from typing import Mapping

import numpy as np

__all__ = ["StateSpaceModel", "sensor_dims"]


class StateSpaceModel(ABC):
    """The interface a scenario implements so that the filter can run it."""

    #: Registry name of the model.
    name: str
    #: Dimension d of the state.
    dim: int
    #: Names of the control input's components (empty: not driven).
    controls: tuple[str, ...] = ()
    #: Sensor name -> dimension of its observation (empty: one sensor of ``obs_dim`` values).
    sensors: Mapping[str, int] = MappingProxyType({})

    @property
    def obs_dim(self) -> int:
        """Dimension m of one observation; a model with ``sensors``: the largest of theirs. A model with one
        sensor sets it (a class attribute or a field)."""
        if "obs_dim" in getattr(self, "__dict__", {}):
            return self.__dict__["obs_dim"]
        if self.sensors:
            return max(int(m) for m in self.sensors.values())
        raise AttributeError(f"{type(self).__name__} sets no obs_dim")

    @obs_dim.setter
    def obs_dim(self, value: int) -> None:
        self.__dict__["obs_dim"] = value

    #: The most steps a simulation of the model can have (None: any number; the video has its frames).
    max_steps: int | None = None

    @property
    def samples_observations(self) -> bool:
        """Whether ``sample_observation`` can draw z_k (the system layer's simulating policies and
        ``dtpf sensor`` need it): True when the model overrides it. A subclass may set it as a class
        attribute instead."""
        return type(self).sample_observation is not StateSpaceModel.sample_observation

    @abstractmethod
    def initial_particles(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """N particles of step 1, drawn from the prior p(x_1): (N, d)."""

    @abstractmethod
    def propagate(self, particles: np.ndarray, k: int, rng: np.random.Generator,
                  noise: np.ndarray | None = None) -> np.ndarray:
        """Draw x_k ~ p(x_k | x_(k-1)) for every particle: (N, d) -> (N, d).

        A driven model adds keyword arguments ``*, dt=None, control=None`` (the
        module docstring): the seconds since the last step and the ``(c,)``
        control in force over them.

        ``noise``: what :meth:`propagation_noise` drew for this step, if it was
        drawn ahead; the model then uses it (and may overwrite it) instead of
        drawing. Only models whose ``propagation_noise`` returns an array get it.
        """

    def propagation_noise(self, n: int, k: int, rng: np.random.Generator) -> np.ndarray | None:
        """The random numbers :meth:`propagate` draws first at step k, drawn on their own.

        They depend on nothing but (n, k, rng), so the entity can draw them
        while it waits for the information layer's answer of step k - 1.
        ``propagate(particles, k, rng, noise=propagation_noise(n, k, rng))``
        gives the same numbers as ``propagate(particles, k, rng)``. None (the
        default): this model draws inside ``propagate`` only.
        """
        return None

    @abstractmethod
    def log_likelihood(self, particles: np.ndarray, observation: np.ndarray, k: int) -> np.ndarray:
        """log p(z_k | x_k) for every particle: (N, d), (m,) -> (N,).

        A model with several sensors adds ``*, sensor=None``: the sensor z_k is from."""

    def sample_observation(self, states: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """Draw z_k ~ p(z_k | x_k) for every state: (S, d) -> (S, m).

        Optional: a twin of a real system filters observations from outside and
        never draws them; only the simulating policies, ``simulate`` and
        ``dtpf sensor`` need it. A model with several sensors adds ``*, sensor=None``.
        """
        raise NotImplementedError(f"model {getattr(self, 'name', type(self).__name__)!r} does not "
                                  f"implement sample_observation")

    def observation_moments(self, particles: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Mean of z_k given each particle and the observation noise variance: (N, m), (m,).

        Optional (default None). Where a model gives it, the filter reports the
        normalised innovation of each observation, the check of a filter that
        runs without truth. A model with several sensors adds ``*, sensor=None``.
        """
        return None

    def simulate(self, steps: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A true path and its observations for k = 1 .. steps: (T, d), (T, m).

        The default draws x_1 from the prior, then x_k with ``propagate`` and
        z_k with ``sample_observation``; models with a fixed x_1 override it.
        """
        if steps < 1:
            raise ValueError(f"steps must be at least 1, got {steps}")
        x = self.initial_particles(1, rng)
        states, observations = [], []
        for k in range(1, steps + 1):
            if k > 1:
                x = self.propagate(x, k, rng)
            states.append(np.array(x[0], dtype=np.float64))
            observations.append(np.array(self.sample_observation(x, k, rng)[0], dtype=np.float64))
        return np.array(states), np.array(observations)

    def step_messages(self, header: dict, particles=None, weights=None, mean=None) -> list:
        """What else the entity publishes at a step besides its estimate: messages of
        :mod:`dtpf.messages.models` built with ``header`` (run_id, twin_id, step), from the step's
        ``particles`` and ``weights`` (before resampling) and its estimated ``mean``. None by default;
        the video scenario returns the step's frame and the particles drawn over it, so a log plays
        as a video in Foxglove."""
        return []


def sensor_dims(model) -> dict[str | None, int]:
    """Each sensor of ``model`` and the dimension of its observation: its ``sensors``, or ``{None: obs_dim}``
    for a model of one unnamed sensor."""
    sensors = getattr(model, "sensors", None) or {}
    if sensors:
        return {str(name): int(m) for name, m in sensors.items()}
    return {None: int(model.obs_dim)}
