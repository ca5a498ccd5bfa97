"""Evaluate the system layer's PS policies against fixed PS and the traditional resamplers.

For each scenario (``ungm``, ``ungm-printed``), N and seed (each seed its own
simulated data set, shared by every variant), the in-process pipeline runs:

- the four traditional resamplers without preprocessing;
- DT preprocessing (Eq. 28-30, inherit weights) with fixed PS in {0, 0.5, 0.81, 1},
  then systematic resampling;
- DT preprocessing with each adaptive policy (``rule``, ``predictive``; initial
  PS 0.81, at most 0.25 change per step), then systematic resampling.

It prints, per scenario and N, the MSE over T = 100 with its 95% confidence
interval over seeds, the differences against plain systematic resampling and
against the paper's fixed PS = 0.81, paired by seed (with their 95% CI), the
mean ESS, the mean distinct ancestors
per resampling over N, the number of steps with ESS < N/2 (the resamplings an
adaptive filter with threshold N/2 would run; every variant here resamples at
every step, as the paper) and the wall time per filter step. It also checks
the predictor (correlation of its forecast ESS/N and distinct/N with what
the filter then saw) and draws PS over time for a typical run::

    python -m dtpf.scripts.paper.evaluate_policies              # 200 seeds, N in {100, 500, 1000}
    python -m dtpf.scripts.paper.evaluate_policies --quick      # 10 seeds, N = 100: a smoke run

Progress goes to stderr, the tables to stdout. The variants are ``dtpf compare`` variants and the
statistics are its own (:mod:`dtpf.scripts.compare_stats`): the MSE and difference columns of a cell
are what ``dtpf compare`` prints for it, the command printed at the end of the report.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from dtpf.messages.config import RunConfig
from dtpf.scripts.compare_stats import mean_interval, paired_difference
from dtpf.scripts.compare_variants import Variant, parse_variant
from dtpf.scripts.inprocess import build, simulate

#: The variants, as ``dtpf compare --variant`` reads them (LABEL:FIELD=VALUE,...).
VARIANT_SPECS = (
    "systematic:preprocess=false,resampler=systematic",
    "multinomial:preprocess=false,resampler=multinomial",
    "stratified:preprocess=false,resampler=stratified",
    "residual:preprocess=false,resampler=residual",
    "DT, PS = 0:policy=fixed,ps=0",
    "DT, PS = 0.5:policy=fixed,ps=0.5",
    "DT, PS = 0.81:policy=fixed,ps=0.81",
    "DT, PS = 1:policy=fixed,ps=1",
    "DT, rule:policy=rule,ps=0.81",
    "DT, predictive:policy=predictive,ps=0.81",
)
#: Variants by label.
VARIANTS: dict[str, Variant] = {variant.label: variant for variant in map(parse_variant, VARIANT_SPECS)}
BASELINE = "systematic"
PAPER = "DT, PS = 0.81"
FIGURES = ("mse", "ess", "distinct", "low_ess_steps", "ms_per_step")


@dataclass
class Task:
    scenario: str
    particles: int
    seed: int
    steps: int


def run_variant(config: RunConfig) -> dict:
    """One run: its figures, PS trace and (for simulating policies) forecast checks."""
    truth, observations = simulate(config)
    pf = build(config, observations)
    start = time.perf_counter()
    steps = list(pf)
    elapsed = time.perf_counter() - start
    n = config.particles
    means = np.array([s.mean for s in steps])
    ess = np.array([s.ess for s in steps])
    distinct = [1 + int(np.count_nonzero(s.ancestors[1:] != s.ancestors[:-1])) for s in steps if s.resampled]
    out = dict(mse=float(np.mean((means - truth[: len(steps)]) ** 2)), ess=float(ess.mean()),
               distinct=float(np.mean(distinct)) / n, low_ess_steps=int(np.count_nonzero(ess < n / 2)),
               ms_per_step=1e3 * elapsed / len(steps),
               ps=[s.report.ps if s.report is not None else math.nan for s in steps])
    if pf.preprocessor is not None and pf.preprocessor.system.needs_particles:
        forecasts = pf.preprocessor.system.forecasts
        # The forecast made at step k is of step k + 1: its ESS/N, and the distinct
        # ancestors of its resampling (which step k + 2 records as its parents).
        out["forecast_ess"] = [(f.predicted_ess_ratio, ess[f.step] / n) for f in forecasts if f.step < len(steps)]
        out["forecast_distinct"] = [(f.predicted_distinct_ratio, steps[f.step + 1].parents / n)
                                    for f in forecasts if f.step + 1 < len(steps)]
        out["forecast_ess_now"] = [(f.ess_ratio, ess[f.step] / n) for f in forecasts if f.step < len(steps)]
    return out


def _warm_up() -> None:
    """Load every compiled function in a worker, so no run's time per step includes it."""
    for variant in VARIANTS.values():
        run_variant(variant.config(RunConfig(particles=50, steps=3), seed=0))


