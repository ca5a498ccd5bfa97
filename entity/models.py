"""State-space models the filter runs on: parameters plus laws.

A model says how particles start (``initial_particles``), move
(``propagate``, the state equation) and are weighed (``log_likelihood``, the
observation density), how observations arise (``sample_observation``; the
system layer's one-step simulation draws them), and can ``simulate`` a true
path with observations.
States are ``(N, d)`` arrays of float64, observations ``(m,)`` per step.

The recommended import is::

    from dtpf.entity import models
    model = models.get("ungm")                 # the standard benchmark
    truth, observations = model.simulate(100, rng)

Time steps are numbered k = 1 .. T as in the paper: x_1 is the fixed
initial state, the simulation draws x_2 .. x_T (section 4.1).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dtpf.entity.base import StateSpaceModel

__all__ = ["StateSpaceModel", "GrowthModel", "DriftModel", "SensorSwitchModel", "MODELS", "get"]


@dataclass(frozen=True)
class GrowthModel(StateSpaceModel):
    """Univariate nonstationary growth model (Eq. 35, 36).

    x_k = 0.5 x_(k-1) + c x_(k-1) / (1 + x_(k-1)^2) + 8 cos(1.2 (k - 1)) + u_(k-1)
    z_k = x_k^2 / 20 + v_k,   u ~ N(0, process_var),  v ~ N(0, observation_var)

    The benchmark the paper cites (Gordon, Salmond and Smith 1993) has
    c = 25; the paper's Eq. 35 prints c = 0.25. Both are registered, under
    names nobody can confuse: ``ungm`` (c = 25) and ``ungm-printed``
    (c = 0.25). Defaults are the paper's settings (section 4.1): process
    noise variance 10, observation noise variance 1, x_1 = 0.1, initial
    estimate 1 with variance 5.
    """

    name: str = "ungm"
    growth: float = 25.0
    process_var: float = 10.0
    observation_var: float = 1.0
    x1: float = 0.1
    prior_mean: float = 1.0
    prior_var: float = 5.0
    dim: int = 1
    obs_dim: int = 1

    def transition_mean(self, x: np.ndarray, k: int) -> np.ndarray:
        """Deterministic part of Eq. 35 for step k (x is x_(k-1))."""
        return 0.5 * x + self.growth * x / (1.0 + x * x) + 8.0 * math.cos(1.2 * (k - 1))

    def initial_particles(self, n, rng):
        return rng.normal(self.prior_mean, math.sqrt(self.prior_var), size=(n, 1))

    def propagation_noise(self, n, k, rng):
        from dtpf.entity import _growth  # numba on first use: a process that only reads models (the recorder) skips it

        if n * self.dim < _growth.COMPILED_DRAWS:
            return rng.standard_normal((n, self.dim))
        return _growth.normals(rng, np.empty((n, self.dim)))

    def propagate(self, particles, k, rng, noise=None):
        # One compiled pass (dtpf.entity._growth): the numbers of
        # noise * sqrt(Q) + transition_mean(particles, k), noise ~ N(0, 1).
        from dtpf.entity import _growth

        x = np.ascontiguousarray(particles, dtype=np.float64)
        args = (math.sqrt(self.process_var), self.growth, 8.0 * math.cos(1.2 * (k - 1)))
        if noise is None and x.size >= _growth.COMPILED_DRAWS:
            return _growth.propagate_drawing(x, rng, *args)
        if noise is None:
            noise = rng.standard_normal(x.shape)
        return _growth.propagate(x, noise, *args)

    def log_likelihood(self, particles, observation, k):
        from dtpf.entity import _growth

        z = float(np.asarray(observation).reshape(-1)[0])
        constant = 0.5 * math.log(2.0 * math.pi * self.observation_var)
        return _growth.log_likelihood(np.ascontiguousarray(particles, dtype=np.float64), z,
                                      self.observation_var, constant)

    def observation_moments(self, particles, k):
        return particles[:, :1] ** 2 / 20.0, np.array([self.observation_var])

    def sample_observation(self, states, k, rng):
        noise = rng.standard_normal((states.shape[0], 1))
        noise *= math.sqrt(self.observation_var)
        noise += states[:, :1] ** 2 / 20.0
        return noise

    def simulate(self, steps, rng):
        if steps < 1:
            raise ValueError(f"steps must be at least 1, got {steps}")
        x = np.empty((steps, 1))
        x[0, 0] = self.x1
        for k in range(2, steps + 1):
            x[k - 1] = self.transition_mean(x[k - 2], k) + math.sqrt(self.process_var) * rng.standard_normal()
        z = x ** 2 / 20.0 + math.sqrt(self.observation_var) * rng.standard_normal((steps, 1))
        return x, z


def _video_model() -> StateSpaceModel:
    from dtpf.entity.tracking import VideoTrackingModel  # imports this module: only on first use
    return VideoTrackingModel()


def _drift_model() -> StateSpaceModel:
    return DriftModel()  # defined below the registry


def _switching_model() -> StateSpaceModel:
    return SensorSwitchModel()  # defined below the registry


def _moving_model() -> StateSpaceModel:
    return MovingDriftModel()  # defined below the registry


#: Registered models by name. ``ungm`` is the standard benchmark (25),
#: ``ungm-printed`` the form printed in the paper's Eq. 35 (0.25), ``video``
#: the tracking scenario of section 5 (:mod:`dtpf.entity.tracking`), ``drift`` a slowly drifting constant
#: where particles impoverish (:class:`DriftModel`, not in the paper), ``switching`` the same constant seen
#: by a sensor whose noise drops mid-run (:class:`SensorSwitchModel`), ``moving`` the constant moving away
#: from the origin (:class:`MovingDriftModel`: the best cure changes as it goes). A value may be a
#: zero-argument factory, built once by :func:`get`.
MODELS: dict[str, StateSpaceModel] = {
    "ungm": GrowthModel(name="ungm", growth=25.0),
    "ungm-printed": GrowthModel(name="ungm-printed", growth=0.25),
    "video": _video_model,
    "drift": _drift_model,
    "switching": _switching_model,
    "moving": _moving_model,
}


def get(name: str) -> StateSpaceModel:
    """The model registered as ``name``, or a ValueError listing the names."""
    try:
        model = MODELS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown model {name!r}; expected one of {', '.join(MODELS)}") from None
    if not isinstance(model, StateSpaceModel):
        model = MODELS[name] = model()
    return model


@dataclass(frozen=True)
class DriftModel(StateSpaceModel):
    """An unknown, slowly drifting constant learned online: a scenario where particles impoverish.

    x_k = x_(k-1) + u_k,   z_k = x_k + v_k,   u ~ N(0, process_var), v ~ N(0, observation_var),
    x_1 ~ N(prior_mean, prior_var), each of the ``dim`` components independent.

    The defaults: drift sd 0.001 per step, observation sd 0.01, prior sd 1.
    The process noise is tiny against the prior and the observations are
    precise, so after a few steps the posterior is far narrower than the
    initial cloud: resampling leaves a few distinct values, and the process
    noise is too small to spread them again (Gordon, Salmond and Smith 1993
    introduced roughening for this case). The model is linear and Gaussian,
    so :meth:`kalman` gives the exact posterior mean to measure a filter
    against.
    """

    name: str = "drift"
    process_var: float = 1e-6
    observation_var: float = 1e-4
    prior_mean: float = 0.0
    prior_var: float = 1.0
    dim: int = 1
    obs_dim: int = 1

    def __post_init__(self):
        object.__setattr__(self, "obs_dim", self.dim)

    def initial_particles(self, n, rng):
        return self.prior_mean + math.sqrt(self.prior_var) * rng.standard_normal((n, self.dim))

    def propagation_noise(self, n, k, rng):
        return rng.standard_normal((n, self.dim))

    def propagate(self, particles, k, rng, noise=None):
        if noise is None:
            noise = self.propagation_noise(particles.shape[0], k, rng)
        return particles + math.sqrt(self.process_var) * noise

    def log_likelihood(self, particles, observation, k):
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
        residual = particles - z
        return (-0.5 * np.sum(residual * residual, axis=1) / self.observation_var
                - 0.5 * self.dim * math.log(2.0 * math.pi * self.observation_var))

    def observation_moments(self, particles, k):
        return particles, np.full(self.dim, self.observation_var)

    def sample_observation(self, states, k, rng):
        return states + math.sqrt(self.observation_var) * rng.standard_normal(states.shape)

    def simulate(self, steps, rng):
        if steps < 1:
            raise ValueError(f"steps must be at least 1, got {steps}")
        x = np.empty((steps, self.dim))
        x[0] = self.prior_mean + math.sqrt(self.prior_var) * rng.standard_normal(self.dim)
        for k in range(1, steps):
            x[k] = x[k - 1] + math.sqrt(self.process_var) * rng.standard_normal(self.dim)
        z = x + math.sqrt(self.observation_var) * rng.standard_normal((steps, self.dim))
        return x, z

    def variance_at(self, k: int) -> float:
        """The observation variance of step k (from 1): the same at every step."""
        return self.observation_var

    def kalman(self, observations) -> np.ndarray:
        """(T, d) exact posterior means E[x_k | z_1..z_k] (the Kalman filter; the optimum of any filter),
        with each step's observation variance (:meth:`variance_at`)."""
        z = np.asarray(observations, dtype=np.float64).reshape(len(observations), self.dim)
        means = np.empty_like(z)
        mean, var = np.full(self.dim, self.prior_mean), self.prior_var
        for k in range(z.shape[0]):
            if k:
                var = var + self.process_var
            gain = var / (var + self.variance_at(k + 1))
            mean = mean + gain * (z[k] - mean)
            var = (1.0 - gain) * var
            means[k] = mean
        return means


