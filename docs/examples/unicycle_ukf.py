"""The unicycle's data filtered by dtpf and by filterpy's unscented Kalman filter: RMSE of both, side by side.

Both filters read the same files (make_unicycle_csv.py) and step at the same stamps with the same drives
(dtpf.entity.stamped: each observation one step, dt and the odometry held over it, piece by piece). The UKF
(filterpy's UnscentedKalmanFilter, Merwe sigma points alpha 0.1, beta 2, kappa 0) predicts over every piece
with the unicycle's mean motion and a process noise that carries the odometry's noise through the motion's
Jacobian (plus the model's random walk), and updates with the GPS's or the beacons' measurement function and
noise. dtpf runs the model as given, with the paper's DT preprocessing (its defaults) and without it (the plain
bootstrap filter), once per seed::

    python docs/examples/make_unicycle_csv.py --out /tmp/robot --duration 60
    python docs/examples/unicycle_ukf.py /tmp/robot --particles 1000 --seeds 5

It prints the position RMSE (m) and heading RMSE (rad) of each: dtpf's as the mean over the seeds with a
95% interval (t quantile), the UKF's once (it draws no random numbers).
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
MODEL = f"{HERE / 'unicycle.py'}:Unicycle"


def config_of(folder: Path, particles: int, seed: int, preprocess: bool = True):
    from dtpf.messages.config import RunConfig

    return RunConfig(model=MODEL, sensor_files={"gps": str(folder / "gps.csv"), "beacons": str(folder / "beacons.csv")},
                     controls=str(folder / "odometry.csv"), particles=particles, seed=seed, twin="unicycle-1",
                     preprocess=preprocess)


def motion(x, dt, u):
    """The unicycle's mean motion over dt with u = (v, omega) held (unicycle.py without its noise)."""
    v, omega = u
    heading = x[2] + 0.5 * omega * dt
    return np.array([x[0] + v * dt * math.cos(heading), x[1] + v * dt * math.sin(heading), x[2] + omega * dt])


def process_noise(x, dt, u, model) -> np.ndarray:
    """Q over dt: the odometry's noise through the motion's Jacobian in (v, omega), plus the random walk."""
    v, omega = u
    heading = x[2] + 0.5 * omega * dt
    jacobian = np.array([[dt * math.cos(heading), -0.5 * v * dt * dt * math.sin(heading)],
                         [dt * math.sin(heading), 0.5 * v * dt * dt * math.cos(heading)],
                         [0.0, dt]])
    return jacobian @ np.diag([model.sd_v ** 2, model.sd_omega ** 2]) @ jacobian.T + model.q * dt * np.eye(3)


def ukf_estimates(data, model) -> np.ndarray:
    """The UKF's posterior mean at every step of ``data`` (a RunData of the driven run)."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    from unicycle import BEACONS

    def hx_gps(x):
        return x[:2]

    def hx_beacons(x):
        return np.hypot(x[0] - BEACONS[:, 0], x[1] - BEACONS[:, 1])

    points = MerweScaledSigmaPoints(3, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(dim_x=3, dim_z=2, dt=0.1, hx=hx_gps, fx=motion, points=points)
    ukf.x = np.zeros(3)
    ukf.P = np.diag(np.square(model.prior_sd))
    means = []
    for step, sensor in enumerate(data.sensors):
        drive = data.drives[step]
        if drive is not None:
            for dt, u in drive.iter_pieces():
                if dt > 0:
                    ukf.Q = process_noise(ukf.x, dt, u, model)
                    ukf.predict(dt=dt, u=u)
        m = model.sensors[sensor]
        z = data.observations[step, :m]
        hx, sd = (hx_gps, model.gps_sd) if sensor == "gps" else (hx_beacons, model.range_sd)
        ukf.update(z, R=np.eye(m) * sd ** 2, hx=hx)
        means.append(ukf.x.copy())
    return np.array(means)


def rmse(means: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(position RMSE, heading RMSE) over the steps."""
    position = float(np.sqrt(np.mean(np.sum((means[:, :2] - truth[:, :2]) ** 2, axis=1))))
    heading = float(np.sqrt(np.mean((means[:, 2] - truth[:, 2]) ** 2)))
    return position, heading


def main(folder: Path, particles: int, seeds: int) -> str:
    from scipy import stats

    from dtpf.entity import sources
    from dtpf.scripts import inprocess

    sys.path.insert(0, str(HERE))
    config = config_of(folder, particles, 0)
    model = sources.load_model(config)
    data = sources.observations_of(config, model)
    lines = [f"{data.steps} steps ({data.sensors.count('gps')} GPS, {data.sensors.count('beacons')} beacons), "
             f"{folder}",
             f"{'filter':<38} {'position RMSE (m)':>20} {'heading RMSE (rad)':>20}"]
    for preprocess, label in ((True, "DT preprocessing"), (False, "plain")):
        ours = np.array([rmse(inprocess.run(config_of(folder, particles, seed, preprocess), model=model).means,
                              data.truth) for seed in range(seeds)])
        half = stats.t.ppf(0.975, seeds - 1) * ours.std(axis=0, ddof=1) / math.sqrt(seeds) if seeds > 1 else (0, 0)
        lines.append(f"{f'dtpf {label}, N = {particles}, {seeds} seeds':<38} {ours[:, 0].mean():>12.4f} +- "
                     f"{half[0]:.4f} {ours[:, 1].mean():>12.4f} +- {half[1]:.4f}")
    theirs = rmse(ukf_estimates(data, model), data.truth)
    lines.append(f"{'filterpy UKF':<38} {theirs[0]:>20.4f} {theirs[1]:>20.4f}")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="the folder make_unicycle_csv.py wrote")
    parser.add_argument("--particles", type=int, default=1000, help="N of dtpf (default: 1000)")
    parser.add_argument("--seeds", type=int, default=5, help="dtpf runs, seeds 0 .. K-1 (default: 5)")
    args = parser.parse_args()
    print(main(args.folder, args.particles, args.seeds))
