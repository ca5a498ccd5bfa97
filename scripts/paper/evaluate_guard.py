"""Does the system layer ever make the filter worse? The guard policies against the field's cures.

For each scenario, N and seed (each seed its own simulated data set, shared by every variant, so all
comparisons are paired by seed) the in-process pipeline runs:

- the four traditional resamplers, no preprocessing;
- DT preprocessing always on: the paper's rule (Eq. 29-30, PS = 0.81, inherit weights) and the
  relative rule (translation invariant, PS = 0, likelihood weights; chosen on pilot seeds 10000-10199,
  not on the seeds of the table);
- the guard (what-if on the twin's simulation; on only if predicted better than off with one-sided
  95% confidence) with each rule;
- guard-observed (on only while the real observations favour it by a log Bayes factor above log 19)
  with each rule;
- roughening (Gordon, Salmond and Smith 1993) and the regularised filter's kernel (Musso, Oudjane and
  Le Gland 2001), after systematic resampling, no preprocessing.

Scenarios: ``ungm`` (Eq. 35 with 25), ``drift`` (a slowly drifting constant seen precisely: particles
impoverish), ``drift+100`` (the same, the state shifted by 100: a translation-invariant method gives
the same errors as on ``drift``), ``range-bearing`` (docs/examples/range_bearing.py: a target in the
plane, small process noise, precise bearings) and ``video`` (the paper's tracking scene; the what-if
guard needs simulated observations, which the video cannot draw, so it is left out there; the error is
the squared distance of the estimated to the true centre, in pixels squared).

It prints one table per scenario: the error (MSE over steps and state dimensions) with its 95% CI over
seeds; the paired difference against the *best traditional resampler of that cell* (lowest mean) with
its 95% CI; mean ESS; distinct ancestors per resampling / N; the share of steps preprocessed; ms per
step (wall time of one in-process step with its layers, measured inside the workers). Then a verdict
per scenario::

    python -m dtpf.scripts.paper.evaluate_guard                 # 1000 seeds, N = 100, every scenario
    python -m dtpf.scripts.paper.evaluate_guard --quick         # 8 seeds, T = 25: a smoke run

Progress goes to stderr, the tables to stdout; ``--csv`` keeps every run's figures.
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from dtpf.entity import model_ref, models
from dtpf.messages.config import RunConfig
from dtpf.scripts.console import TaskProgress
from dtpf.scripts.inprocess import build, simulate
from dtpf.scripts.paper.common import mean_ci, significance

TRADITIONAL = ("systematic", "multinomial", "stratified", "residual")
#: The relative rule's options (PS and weights chosen on pilot seeds, see the module docstring).
RELATIVE = dict(move_rule="relative", weight_rule="likelihood", ps=0.0)
PAPER = dict(move_rule="paper", weight_rule="inherit", ps=0.81)

#: Variants by label: RunConfig options.
VARIANTS: dict[str, dict] = {
    **{name: dict(preprocess=False, resampler=name) for name in TRADITIONAL},
    "DT paper rule, PS 0.81": dict(policy="fixed", **PAPER),
    "DT relative rule, PS 0": dict(policy="fixed", **RELATIVE),
    "guard, paper rule": dict(policy="guard", **PAPER),
    "guard, relative rule": dict(policy="guard", **RELATIVE),
    "guard-observed, paper rule": dict(policy="guard-observed", **PAPER),
    "guard-observed, relative rule": dict(policy="guard-observed", **RELATIVE),
    "roughening": dict(preprocess=False, jitter="roughening"),
    "regularised": dict(preprocess=False, jitter="regularised"),
}
GUARDS = tuple(label for label in VARIANTS if label.startswith("guard"))
#: ``--pilot``: the relative rule's PS and weights, tried on seeds of their own (10000 on) before the table.
PILOT_VARIANTS: dict[str, dict] = {
    "systematic": VARIANTS["systematic"],
    **{f"DT relative rule, PS {ps:g}, {weights}": dict(policy="fixed", move_rule="relative", weight_rule=weights, ps=ps)
       for ps in (0.81, 0.0) for weights in ("inherit", "likelihood")},
}
PILOT_SEED = 10_000
SCENARIOS = ("ungm", "drift", "drift+100", "range-bearing", "video")
#: The range-bearing target: the user-model example of docs/examples, by reference.
RANGE_BEARING = Path(__file__).resolve().parents[2] / "docs" / "examples" / "range_bearing.py"


def scenario_model(name: str):
    """(RunConfig options, model object) of a scenario of this evaluation."""
    if name == "drift+100":
        return dict(scenario="drift"), models.DriftModel(prior_mean=100.0)
    if name == "range-bearing":
        reference = f"{RANGE_BEARING}:RangeBearingTarget"
        return dict(model=reference), model_ref.resolve(reference)
    return dict(scenario=name), models.get(name)


def runs_on(scenario: str, label: str) -> bool:
    """The what-if guard cannot run on the video (it cannot draw observations)."""
    return not (scenario == "video" and VARIANTS[label].get("policy") == "guard")


@dataclass(frozen=True)
class Task:
    scenario: str
    particles: int
    seed: int
    steps: int
    pilot: bool = False


def _errors(scenario: str, means: np.ndarray, truth: np.ndarray) -> float:
    if scenario == "video":  # squared centre error, pixels^2
        return float(np.mean(np.sum((means[:, :2] - truth[:, :2]) ** 2, axis=1)))
    return float(np.mean((means - truth) ** 2))


def task_config(task: Task, options: dict, **variant) -> RunConfig:
    """The run of ``task`` on its scenario (``options``) with a variant's options."""
    return RunConfig(particles=task.particles, seed=task.seed, steps=task.steps, twin="guard-1", **options, **variant)


