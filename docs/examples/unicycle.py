"""A wheeled robot (unicycle) driven by wheel odometry, seen by a GPS and by ranges to three beacons.

A driven model with two sensors (docs/guides/driven.md): the state is the pose (x, y, theta), the control
is what the wheel odometry measures, (v, omega) (forward speed, turn rate), and two sensors see it at their
own rates::

    dtpf run --model docs/examples/unicycle.py:Unicycle \\
        --observations gps=gps.csv --observations beacons=beacons.csv --controls odometry.csv

``make_unicycle_csv.py`` beside this file simulates the robot into those three CSV files.

Motion over dt seconds with the control u = (v, omega) held (the odometry is noisy: each particle drives
with its own draw of it)::

    v' = v + sd_v e_1,   omega' = omega + sd_omega e_2,   e ~ N(0, I)
    theta_k = theta + omega' dt
    x_k = x + v' dt cos(theta + omega' dt / 2),   y_k = y + v' dt sin(theta + omega' dt / 2)

plus a small random walk of intensity q per second on (x, y, theta), so that a particle that stands still
(dt = 0: two sensors at one stamp) does not move. Observations::

    gps:      z = (x, y) + N(0, gps_sd^2 I)
    beacons:  z_j = |(x, y) - b_j| + N(0, range_sd^2),  j = 1, 2, 3
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dtpf import StateSpaceModel

__all__ = ["Unicycle", "BEACONS"]

#: The beacons' positions (m).
BEACONS = np.array([[0.0, 30.0], [30.0, -10.0], [-25.0, -15.0]])


@dataclass(frozen=True)
class Unicycle(StateSpaceModel):
    """A unicycle robot: pose (x, y, theta), control (v, omega), sensors gps (2) and beacons (3).

    Parameters
    ----------
    sd_v, sd_omega : float
        Standard deviations of the odometry's speed (m/s) and turn rate (rad/s).
    q : float
        Intensity of the pose's random walk (variance per second).
    gps_sd, range_sd : float
        Standard deviations of a GPS coordinate and of a beacon range (m).
    prior_sd : tuple of float
        Standard deviations of the prior around the origin, heading 0.
    """

    sd_v: float = 0.1
    sd_omega: float = 0.05
    q: float = 0.01
    gps_sd: float = 1.5
    range_sd: float = 0.3
    prior_sd: tuple = (1.0, 1.0, 0.1)
    name: str = "unicycle"
    dim: int = 3
    controls: tuple = ("v", "omega")
    sensors: tuple = (("gps", 2), ("beacons", 3))

    def __post_init__(self):
        object.__setattr__(self, "sensors", dict(self.sensors))

    def initial_particles(self, n, rng):
        return rng.standard_normal((n, 3)) * np.asarray(self.prior_sd)

    def propagate(self, particles, k, rng, noise=None, *, dt=None, control=None):
        dt = 0.1 if dt is None else float(dt)
        v, omega = (0.0, 0.0) if control is None else (float(control[0]), float(control[1]))
        e = rng.standard_normal((particles.shape[0], 5))
        speed = v + self.sd_v * e[:, 0]
        turn = omega + self.sd_omega * e[:, 1]
        heading = particles[:, 2] + 0.5 * turn * dt
        walk = math.sqrt(self.q * dt)
        out = np.empty_like(particles)
        out[:, 0] = particles[:, 0] + speed * dt * np.cos(heading) + walk * e[:, 2]
        out[:, 1] = particles[:, 1] + speed * dt * np.sin(heading) + walk * e[:, 3]
        out[:, 2] = particles[:, 2] + turn * dt + walk * e[:, 4]
        return out

    def _mean(self, states, sensor):
        if sensor == "gps":
            return states[:, :2]
        if sensor == "beacons":
            return np.hypot(states[:, None, 0] - BEACONS[None, :, 0], states[:, None, 1] - BEACONS[None, :, 1])
        raise ValueError(f"unknown sensor {sensor!r}")

    def _sd(self, sensor):
        return self.gps_sd if sensor == "gps" else self.range_sd

    def log_likelihood(self, particles, observation, k, *, sensor=None):
        residual = (np.asarray(observation) - self._mean(particles, sensor)) / self._sd(sensor)
        m = residual.shape[1]
        return -0.5 * np.sum(residual * residual, axis=1) - m * (math.log(self._sd(sensor))
                                                                 + 0.5 * math.log(2.0 * math.pi))

    def sample_observation(self, states, k, rng, *, sensor=None):
        mean = self._mean(states, sensor)
        return mean + self._sd(sensor) * rng.standard_normal(mean.shape)

    def observation_moments(self, particles, k, *, sensor=None):
        mean = self._mean(particles, sensor)
        return mean, np.full(mean.shape[1], self._sd(sensor) ** 2)