@dataclass(frozen=True)
class SensorSwitchModel(DriftModel):
    """A slowly drifting constant seen by a sensor whose noise drops mid-run: the best cure changes.

    x_k as in :class:`DriftModel` (drift sd 0.001 per step, prior N(``prior_mean``, 1)); z_k = x_k + v_k
    with v_k ~ N(0, ``noisy_var``) for k < ``switch_step`` (sd 1: a coarse sensor) and N(0,
    ``observation_var``) from ``switch_step`` on (sd 0.01: a precise one).

    While the sensor is coarse the posterior narrows slowly and plain resampling keeps enough
    distinct particles; a kernel that adds a share of the posterior's spread every step (the
    regularised filter's) then throws information away. Once the sensor is precise, the cloud
    collapses onto a few particles (impoverishment) and the moves that spread it win. The model is
    linear and Gaussian: :meth:`kalman` gives the exact posterior mean.
    """

    name: str = "switching"
    noisy_var: float = 1.0
    switch_step: int = 51

    def variance_at(self, k: int) -> float:
        """The observation variance of step k (from 1): coarse before ``switch_step``, precise from it."""
        return self.noisy_var if int(k) < self.switch_step else self.observation_var

    def log_likelihood(self, particles, observation, k):
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
        var = self.variance_at(k)
        residual = particles - z
        return -0.5 * np.sum(residual * residual, axis=1) / var - 0.5 * self.dim * math.log(2.0 * math.pi * var)

    def observation_moments(self, particles, k):
        return particles, np.full(self.dim, self.variance_at(k))

    def sample_observation(self, states, k, rng):
        return states + math.sqrt(self.variance_at(k)) * rng.standard_normal(states.shape)

    def simulate(self, steps, rng):
        x, _ = DriftModel.simulate(self, steps, rng)
        sd = np.sqrt([self.variance_at(k) for k in range(1, steps + 1)])[:, None]
        return x, x + sd * rng.standard_normal((steps, self.dim))