def run_variant(task: Task, label: str, model, options: dict, truth: np.ndarray, observations: np.ndarray) -> dict:
    """One variant on the task's data set (``truth``, ``observations``: shared by every variant)."""
    variants = PILOT_VARIANTS if task.pilot else VARIANTS
    pf = build(task_config(task, options, **variants[label]), observations, model)
    start = time.perf_counter()
    steps = list(pf)
    elapsed = time.perf_counter() - start
    n = task.particles
    means = np.array([s.mean for s in steps])
    distinct = [1 + int(np.count_nonzero(s.ancestors[1:] != s.ancestors[:-1])) for s in steps if s.resampled]
    on = [s.report is not None and s.report.n_processed > 0 for s in steps]
    return dict(error=_errors(task.scenario, means, truth[: len(steps)]), ess=float(np.mean([s.ess for s in steps])),
                distinct=float(np.mean(distinct)) / n, on=float(np.mean(on)), ms=1e3 * elapsed / len(steps))


_MODELS: dict[str, tuple[dict, object]] = {}


def run_task(task: Task) -> tuple[Task, dict[str, dict]]:
    if task.scenario not in _MODELS:
        _MODELS[task.scenario] = scenario_model(task.scenario)
    options, model = _MODELS[task.scenario]
    variants = PILOT_VARIANTS if task.pilot else VARIANTS
    truth, observations = simulate(task_config(task, options), model)  # one data set for every variant
    results = {label: run_variant(task, label, model, options, truth, observations) for label in variants
               if task.pilot or runs_on(task.scenario, label)}
    if isinstance(model, models.DriftModel):  # the exact posterior mean: the floor of any filter
        results["Kalman (exact)"] = dict(error=float(np.mean((model.kalman(observations) - truth) ** 2)))
    return task, results


def _warm_up(scenarios) -> None:
    """Load every compiled function and scenario (the video's scene) in a worker, so no run's time per
    step includes it."""
    for scenario in scenarios:
        run_task(Task(scenario, 20, 0, 3))


def _num(value: float) -> str:
    return f"{value:.4g}"


