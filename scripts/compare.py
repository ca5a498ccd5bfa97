"""``dtpf compare``: run variants of a run over many seeds and say which differ, with 95% intervals.

Each seed is one data set (a simulation of the model, or the same observation file) that every variant
filters, so a variant's difference to the baseline is paired by seed::

    dtpf compare --variant plain:preprocess=false --variant dt:policy=fixed,ps=0.81 \\
        --baseline plain --seeds 200 -n 100 --csv runs/compare.csv

The variants (:mod:`~dtpf.scripts.compare_variants`) are read and, in every cell of a grid
(:mod:`~dtpf.scripts.compare_plan`), each one's run of seed 0 is built and its model checked before any
run starts; the runs (:mod:`~dtpf.scripts.compare_runs`) go to worker processes, each judged by its
metric (:mod:`~dtpf.scripts.compare_metrics`); each finished run is a CSV row at once
(:mod:`~dtpf.scripts.compare_csv`), which a second call with the same CSV does not run again; the
report (:mod:`~dtpf.scripts.compare_report`) holds a table per cell, its statistics
:mod:`~dtpf.scripts.compare_stats`.
"""
from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import time
from pathlib import Path

from dtpf.messages.config import RunInputError, add_run_arguments, config_from_args, read_config_file
from dtpf.scripts.compare_csv import CompareCsv, RunRow
from dtpf.scripts.compare_metrics import METRICS
from dtpf.scripts.compare_plan import Plan, make_plan, parse_grid, parse_seeds, tasks_of, warm_configs
from dtpf.scripts.compare_report import comparisons, report
from dtpf.scripts.compare_runs import RunFailed, run_all
from dtpf.scripts.compare_variants import parse_variant
from dtpf.scripts.console import TaskProgress

__all__ = ["register", "cmd_compare", "plans"]

EXAMPLE = """\
example:
  dtpf compare --variant plain:preprocess=false --variant dt:policy=fixed,ps=0.81 \\
      --variant rel:move_rule=relative,weight_rule=likelihood,ps=0 \\
      --baseline plain --seeds 200 -n 100 -T 100 --csv runs/compare.csv --plot runs/compare.png

A variant is LABEL:FIELD=VALUE[,FIELD=VALUE...] over the run's settings (the RunConfig fields:
scenario, model, observations, particles, steps, resampler, resample_below, preprocess, threshold,
weight_rule, move_rule, jitter, policy, choose_base, ps, ps_rate, ...), applied over the run options
given. The label ends at the first ':', so a value may hold ':' (model=path/to/file.py:Target) and ','
(ros2_fields=point.x,point.y); 'LABEL' alone is the run options unchanged; 'none' is None.

Each seed S is one data set that every variant filters (the simulation of seed S, or the same
observation file with the filter's seed S). The metric of a run (--metric) is, with the truth known,
over the state components of --components (default: all the truth covers), e_k the estimate minus
the truth at step k:
  mse               mean over steps and components of e^2 (the default with the truth)
  rmse              its square root
  squared-distance  mean over steps of |e_k|^2, e.g. a tracker's position: --components 0,1
  distance          mean over steps of |e_k|
  log-predictive    mean log p(z_k | z_1:k-1) per step, higher is better (the default without truth)

--grid FIELD=VALUE,... compares in every cell of a grid (repeat for more fields: every
combination, the first outermost), e.g. --grid particles=100,1000 --grid scenario=ungm,drift: one
table per cell, the same variants, seeds and baseline in each. The table gives,
per variant: the mean over seeds with its 95% interval (z = 1.96, sample sd / sqrt(S)); the
difference to the baseline paired by seed with its 95% interval; that difference in % of the
baseline's mean (delta-method interval); the verdict, 'better' or 'worse' when the difference's
interval excludes 0, else 'not significantly different'; and the wall time per filter step.

With --csv each finished run is appended as a row at once; the same command again runs only the
(cell, variant, seed) runs the file does not hold (Ctrl-C, then re-run, goes on where it stopped). A
file that is not a compare CSV, or that holds a label run with other settings or judged by another
metric, is refused."""


def plans(args: argparse.Namespace) -> list[Plan]:
    """The plan of each cell of parsed arguments (one without --grid); RunInputError (one line, naming the
    variant) for anything wrong, before any run starts: every variant's run of seed 0 in every cell is built
    and its model loaded and checked."""
    if args.seed is not None:
        raise RunInputError("--seed: each run's seed comes from --seeds or --seed-list")
    variants = [parse_variant(text) for text in args.variant]
    seeds = parse_seeds(args.seeds, args.seed_list)
    cells = parse_grid(args.grid)
    base = config_from_args(args)
    steps_given = args.steps is not None or bool(args.config and "steps" in read_config_file(args.config))
    return [make_plan(base, variants, seeds, args.baseline, args.metric, args.components, steps_given, cell)
            for cell in cells]


