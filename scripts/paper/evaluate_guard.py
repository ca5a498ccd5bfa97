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

The runs are ``dtpf compare``'s: each (scenario, N) is a cell (:func:`dtpf.scripts.compare_plan.make_plan`)
of the variants of :data:`VARIANT_SPECS` (``dtpf compare --variant`` specs), each scenario a run option
(``drift+100`` the model reference ``dtpf.scripts.paper.evaluate_guard:DRIFT_PLUS_100``, the video's error
the metric ``squared-distance`` over components 0 and 1), run over the seeds by
:func:`dtpf.scripts.compare_runs.run_all`; the intervals and differences are :mod:`dtpf.scripts.compare_stats`'
at the exact normal quantile. What stays here: the baseline chosen per cell (the best traditional
resampler), the second difference column, the Kalman floor on the drifting constant and the verdicts.
The command of ``dtpf compare`` that gives a cell's error and difference columns is printed at the end.

Progress goes to stderr, the tables to stdout; ``--csv`` is a ``dtpf compare`` CSV: every run's figures,
appended as each ends, and the same command again runs only what the file lacks.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from dtpf.entity import model_ref, models, sources
from dtpf.messages.config import RunConfig
from dtpf.scripts.compare_csv import CompareCsv, RunRow
from dtpf.scripts.compare_plan import Cell, Plan, make_plan, tasks_of, warm_configs
from dtpf.scripts.compare_runs import run_all
from dtpf.scripts.compare_stats import BETTER, WORSE, compare
from dtpf.scripts.compare_variants import Variant, parse_variant
from dtpf.scripts.console import TaskProgress
from dtpf.scripts.inprocess import simulate
from dtpf.scripts.paper.common import Z95

TRADITIONAL = ("systematic", "multinomial", "stratified", "residual")
#: The relative rule's options (PS and weights chosen on pilot seeds, see the module docstring) and the paper's.
_RELATIVE, _PAPER = "move_rule=relative,weight_rule=likelihood,ps=0", "move_rule=paper,weight_rule=inherit,ps=0.81"

#: The variants, as ``dtpf compare --variant`` reads them (LABEL:FIELD=VALUE,...).
VARIANT_SPECS = (
    *(f"{name}:preprocess=false,resampler={name}" for name in TRADITIONAL),
    f"DT paper rule, PS 0.81:policy=fixed,{_PAPER}",
    f"DT relative rule, PS 0:policy=fixed,{_RELATIVE}",
    f"guard, paper rule:policy=guard,{_PAPER}",
    f"guard, relative rule:policy=guard,{_RELATIVE}",
    f"guard-observed, paper rule:policy=guard-observed,{_PAPER}",
    f"guard-observed, relative rule:policy=guard-observed,{_RELATIVE}",
    "roughening:preprocess=false,jitter=roughening",
    "regularised:preprocess=false,jitter=regularised",
)
#: Variants by label.
VARIANTS: dict[str, Variant] = {variant.label: variant for variant in map(parse_variant, VARIANT_SPECS)}
GUARDS = tuple(label for label in VARIANTS if label.startswith("guard"))
#: ``--pilot``: the relative rule's PS and weights, tried on seeds of their own (10000 on) before the table.
PILOT_SPECS = (
    VARIANT_SPECS[0],
    *(f"DT relative rule, PS {ps:g}, {weights}:policy=fixed,move_rule=relative,weight_rule={weights},ps={ps:g}"
      for ps in (0.81, 0.0) for weights in ("inherit", "likelihood")),
)
PILOT_VARIANTS: dict[str, Variant] = {variant.label: variant for variant in map(parse_variant, PILOT_SPECS)}
PILOT_SEED = 10_000
SCENARIOS = ("ungm", "drift", "drift+100", "range-bearing", "video")
#: The range-bearing target: the user-model example of docs/examples, by reference.
RANGE_BEARING = Path(__file__).resolve().parents[2] / "docs" / "examples" / "range_bearing.py"
#: The drifting constant with its state shifted by 100 (``drift+100``), a model reference's target.
DRIFT_PLUS_100 = models.DriftModel(prior_mean=100.0)
#: The run options of each scenario that is not a built-in one, as ``dtpf compare`` takes them (the range-bearing
#: file relative to the repository's root, as the printed command gives it).
REFERENCES = {"drift+100": f"{__name__}:DRIFT_PLUS_100",
              "range-bearing": "docs/examples/range_bearing.py:RangeBearingTarget"}
#: The video's frames: its runs have at most this many steps.
FRAMES = 50
KALMAN = "Kalman (exact)"