@dataclass(frozen=True)
class MovingDriftModel(DriftModel):
    """The drifting constant of :class:`DriftModel` moving away from the origin at a known ``velocity``.

    x_k = x_(k-1) + velocity + u_k,   z_k = x_k + v_k (drift sd 0.001 per step, sensor sd 0.01, prior
    N(0, 1)); with the default 0.3 per step the state goes from about 0 to about 30 in 100 steps.

    Near the origin the paper's DT rule (Eq. 29-30) is the best cure of the cloud's impoverishment; its
    move is not translation invariant, so as the state leaves the origin the same rule scatters the
    cloud more and more, and other moves win: the best cure changes during the run. Linear and
    Gaussian: :meth:`kalman` gives the exact posterior mean.
    """

    name: str = "moving"
    velocity: float = 0.3

    def propagate(self, particles, k, rng, noise=None):
        return DriftModel.propagate(self, particles, k, rng, noise) + self.velocity

    def simulate(self, steps, rng):
        x, z = DriftModel.simulate(self, steps, rng)
        shift = self.velocity * np.arange(steps)[:, None]
        return x + shift, z + shift

    def kalman(self, observations) -> np.ndarray:
        """(T, d) exact posterior means E[x_k | z_1..z_k] (the Kalman filter with the known velocity)."""
        z = np.asarray(observations, dtype=np.float64).reshape(len(observations), self.dim)
        means = np.empty_like(z)
        mean, var = np.full(self.dim, self.prior_mean), self.prior_var
        for k in range(z.shape[0]):
            if k:
                mean, var = mean + self.velocity, var + self.process_var
            gain = var / (var + self.variance_at(k + 1))
            mean = mean + gain * (z[k] - mean)
            var = (1.0 - gain) * var
            means[k] = mean
        return means