def cmd_compare(args: argparse.Namespace) -> int:
    the_plans = plans(args)
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    if workers < 1:
        raise RunInputError(f"--workers: at least 1, got {workers}")
    store = CompareCsv(args.csv) if args.csv is not None else None
    rows: dict[tuple[str, str, int], RunRow] = {}
    wanted = {(plan.cell, label, seed) for plan in the_plans for label in plan.labels for seed in plan.seeds}
    if store is not None:
        held, note = store.read()
        if note:
            print(f"dtpf compare: note: {note}", file=sys.stderr)
        store.check(held, {key: text for plan in the_plans for key, text in plan.settings().items()},
                    the_plans[0].metric.key)
        rows = {key: row for key, row in held.items() if key in wanted}
        store.start()
    tasks = tasks_of(the_plans, set(rows))
    if store is not None and rows:
        cells = f" x {len(the_plans)} cells" if len(the_plans) > 1 else ""
        print(f"dtpf compare: {args.csv} holds {len(rows)} of the {len(wanted)} runs ({len(the_plans[0].labels)} "
              f"variants x {len(the_plans[0].seeds)} seeds{cells}); skipping them, "
              f"{'nothing to run' if not tasks else f'running the other {len(tasks)}'}", file=sys.stderr, flush=True)
    progress = TaskProgress("dtpf compare", len(tasks))
    finished = []

    def keep(row: RunRow) -> None:
        if store is not None:
            store.append(row)
        rows[row.key] = row
        finished.append(row)
        progress(len(finished))

    # Ctrl-C and SIGTERM stop the compare, also when it was started in the background of a script (a
    # non-interactive shell starts such a job with SIGINT ignored, and Python then installs no handler).
    before = signal.signal(signal.SIGTERM, _interrupt), signal.signal(signal.SIGINT, signal.default_int_handler)
    start = time.perf_counter()
    try:
        run_all(tasks, workers, warm_configs(the_plans), keep)
    except KeyboardInterrupt:
        where = f"{args.csv} holds every finished run; the same command goes on" if store is not None else \
            "no --csv, so they are not kept"
        print(f"{chr(10) if progress.enabled and progress.tty else ''}dtpf compare: interrupted after {len(finished)} of {len(tasks)} runs; {where}", file=sys.stderr)
        return 130
    except RunFailed as error:
        print(f"dtpf compare: error: {error}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGTERM, before[0])
        signal.signal(signal.SIGINT, before[1])
    if tasks:
        print(f"dtpf compare: {len(tasks)} runs in {time.perf_counter() - start:.1f} s on "
              f"{min(workers, len(tasks))} worker{'s' if min(workers, len(tasks)) != 1 else ''}", file=sys.stderr)
    text = report(the_plans, rows)
    print(text)
    if args.markdown is not None:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(text + "\n")
    if args.plot is not None:
        _plot(args.plot, the_plans, rows)
    return 0


def _plot(path: Path, the_plans: list[Plan], rows) -> None:
    """--plot: the figure of the differences, one file per cell of a grid (the cell's name added to the file's)."""
    from dtpf.scripts.compare_plot import plot_differences

    for plan in the_plans:
        where = path
        if len(the_plans) > 1:
            where = path.with_name(f"{path.stem}-{re.sub(r'[^A-Za-z0-9.]+', '-', plan.cell).strip('-')}{path.suffix}")
        plot_differences(where, [(label, row) for label, row, _ in comparisons(plan, rows)], plan.baseline,
                         METRICS[plan.metric.name][0], plan.metric.higher_is_better, len(plan.seeds))
        print(f"dtpf compare: wrote {where}", file=sys.stderr)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def register(subparsers) -> None:
    """``dtpf compare``."""
    parser = subparsers.add_parser(
        "compare", help="run variants of a run over many seeds and say which differ from a baseline (95%% intervals)",
        description="Run each variant (LABEL:FIELD=VALUE,... over the run options) on every seed, in worker "
                    "processes, and print a Markdown table: each variant's mean metric, its difference to the "
                    "baseline paired by seed, the change in %, with 95% intervals, and a verdict.",
        epilog=EXAMPLE, formatter_class=argparse.RawDescriptionHelpFormatter)
    group = parser.add_argument_group("compare")
    group.add_argument("--variant", "-V", action="append", required=True, metavar="LABEL:FIELD=VALUE,...",
                       help="a variant: its label and the run settings it changes, e.g. dt:policy=fixed,ps=0.81 "
                            "(repeat for each variant)")
    group.add_argument("--baseline", default=None, metavar="LABEL",
                       help="the variant the others are compared with (default: the first)")
    group.add_argument("--seeds", type=int, default=30, metavar="S",
                       help="run seeds 0 .. S-1 (default: %(default)s)")
    group.add_argument("--seed-list", default=None, metavar="SEEDS",
                       help="these seeds instead, e.g. 1000-1199 or 3,5,8 (comma-separated seeds and ranges)")
    group.add_argument("--metric", default=None, choices=list(METRICS), metavar="NAME",
                       help="what a run is judged by: " + ", ".join(METRICS) + " (default: mse when the truth is "
                            "known, else log-predictive; see below)")
    group.add_argument("--components", default=None, metavar="LIST",
                       help="the state components a truth metric is over, e.g. 0,1 for a tracker's position "
                            "(default: every component the truth covers)")
    group.add_argument("--grid", action="append", default=None, metavar="FIELD=VALUE,...",
                       help="compare in each cell of a grid: e.g. --grid particles=100,1000 (repeat for more "
                            "fields: every combination); one table per cell")
    group.add_argument("--workers", "-j", type=int, default=None, metavar="K",
                       help="worker processes (default: one per CPU; 1 runs in this process)")
    group.add_argument("--csv", type=Path, default=None, metavar="FILE",
                       help="append one row per (variant, seed) as it finishes; the pairs it already holds are "
                            "not run again (resume)")
    group.add_argument("--plot", type=Path, default=None, metavar="PNG",
                       help="draw each variant's difference to the baseline with its interval")
    group.add_argument("--markdown", type=Path, default=None, metavar="FILE",
                       help="also write the table to this file")
    add_run_arguments(parser)
    parser.set_defaults(handler=cmd_compare)