def scenario_model(name: str):
    """(RunConfig options, model object) of a scenario of this evaluation."""
    if name == "drift+100":
        return dict(scenario="drift"), DRIFT_PLUS_100
    if name == "range-bearing":
        reference = f"{RANGE_BEARING}:RangeBearingTarget"
        return dict(model=reference), model_ref.resolve(reference)
    return dict(scenario=name), models.get(name)


def scenario_options(name: str, printed: bool = False) -> dict:
    """The run options of a scenario (``printed``: the range-bearing file as the printed command names it)."""
    if name == "range-bearing" and not printed:
        return dict(model=f"{RANGE_BEARING}:RangeBearingTarget")
    return dict(model=REFERENCES[name]) if name in REFERENCES else dict(scenario=name)


def metric_of(scenario: str) -> tuple[str, str | None]:
    """(metric, components) of a scenario: the video's is the squared distance of the estimated to the true
    centre, pixels^2; every other one's the MSE over steps and state dimensions."""
    return ("squared-distance", "0,1") if scenario == "video" else ("mse", None)


def _errors(scenario: str, means: np.ndarray, truth: np.ndarray) -> float:
    """The error of :func:`metric_of` from the posterior means and the truth."""
    if scenario == "video":  # squared centre error, pixels^2
        return float(np.mean(np.sum((means[:, :2] - truth[:, :2]) ** 2, axis=1)))
    return float(np.mean((means - truth) ** 2))


def runs_on(scenario: str, label: str) -> bool:
    """The what-if guard cannot run on the video (it cannot draw observations)."""
    return not (scenario == "video" and VARIANTS[label].fields.get("policy") == "guard")


def cell_name(scenario: str, n: int) -> str:
    return f"{scenario}, N = {n}"


def cell_plan(scenario: str, n: int, steps: int, seeds: list[int], pilot: bool = False) -> Plan:
    """The ``dtpf compare`` plan of one (scenario, N) cell: every variant that can run there, checked."""
    variants = list(PILOT_VARIANTS.values()) if pilot else \
        [variant for label, variant in VARIANTS.items() if runs_on(scenario, label)]
    base = RunConfig(particles=n, steps=min(steps, FRAMES) if scenario == "video" else steps, twin="guard-1",
                     **scenario_options(scenario))
    metric, components = metric_of(scenario)
    return make_plan(base, variants, seeds, "systematic", metric, components, steps_given=True,
                     cell=Cell(cell_name(scenario, n)))


def compare_command(scenario: str, n: int, steps: int, seeds: int, baseline: str) -> str:
    """The ``dtpf compare`` command that gives the error and difference columns of one cell (``baseline``: the
    cell's best traditional resampler; systematic for the other difference column)."""
    options = " ".join(f"--{name} {value}" for name, value in scenario_options(scenario, printed=True).items())
    metric, components = metric_of(scenario)
    judged = "" if metric == "mse" else f" --metric {metric} --components {components}"
    variants = [f"--variant '{VARIANTS[label].label}:{VARIANTS[label].spec}'" for label in VARIANTS
                if runs_on(scenario, label)]
    steps = min(steps, FRAMES) if scenario == "video" else steps
    return " \\\n      ".join([f"dtpf compare {options} -n {n} -T {steps} --twin guard-1 --seeds {seeds}{judged}",
                               *variants, f"--baseline {baseline}"])


def kalman_errors(plan: Plan) -> dict[int, float] | None:
    """The exact posterior mean's error on each seed of a drifting-constant cell (the floor of any filter), from
    the same simulated data set the filters ran on; None for any other model."""
    config = plan.configs[plan.labels[0]]
    model = sources.load_model(config, check=False)
    if not isinstance(model, models.DriftModel):
        return None
    out = {}
    for seed in plan.seeds:
        truth, observations = simulate(config.model_copy(update={"seed": seed}), model)
        out[seed] = float(np.mean((model.kalman(observations) - truth) ** 2))
    return out


def figures(row: RunRow) -> dict:
    """The figures the table shows of a compare row."""
    return dict(error=row.value, ess=row.mean_ess, distinct=row.distinct, on=row.preprocessed, ms=row.ms_per_step)


def _num(value: float) -> str:
    return f"{value:.4g}"


def _sign(verdict: str) -> int:
    return {BETTER: -1, WORSE: 1}.get(verdict, 0)


