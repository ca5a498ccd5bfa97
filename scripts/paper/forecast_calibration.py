"""Are the twin's forecast bands honest? The share of true states inside the 95% band, H steps ahead.

For each scenario and seed: simulate a true path and its observations for k + 20 steps (the seed's own
data), run the bootstrap particle filter (:class:`dtpf.entity.filter.ParticleFilter`, systematic
resampling at every step, N particles) on the first k observations, forecast the weighted set of step k
(before resampling, the set a twin answers from) H = 1 .. 20 steps ahead with
:func:`dtpf.entity.forecast.forecast` (the twin's own streams), and count, for H = 1, 5 and 20 and each
state component, whether the true x_(k+H) of the simulated continuation lies inside the band (the 2.5% and
97.5% weighted quantiles). If the filter's weighted set were the exact posterior p(x_k | z_1:k), the band
would hold the truth with probability 0.95 whatever the data, so over independent seeds the share is
binomial with p = 0.95; the table gives it with its Wilson 95% interval.

Scenarios: ``ungm`` (Eq. 35 with 25: a two-peaked posterior, since z = x^2 / 20 + v cannot tell x from
-x), ``drift`` (a slowly drifting constant seen precisely: particles impoverish) and ``range-bearing``
(docs/examples/range_bearing.py:RangeBearingTarget, simulated: a target in the plane, x, y, vx, vy)::

    python -m dtpf.scripts.paper.forecast_calibration                       # 400 seeds, N = 1000, k = 50
    python -m dtpf.scripts.paper.forecast_calibration --seeds 20 --steps 10  # a smoke run
    python -m dtpf.scripts.paper.forecast_calibration --seeds 300 --ungm-signs  # do misses lose the mirror peak?

``--ungm-signs`` counts, on ``ungm`` at H = 20, the seeds whose band missed the truth and, of those, the
ones whose set of step k held less than 5% of its weight on the sign of the true x_k (the filter lost the
peak the truth was in).

Research, run from a checkout (it reads the example model from docs/examples); the product never
imports it. It prints a Markdown table (docs/results/forecast.md).
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from dtpf.entity import model_ref, models
from dtpf.entity.filter import ParticleFilter
from dtpf.entity.forecast import forecast

__all__ = ["SCENARIOS", "HORIZONS", "wilson", "coverage_of_seed", "calibrate", "main"]

RANGE_BEARING = Path(__file__).resolve().parents[2] / "docs" / "examples" / "range_bearing.py"
SCENARIOS = ("ungm", "drift", "range-bearing")
HORIZONS = (1, 5, 20)
#: The two-sided normal quantile of a 95% interval.
Z95 = 1.959963984540054


def model_of(name: str):
    """The model of a scenario name."""
    if name == "range-bearing":
        return model_ref.resolve(f"{RANGE_BEARING}:RangeBearingTarget")
    return models.get(name)


def component_names(name: str, dim: int) -> list[str]:
    return ["x", "y", "vx", "vy"] if name == "range-bearing" else (["x"] if dim == 1 else
                                                                   [f"x{i}" for i in range(dim)])


def wilson(successes: int, trials: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion (95% by default)."""
    if trials <= 0:
        return float("nan"), float("nan")
    p = successes / trials
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    return max(0.0, centre - half), min(1.0, centre + half)


def coverage_of_seed(model, name: str, seed: int, n: int, k: int, horizons=HORIZONS) -> np.ndarray:
    """(len(horizons), d) booleans: the true state of step k + H inside the forecast's band from step k."""
    horizon = max(horizons)
    rng = np.random.default_rng([seed, SCENARIOS.index(name) if name in SCENARIOS else 99, 20261205])
    truth, observations = model.simulate(k + horizon, rng)
    pf = ParticleFilter(model, observations[:k], n_particles=n, seed=seed, twin=name)
    last = None
    for last in pf:
        pass
    ahead = forecast(model, last.particles, last.weights, last.step, horizon, seed=seed, twin=name)
    out = np.empty((len(horizons), truth.shape[1]), dtype=bool)
    for i, h in enumerate(horizons):
        true = truth[k + h - 1]
        out[i] = (ahead.lower[h - 1] <= true) & (true <= ahead.upper[h - 1])
    return out


def ungm_signs(seeds: int, n: int, k: int, horizon: int = 20) -> tuple[int, int]:
    """(misses at ``horizon``, misses whose set of step k held < 5% weight on the sign of the true x_k)."""
    model, misses, lost = model_of("ungm"), 0, 0
    for seed in range(seeds):
        rng = np.random.default_rng([seed, SCENARIOS.index("ungm"), 20261205])
        truth, observations = model.simulate(k + horizon, rng)
        last = None
        for last in ParticleFilter(model, observations[:k], n_particles=n, seed=seed, twin="ungm"):
            pass
        ahead = forecast(model, last.particles, last.weights, k, horizon, seed=seed, twin="ungm")
        true = truth[k + horizon - 1, 0]
        if not ahead.lower[-1, 0] <= true <= ahead.upper[-1, 0]:
            misses += 1
            same_sign = np.sign(last.particles[:, 0]) == np.sign(truth[k - 1, 0])
            lost += float(last.weights[same_sign].sum()) < 0.05
    return misses, lost


def calibrate(name: str, seeds: int, n: int, k: int, horizons=HORIZONS) -> np.ndarray:
    """(horizons, d) counts of seeds 0 .. seeds - 1 whose truth lay inside the band."""
    model = model_of(name)
    counts = None
    for seed in range(seeds):
        inside = coverage_of_seed(model, name, seed, n, k, horizons).astype(int)
        counts = inside if counts is None else counts + inside
    return counts


def table(results: dict, seeds: int, horizons=HORIZONS) -> str:
    """The Markdown table: a row per scenario and component, a column per horizon."""
    head = "| scenario | component | " + " | ".join(f"H = {h}" for h in horizons) + " |"
    lines = [head, "|---|---|" + "---|" * len(horizons)]
    for name, counts in results.items():
        for j, component in enumerate(component_names(name, counts.shape[1])):
            cells = []
            for i in range(len(horizons)):
                low, high = wilson(int(counts[i, j]), seeds)
                cells.append(f"{counts[i, j] / seeds:.3f} ({low:.3f}-{high:.3f})")
            lines.append(f"| {name} | {component} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=400, help="seeds (data sets) per scenario (default: 400)")
    parser.add_argument("--particles", type=int, default=1000, help="N (default: 1000)")
    parser.add_argument("--steps", type=int, default=50, help="k, the step forecast from (default: 50)")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    parser.add_argument("--ungm-signs", action="store_true",
                        help="instead of the table: ungm's misses at H = 20 and how many lost the true sign's peak")
    args = parser.parse_args(argv)
    if args.seeds < 1 or args.particles < 1 or args.steps < 1:
        print("forecast_calibration: error: --seeds, --particles and --steps must be at least 1", file=sys.stderr)
        return 2
    if args.ungm_signs:
        misses, lost = ungm_signs(args.seeds, args.particles, args.steps)
        print(f"ungm, {args.seeds} seeds, N = {args.particles}, k = {args.steps}: {misses} bands missed the truth at "
              f"H = 20; {lost} of them from a set with less than 5% of its weight on the true x_k's sign")
        return 0
    results = {name: calibrate(name, args.seeds, args.particles, args.steps) for name in args.scenarios}
    print(f"share of true states inside the forecast's 95% band (Wilson 95% interval), {args.seeds} seeds, "
          f"N = {args.particles}, forecast from step k = {args.steps}")
    print()
    print(table(results, args.seeds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