def run_task(task: Task) -> tuple[Task, dict[str, dict]]:
    base = RunConfig(scenario=task.scenario, particles=task.particles, steps=task.steps)
    results = {label: run_variant(variant.config(base, seed=task.seed)) for label, variant in VARIANTS.items()}
    return task, results


def compare_command(scenario: str, particles: int, seeds: int, steps: int, baseline: str = BASELINE) -> str:
    """The ``dtpf compare`` command that gives the MSE and difference columns of one cell."""
    variants = " ".join(f"--variant '{spec}'" for spec in VARIANT_SPECS)
    return (f"dtpf compare --scenario {scenario} -n {particles} -T {steps} --seeds {seeds} {variants} "
            f"--baseline '{baseline}'")


def _fmt(value: float, half: float, digits: int) -> str:
    return f"{value:.{digits}f} ± {half:.{digits}f}"


def table(cells: dict[tuple[str, int], dict[int, dict[str, dict]]]) -> str:
    lines = ["| scenario | N | variant | MSE | difference vs systematic | difference vs DT, PS = 0.81 | mean ESS "
             "| distinct / N | steps ESS < N/2 | ms / step |", "|---|---|---|---|---|---|---|---|---|---|"]
    for (scenario, n), by_seed in cells.items():
        seeds = sorted(by_seed)
        digits = 2 if scenario == "ungm" else 3
        base = np.array([by_seed[s][BASELINE]["mse"] for s in seeds])
        paper = np.array([by_seed[s][PAPER]["mse"] for s in seeds])
        for label in VARIANTS:
            get = {f: np.array([by_seed[s][label][f] for s in seeds]) for f in FIGURES}
            m, h = mean_interval(get["mse"])
            diff = "-" if label == BASELINE else _fmt(*paired_difference(get["mse"], base), digits)
            vs_paper = _fmt(*paired_difference(get["mse"], paper), digits) \
                if label.startswith("DT") and label != PAPER else "-"
            lines.append(f"| {scenario} | {n} | {label} | {_fmt(m, h, digits)} | {diff} | {vs_paper} "
                         f"| {get['ess'].mean():.1f} "
                         f"| {get['distinct'].mean():.3f} | {get['low_ess_steps'].mean():.1f} "
                         f"| {get['ms_per_step'].mean():.2f} |")
    return "\n".join(lines)


def predictor_table(cells) -> str:
    lines = ["| scenario | N | corr(forecast ESS/N, next ESS/N) | corr(current ESS/N, next ESS/N) "
             "| corr(forecast distinct/N, next distinct/N) | PS changes per run (rule, predictive) |",
             "|---|---|---|---|---|---|"]
    for (scenario, n), by_seed in cells.items():
        runs = [by_seed[s]["DT, predictive"] for s in sorted(by_seed)]

        def corr(key):
            pairs = np.array([p for r in runs for p in r[key]], dtype=np.float64)
            return float(np.corrcoef(pairs[:, 0], pairs[:, 1])[0, 1])

        changes = []
        for label in ("DT, rule", "DT, predictive"):
            ps = [np.asarray(by_seed[s][label]["ps"]) for s in sorted(by_seed)]
            changes.append(np.mean([np.count_nonzero(np.diff(p) != 0) for p in ps]))
        lines.append(f"| {scenario} | {n} | {corr('forecast_ess'):.3f} | {corr('forecast_ess_now'):.3f} "
                     f"| {corr('forecast_distinct'):.3f} | {changes[0]:.1f}, {changes[1]:.1f} |")
    return "\n".join(lines)