def cell_rows(by_seed: dict[int, dict[str, dict]]) -> tuple[str, list[dict]]:
    """(best traditional label, one row per variant) of one (scenario, N) cell."""
    seeds = sorted(by_seed)
    labels = [label for label in [*VARIANTS, *PILOT_VARIANTS, KALMAN] if label in by_seed[seeds[0]]]
    labels = list(dict.fromkeys(labels))
    error = {label: np.array([by_seed[s][label]["error"] for s in seeds]) for label in labels}
    best = min((label for label in TRADITIONAL if label in error), key=lambda label: error[label].mean())
    rows = []
    for label in labels:
        vs_best = compare(error[label], error[best], higher_is_better=False, is_baseline=label == best, z=Z95)
        vs_systematic = compare(error[label], error["systematic"], higher_is_better=False,
                                is_baseline=label == "systematic", z=Z95)
        row = dict(variant=label, error=vs_best.mean, error_ci=vs_best.mean_half, diff=vs_best.difference,
                   diff_ci=vs_best.difference_half, vs_systematic=vs_systematic.difference,
                   vs_systematic_ci=vs_systematic.difference_half, significant=_sign(vs_best.verdict),
                   significant_vs_systematic=_sign(vs_systematic.verdict))
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
    parser.add_argument("--csv", type=Path, default=None,
                        help="a dtpf compare CSV: every run's figures, appended as each ends; the same command "
                             "again runs only the runs it lacks")
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
    seeds = list(range(first_seed, first_seed + args.seeds))
    keys = [(sc, n) for sc in args.scenarios for n in args.particles]
    plans = {key: cell_plan(*key, args.steps, seeds, args.pilot) for key in keys}
    rows: dict[tuple[str, str, int], RunRow] = {}
    store = CompareCsv(args.csv) if args.csv is not None else None
    if store is not None:
        held, _ = store.read()
        store.check(held, {key: text for plan in plans.values() for key, text in plan.settings().items()})
        wanted = {(plan.cell, label, seed) for plan in plans.values() for label in plan.labels for seed in seeds}
        rows = {key: row for key, row in held.items() if key in wanted}
        store.start()
    tasks = tasks_of(list(plans.values()), set(rows))
    progress, finished = TaskProgress("evaluate_guard", len(tasks)), []

    def keep(row: RunRow) -> None:
        if store is not None:
            store.append(row)
        rows[row.key] = row
        finished.append(row.key)
        progress(len(finished))

    start = time.perf_counter()
    try:
        run_all(tasks, args.workers, warm_configs(list(plans.values())), keep)
    except KeyboardInterrupt:
        print(f"evaluate_guard: interrupted; {args.csv or 'no --csv, so the finished runs are not kept'}"
              f"{' holds every finished run and the same command goes on' if store else ''}", file=sys.stderr)
        return 130
    elapsed = time.perf_counter() - start
    given = list(argv if argv is not None else sys.argv[1:])
    command = " ".join(["python -m dtpf.scripts.paper.evaluate_guard", *given])
    print(f"`{command}`: T = {args.steps} (video: its {FRAMES} frames), {args.seeds} seeds per cell "
          f"(from seed {first_seed}), {len(PILOT_VARIANTS if args.pilot else VARIANTS)} variants, {args.workers} worker processes; error mean ± 95% CI over seeds; difference "
          f"= variant - best traditional resampler of the cell, paired by seed, ± its 95% CI, marked where the "
          f"interval excludes 0.\n")
    verdicts, bests = [], {}
    for (scenario, n), plan in plans.items():
        by_seed = {seed: {label: figures(rows[(plan.cell, label, seed)]) for label in plan.labels} for seed in seeds}
        floor = kalman_errors(plan)
        if floor is not None:
            for seed in seeds:
                by_seed[seed][KALMAN] = dict(error=floor[seed])
        best, table_rows = cell_rows(by_seed)
        bests[(scenario, n)] = best
        print(table(scenario, n, best, table_rows) + "\n")
        if not args.pilot:
            verdicts.append(verdict(scenario, n, best, table_rows))
    if verdicts:
        print("Verdicts:\n")
        for line in verdicts:
            print(f"- {line}")
    if not args.pilot:
        (scenario, n), best = next(iter(bests.items()))
        print(f"\nThe error and the difference against the best traditional resampler of a cell (here {scenario}, "
              f"N = {n}, run from the repository's root) with dtpf compare (--baseline systematic for the other "
              f"column; its intervals use z = 1.96):\n\n    {compare_command(scenario, n, args.steps, args.seeds, best)}")
    print(f"\n({elapsed:.0f} s on {args.workers} workers)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
