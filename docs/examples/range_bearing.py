"""A target in the plane seen by a range-bearing sensor: a model of your own, outside dtpf.

The classic tracking example of Stone Soup's and filterpy's tutorials. The
state is (x, y, vx, vy); the target moves with nearly constant velocity and
a sensor at the origin measures its range and bearing. Run dtpf on it by
reference, without editing dtpf::

    dtpf ... --model docs/examples/range_bearing.py:RangeBearingTarget

or in Python::

    from dtpf.entity import model_ref
    model = model_ref.resolve("docs/examples/range_bearing.py:RangeBearingTarget")

``range_bearing.csv`` next to this file holds 100 simulated steps
(``make_range_bearing_csv.py`` regenerates it).

Motion (white-acceleration noise of intensity q, per axis, time step dt)::

    x_k = F x_(k-1) + u_k,   u_k ~ N(0, Q)
    F = [[1, dt], [0, 1]],   Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]

Observation::

    z_k = (hypot(x, y), arctan2(y, x)) + v_k,   v_k ~ N(0, diag(range_sd^2, bearing_sd^2))

The bearing residual is wrapped to (-pi, pi]. The prior puts the target
about 45 away from the sensor, heading along +x; the simulated path stays
far from the origin and from the negative x axis, where the bearing jumps
from pi to -pi.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dtpf import StateSpaceModel

__all__ = ["RangeBearingTarget", "wrap_angle"]


def wrap_angle(angle):
    """Angles wrapped to (-pi, pi]."""
    return math.pi - np.mod(math.pi - np.asarray(angle, dtype=np.float64), 2.0 * math.pi)


@dataclass(frozen=True)
class RangeBearingTarget(StateSpaceModel):
    """Nearly-constant-velocity target, range-bearing sensor at the origin.

    Parameters
    ----------
    dt : float
        Time step.
    q : float
        Intensity of the white acceleration noise (per axis).
    range_sd, bearing_sd : float
        Standard deviations of the range (same unit as x, y) and bearing
        (radians) noise.
    prior_mean, prior_sd : tuple of 4 floats
        Independent normal prior of x_1 = (x, y, vx, vy).
    """

    name: str = "range-bearing"
    dt: float = 1.0
    q: float = 0.05
    range_sd: float = 1.0
    bearing_sd: float = 0.02
    prior_mean: tuple[float, float, float, float] = (20.0, 40.0, 1.0, 0.0)
    prior_sd: tuple[float, float, float, float] = (5.0, 5.0, 0.5, 0.5)
    dim: int = 4
    obs_dim: int = 2

    # --- motion ---

    def transition(self) -> np.ndarray:
        """F, the 4 x 4 transition matrix of (x, y, vx, vy)."""
        f = np.eye(4)
        f[0, 2] = f[1, 3] = self.dt
        return f

    def process_covariance(self) -> np.ndarray:
        """Q, the 4 x 4 covariance of the motion noise (the discrete NCV model)."""
        dt, q = self.dt, self.q
        cov = np.zeros((4, 4))
        cov[0, 0] = cov[1, 1] = q * dt ** 3 / 3.0
        cov[0, 2] = cov[2, 0] = cov[1, 3] = cov[3, 1] = q * dt ** 2 / 2.0
        cov[2, 2] = cov[3, 3] = q * dt
        return cov

    def initial_particles(self, n, rng):
        return np.asarray(self.prior_mean) + np.asarray(self.prior_sd) * rng.standard_normal((n, 4))

    def propagation_noise(self, n, k, rng):
        return rng.standard_normal((n, 4))

    def propagate(self, particles, k, rng, noise=None):
        if noise is None:
            noise = self.propagation_noise(particles.shape[0], k, rng)
        chol = np.linalg.cholesky(self.process_covariance())
        return particles @ self.transition().T + noise @ chol.T

    # --- observation ---

    def measure(self, states: np.ndarray) -> np.ndarray:
        """Noise-free (range, bearing) of each state: (N, 4) -> (N, 2)."""
        h = np.empty((states.shape[0], 2))
        h[:, 0] = np.hypot(states[:, 0], states[:, 1])
        h[:, 1] = np.arctan2(states[:, 1], states[:, 0])
        return h

    def log_likelihood(self, particles, observation, k):
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
        h = self.measure(particles)
        range_res = (z[0] - h[:, 0]) / self.range_sd
        bearing_res = wrap_angle(z[1] - h[:, 1]) / self.bearing_sd
        return (-0.5 * (range_res * range_res + bearing_res * bearing_res)
                - math.log(2.0 * math.pi * self.range_sd * self.bearing_sd))

    def sample_observation(self, states, k, rng):
        z = self.measure(states)
        z += rng.standard_normal(z.shape) * np.array([self.range_sd, self.bearing_sd])
        z[:, 1] = wrap_angle(z[:, 1])
        return z

    def observation_moments(self, particles, k):
        return self.measure(particles), np.array([self.range_sd ** 2, self.bearing_sd ** 2])
