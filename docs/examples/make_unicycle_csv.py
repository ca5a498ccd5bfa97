"""Simulate the unicycle robot of unicycle.py into three CSV files: odometry, GPS and beacons.

The true robot drives for ``--duration`` seconds with a speed and turn rate that vary smoothly, integrated
in steps of 1 ms; its wheel odometry reports the speed and turn rate with noise at 20 Hz, a GPS its
position at 1 Hz, three beacons their ranges at 10 Hz (the GPS's stamps are also beacon stamps: two
observations at one time). Times are written as decimals of whole milliseconds, so their stamps are exact;
the sensors' files carry the true pose (truth_x, truth_y, truth_theta)::

    python docs/examples/make_unicycle_csv.py --out /tmp/robot --duration 60
    dtpf run --model docs/examples/unicycle.py:Unicycle --observations gps=/tmp/robot/gps.csv \\
        --observations beacons=/tmp/robot/beacons.csv --controls /tmp/robot/odometry.csv
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from unicycle import BEACONS, Unicycle  # noqa: E402

#: Periods in milliseconds.
ODOMETRY_MS, BEACONS_MS, GPS_MS = 50, 100, 1000


def true_control(t: float) -> tuple[float, float]:
    """The robot's real speed (m/s) and turn rate (rad/s) at time t (s)."""
    return 1.0 + 0.3 * np.sin(0.2 * t), 0.15 * np.sin(0.1 * t) + 0.05


def simulate(duration: float, seed: int):
    """(odometry rows, gps rows, beacon rows): lists of [time text, values..., truth...]."""
    model = Unicycle()
    rng = np.random.default_rng(seed)
    pose = np.zeros(3)
    odometry, gps, beacons = [], [], []
    for ms in range(1, int(round(duration * 1000)) + 1):
        v, omega = true_control((ms - 1) / 1000)
        heading = pose[2] + 0.5 * omega * 0.001
        pose = pose + np.array([v * 0.001 * np.cos(heading), v * 0.001 * np.sin(heading), omega * 0.001])
        stamp = f"{ms // 1000}.{ms % 1000:03d}"
        if ms % ODOMETRY_MS == 0:
            u = true_control(ms / 1000)
            odometry.append([stamp, u[0] + model.sd_v * rng.standard_normal(),
                             u[1] + model.sd_omega * rng.standard_normal()])
        if ms % BEACONS_MS == 0:
            ranges = np.hypot(pose[0] - BEACONS[:, 0], pose[1] - BEACONS[:, 1])
            beacons.append([stamp, *(ranges + model.range_sd * rng.standard_normal(3)), *pose])
        if ms % GPS_MS == 0:
            gps.append([stamp, *(pose[:2] + model.gps_sd * rng.standard_normal(2)), *pose])
    return odometry, gps, beacons


def main(out_dir: Path = HERE, duration: float = 60.0, seed: int = 2026) -> dict[str, Path]:
    """Write odometry.csv, gps.csv and beacons.csv into ``out_dir``; return their paths by name."""
    out_dir.mkdir(parents=True, exist_ok=True)
    odometry, gps, beacons = simulate(duration, seed)
    truth = ["truth_x", "truth_y", "truth_theta"]
    files = {"odometry": (["time", "v", "omega"], odometry),
             "gps": (["time", "x", "y", *truth], gps),
             "beacons": (["time", "r1", "r2", "r3", *truth], beacons)}
    paths = {}
    for name, (header, rows) in files.items():
        paths[name] = out_dir / f"{name}.csv"
        with open(paths[name], "w", newline="") as handle:
            writer = csv.writer(handle, lineterminator="\n")
            writer.writerow(header)
            for row in rows:
                writer.writerow([row[0], *(repr(float(v)) for v in row[1:])])
    return paths


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE, help="folder of the three files (default: beside this)")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of driving (default: 60)")
    parser.add_argument("--seed", type=int, default=2026, help="seed of the noise (default: 2026)")
    args = parser.parse_args()
    for path in main(args.out, args.duration, args.seed).values():
        print(path)
