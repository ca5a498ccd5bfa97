"""Regenerate range_bearing.csv and range_bearing_no_truth.csv next to this file.

100 steps of :class:`RangeBearingTarget` simulated with
``np.random.default_rng(2026)``; time = k * dt for k = 1 .. 100, floats
written at full (repr) precision, so the files are the same on every run::

    python docs/examples/make_range_bearing_csv.py
"""
from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from range_bearing import RangeBearingTarget  # noqa: E402

STEPS = 100
SEED = 2026


def main(out_dir: Path = HERE) -> tuple[Path, Path]:
    """Write both files into ``out_dir``; return their paths."""
    model = RangeBearingTarget()
    truth, observations = model.simulate(STEPS, np.random.default_rng(SEED))
    full, bare = out_dir / "range_bearing.csv", out_dir / "range_bearing_no_truth.csv"
    with open(full, "w", newline="") as f_full, open(bare, "w", newline="") as f_bare:
        w_full, w_bare = csv.writer(f_full, lineterminator="\n"), csv.writer(f_bare, lineterminator="\n")
        w_full.writerow(["time", "range", "bearing", "truth_x", "truth_y", "truth_vx", "truth_vy"])
        w_bare.writerow(["time", "range", "bearing"])
        for k in range(1, STEPS + 1):
            row = [k * model.dt, *observations[k - 1]]
            w_bare.writerow([repr(float(v)) for v in row])
            w_full.writerow([repr(float(v)) for v in (*row, *truth[k - 1])])
    return full, bare


if __name__ == "__main__":
    for path in main():
        print(path)
