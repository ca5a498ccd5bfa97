"""Which weight rule for processed particles: inherit or likelihood?

Runs the in-process filter on both growth models over many seeds (each seed
is its own simulated data set, shared by every variant) and prints the mean
MSE with a 95% confidence interval for: no preprocessing, DT with
``inherit`` weights, DT with ``likelihood`` weights; plus the paired
difference against no preprocessing.

    python -m dtpf.scripts.paper.compare_weight_rules --seeds 200
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from dtpf.messages.config import RunConfig
from dtpf.scripts.inprocess import run

VARIANTS = {
    "no preprocessing": dict(preprocess=False),
    "DT, inherit": dict(preprocess=True, weight_rule="inherit"),
    "DT, likelihood": dict(preprocess=True, weight_rule="likelihood"),
}


def mean_ci(values: np.ndarray) -> tuple[float, float]:
    """Mean and half-width of its 95% normal interval."""
    return float(values.mean()), 1.96 * float(values.std(ddof=1)) / math.sqrt(values.size)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=200, help="data sets per cell (default: %(default)s)")
    parser.add_argument("--particles", type=int, nargs="+", default=[100, 500], help="N values")
    parser.add_argument("--scenarios", nargs="+", default=["ungm", "ungm-printed"])
    parser.add_argument("--resampler", default="systematic")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    print(f"`python -m dtpf.scripts.paper.compare_weight_rules --seeds {args.seeds}`: MSE over T = 100, "
          f"{args.resampler} resampling, PS = 0.81, mean and 95% CI over {args.seeds} seeds; "
          "difference = variant - no preprocessing, paired by seed.\n")
    print("| scenario | N | variant | MSE | difference |")
    print("|---|---|---|---|---|")
    for scenario in args.scenarios:
        for n in args.particles:
            mse = {name: np.empty(args.seeds) for name in VARIANTS}
            for seed in range(args.seeds):
                for name, options in VARIANTS.items():
                    config = RunConfig(scenario=scenario, particles=n, seed=seed, resampler=args.resampler,
                                       **options)
                    mse[name][seed] = run(config).mse
                print(f"\r{scenario} N={n}: seed {seed + 1}/{args.seeds}", end="", file=sys.stderr)
            print(file=sys.stderr)
            for name, values in mse.items():
                m, h = mean_ci(values)
                if name == "no preprocessing":
                    diff = "-"
                else:
                    d, dh = mean_ci(values - mse["no preprocessing"])
                    diff = f"{d:+.3f} ± {dh:.3f}"
                print(f"| {scenario} | {n} | {name} | {m:.3f} ± {h:.3f} | {diff} |")
    print(f"\n({time.perf_counter() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