def cell_rows(by_seed: dict[int, dict[str, dict]]) -> tuple[str, list[dict]]:
    """(best traditional label, one row per variant) of one (scenario, N) cell."""
    seeds = sorted(by_seed)
    labels = [label for label in [*VARIANTS, *PILOT_VARIANTS, "Kalman (exact)"] if label in by_seed[seeds[0]]]
    labels = list(dict.fromkeys(labels))
    error = {label: np.array([by_seed[s][label]["error"] for s in seeds]) for label in labels}
    best = min((label for label in TRADITIONAL if label in error), key=lambda label: error[label].mean())
    rows = []
    for label in labels:
        m, h = mean_ci(error[label])
        d, dh = mean_ci(error[label] - error[best])
        s, sh = mean_ci(error[label] - error["systematic"])
        row = dict(variant=label, error=m, error_ci=h, diff=d, diff_ci=dh, vs_systematic=s, vs_systematic_ci=sh,
                   significant=significance(d, dh) if label != best else 0,
                   significant_vs_systematic=significance(s, sh) if label != "systematic" else 0)
        for figure in ("ess", "distinct", "on", "ms"):
            values = [by_seed[s][label].get(figure) for s in seeds]
            row[figure] = float(np.mean(values)) if values[0] is not None else math.nan
        rows.append(row)
    return best, rows


def table(scenario: str, n: int, best: str, rows: list[dict]) -> str:
    lines = [f"**{scenario}, N = {n}** (best traditional resampler: {best})", "",
             "| variant | error | difference vs best traditional | difference vs systematic | mean ESS "
             "| distinct / N | preprocessed | ms / step |", "|---|---|---|---|---|---|---|---|"]
    marks = {-1: " (better)", 1: " (worse)", 0: ""}
    for row in rows:
        diff = "-" if row["variant"] == best else \
            f"{_num(row['diff'])} ± {_num(row['diff_ci'])}{marks[row['significant']]}"
        vs = "-" if row["variant"] == "systematic" else \
            f"{_num(row['vs_systematic'])} ± {_num(row['vs_systematic_ci'])}{marks[row['significant_vs_systematic']]}"
        extra = ("| - | - | - | - |" if math.isnan(row["ess"]) else
                 f"| {row['ess']:.1f} | {row['distinct']:.3f} | {100 * row['on']:.0f}% | {row['ms']:.2f} |")
        lines.append(f"| {row['variant']} | {_num(row['error'])} ± {_num(row['error_ci'])} | {diff} | {vs} {extra}")
    return "\n".join(lines)