def plot_typical(cells, path: Path, steps: int) -> str:
    """PS over time of the rule and predictive policies on the run whose predictive MSE is the
    median of the largest-N ungm cell (or the first cell), with ESS/N and its forecast."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [key for key in cells if key[0] == "ungm"] or list(cells)
    scenario, n = max(keys, key=lambda key: key[1])
    by_seed = cells[(scenario, n)]
    mse = {s: by_seed[s]["DT, predictive"]["mse"] for s in by_seed}
    ordered = sorted(mse, key=mse.get)
    seed = ordered[len(ordered) // 2]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    k = np.arange(1, steps + 1)
    for label, style in (("DT, rule", "-"), ("DT, predictive", "-"), ("DT, PS = 0.81", ":")):
        top.step(k, by_seed[seed][label]["ps"], style, where="post", label=label.replace("DT, ", ""))
    top.set_ylabel("PS in force")
    top.set_ylim(-0.05, 1.05)
    top.legend(loc="lower left", fontsize=8)
    top.set_title(f"{scenario}, N = {n}, seed {seed} (median MSE of the predictive policy over "
                  f"{len(by_seed)} seeds)", fontsize=9)
    run = by_seed[seed]["DT, predictive"]
    now = np.array(run["forecast_ess_now"])
    forecast = np.array(run["forecast_ess"], dtype=np.float64)
    bottom.plot(k[: len(now)], now[:, 0], label="ESS/N (mirror)")
    bottom.plot(k[1: len(forecast) + 1], forecast[:, 0], "--", label="ESS/N forecast one step ahead")
    bottom.set_ylabel("ESS / N")
    bottom.set_xlabel("step k")
    bottom.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"{scenario}, N = {n}, seed {seed}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.paper.evaluate_policies",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=200, help="data sets per cell (default: %(default)s)")
    parser.add_argument("--particles", type=int, nargs="+", default=[100, 500, 1000], help="N values")
    parser.add_argument("--scenarios", nargs="+", default=["ungm", "ungm-printed"])
    parser.add_argument("--steps", type=int, default=100, help="T (default: %(default)s)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default: %(default)s)")
    parser.add_argument("--plot", type=Path, default=Path("docs/system-layer-ps.png"),
                        help="PNG of PS over time for a typical run (default: %(default)s)")
    parser.add_argument("--quick", action="store_true", help="10 seeds and N = 100 only: a smoke run")
    args = parser.parse_args(argv)
    if args.quick:
        args.seeds, args.particles = 10, [100]
    if args.seeds < 2:
        parser.error("--seeds must be at least 2 (confidence intervals)")
    tasks = [Task(sc, n, seed, args.steps) for sc in args.scenarios for n in args.particles
             for seed in range(args.seeds)]
    cells: dict[tuple[str, int], dict[int, dict]] = {(sc, n): {} for sc in args.scenarios for n in args.particles}
    start = time.perf_counter()
    with Pool(args.workers, initializer=_warm_up) as pool:
        for done, (task, results) in enumerate(pool.imap_unordered(run_task, tasks, chunksize=2), 1):
            cells[(task.scenario, task.particles)][task.seed] = results
            elapsed = time.perf_counter() - start
            print(f"\r{done}/{len(tasks)} (scenario, N, seed) done, {elapsed:.0f} s, "
                  f"about {elapsed / done * (len(tasks) - done):.0f} s left ", end="", file=sys.stderr)
    print(file=sys.stderr)
    elapsed = time.perf_counter() - start
    command = "python -m dtpf.scripts.paper.evaluate_policies" + (" --quick" if args.quick else f" --seeds {args.seeds}")
    print(f"`{command}`: T = {args.steps}, {args.seeds} seeds per cell, {len(VARIANTS)} variants, "
          f"{args.workers} worker processes; MSE mean ± 95% CI over seeds; differences = variant - plain "
          f"systematic and variant - DT with PS = 0.81, paired by seed; ms / step is the wall time of one filter step with its layers "
          f"(in process, measured while {args.workers} workers ran).\n")
    print(table(cells))
    print("\nPredictor check (from the predictive-policy runs; the forecast made at step k is of step k + 1):\n")
    print(predictor_table(cells))
    which = plot_typical(cells, args.plot, args.steps)
    print(f"\nPS over time: {args.plot} ({which}).")
    scenario, n = next(iter(cells))
    print(f"\nThe MSE and the differences against systematic of a cell (here {scenario}, N = {n}) with dtpf compare "
          f"(add --baseline '{PAPER}' for the other column):\n\n    "
          f"{compare_command(scenario, n, args.seeds, args.steps)}")
    print(f"\n({elapsed:.0f} s on {args.workers} workers)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