def verdict(scenario: str, n: int, best: str, rows: list[dict]) -> str:
    """The guards against the best traditional resampler, in words (only what the CIs show)."""
    by = {row["variant"]: row for row in rows}
    guards = [by[label] for label in GUARDS if label in by]
    best_guard = min(guards, key=lambda row: row["error"])
    worse = [row["variant"] for row in guards if row["significant"] > 0]
    better = [row["variant"] for row in guards if row["significant"] < 0]
    worse_than_own = [row["variant"] for row in guards if row["significant_vs_systematic"] > 0]
    words = [f"{scenario}, N = {n}: best guard {best_guard['variant']} "
             f"({_num(best_guard['diff'])} ± {_num(best_guard['diff_ci'])} against {best};"]
    words.append("significantly better" if best_guard["significant"] < 0 else
                 "significantly worse" if best_guard["significant"] > 0 else "within the noise")
    words[-1] += ")."
    words.append(f"Significantly worse than {best}: {', '.join(worse) or 'no guard'}; "
                 f"significantly better: {', '.join(better) or 'no guard'}; significantly worse than "
                 f"systematic, the resampler the guards run: {', '.join(worse_than_own) or 'no guard'}.")
    cures = [by[label] for label in ("roughening", "regularised")]
    words.append("Cures: " + "; ".join(f"{row['variant']} {_num(row['diff'])} ± {_num(row['diff_ci'])}"
                                       for row in cures) + ".")
    return " ".join(words)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.paper.evaluate_guard",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=1000, help="data sets per cell (default: %(default)s)")
    parser.add_argument("--particles", type=int, nargs="+", default=[100], help="N values (default: 100)")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    parser.add_argument("--steps", type=int, default=100, help="T (default: %(default)s; the video has 50 frames)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default: %(default)s)")
    parser.add_argument("--csv", type=Path, default=None, help="write every run's figures to this CSV file")
    parser.add_argument("--quick", action="store_true", help="8 seeds, T = 25, N = 50: a smoke run")
    parser.add_argument("--pilot", action="store_true",
                        help=f"the pilot that chose the relative rule's options: its four (PS, weights) pairs against "
                             f"systematic on seeds {PILOT_SEED} on (not the table's), drift and range-bearing; "
                             f"--seeds default 200")
    args = parser.parse_args(argv)
    if args.quick:
        args.seeds, args.steps, args.particles = 8, 25, [50]
    first_seed = 0
    if args.pilot:
        first_seed = PILOT_SEED
        if "--seeds" not in (argv if argv is not None else sys.argv[1:]):
            args.seeds = 200
        if "--scenarios" not in (argv if argv is not None else sys.argv[1:]):
            args.scenarios = ["drift", "range-bearing"]
    if args.seeds < 2:
        parser.error("--seeds must be at least 2 (confidence intervals)")
    frames = 50
    tasks = [Task(sc, n, seed, min(args.steps, frames) if sc == "video" else args.steps, args.pilot)
             for sc in args.scenarios for n in args.particles for seed in range(first_seed, first_seed + args.seeds)]
    cells: dict[tuple[str, int], dict[int, dict]] = {(sc, n): {} for sc in args.scenarios for n in args.particles}
    progress = TaskProgress("evaluate_guard", len(tasks))
    start = time.perf_counter()
    if args.workers <= 1:
        _warm_up(args.scenarios)
        for i, task in enumerate(tasks, 1):
            done, results = run_task(task)
            cells[(done.scenario, done.particles)][done.seed] = results
            progress(i)
    else:
        context = get_context("fork")
        with context.Pool(args.workers, initializer=_warm_up, initargs=(args.scenarios,)) as pool:
            for i, (done, results) in enumerate(pool.imap_unordered(run_task, tasks, chunksize=4), 1):
                cells[(done.scenario, done.particles)][done.seed] = results
                progress(i)
    elapsed = time.perf_counter() - start
    given = list(argv if argv is not None else sys.argv[1:])
    command = " ".join(["python -m dtpf.scripts.paper.evaluate_guard", *given])
    print(f"`{command}`: T = {args.steps} (video: its {frames} frames), {args.seeds} seeds per cell "
          f"(from seed {first_seed}), {len(PILOT_VARIANTS if args.pilot else VARIANTS)} variants, {args.workers} worker processes; error mean ± 95% CI over seeds; difference "
          f"= variant - best traditional resampler of the cell, paired by seed, ± its 95% CI, marked where the "
          f"interval excludes 0.\n")
    verdicts = []
    for (scenario, n), by_seed in cells.items():
        best, rows = cell_rows(by_seed)
        print(table(scenario, n, best, rows) + "\n")
        if not args.pilot:
            verdicts.append(verdict(scenario, n, best, rows))
    if verdicts:
        print("Verdicts:\n")
        for line in verdicts:
            print(f"- {line}")
    print(f"\n({elapsed:.0f} s on {args.workers} workers)")
    if args.csv is not None:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        with open(args.csv, "w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["scenario", "particles", "seed", "variant", "error", "ess", "distinct", "on", "ms"])
            for (scenario, n), by_seed in cells.items():
                for seed, results in sorted(by_seed.items()):
                    for label, figures in results.items():
                        writer.writerow([scenario, n, seed, label] + [figures.get(f, "") for f in
                                                                      ("error", "ess", "distinct", "on", "ms")])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
