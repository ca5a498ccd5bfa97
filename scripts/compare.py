"""``dtpf compare``: run variants of a run over many seeds and say which differ, with 95% intervals.

Each seed is one data set (a simulation of the model, or the same observation file) that every variant
filters, so a variant's difference to the baseline is paired by seed::

    dtpf compare --variant plain:preprocess=false --variant dt:policy=fixed,ps=0.81 \\
        --baseline plain --seeds 200 -n 100 --csv runs/compare.csv

The variants (:mod:`~dtpf.scripts.compare_variants`) are read and each one's run of seed 0 is built and
its model checked before any run starts; the runs (:mod:`~dtpf.scripts.compare_runs`) go to worker
processes; each finished run is a CSV row at once (:mod:`~dtpf.scripts.compare_csv`), which a second
call with the same CSV does not run again; the table's statistics are :mod:`~dtpf.scripts.compare_stats`.
"""
from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

from dtpf.messages.config import RunConfig, RunInputError, add_run_arguments, config_from_args, read_config_file
from dtpf.messages.errors import DtpfError
from dtpf.scripts.compare_csv import CompareCsv, RunRow
from dtpf.scripts.compare_runs import LOG_PREDICTIVE, MSE, RunFailed, Task, run_all
from dtpf.scripts.compare_stats import Comparison, compare, format_change, format_interval
from dtpf.scripts.compare_variants import Variant, parse_variant, settings_of
from dtpf.scripts.console import TaskProgress

__all__ = ["register", "cmd_compare", "Plan", "plan", "table", "comparisons", "parse_seeds"]

#: What each metric is called in the table, and which way is better.
METRIC_TITLES = {MSE: "MSE (lower is better)", LOG_PREDICTIVE: "log predictive (higher is better)"}
#: What each metric is, in the line above the table.
METRIC_MEANINGS = {MSE: "the mean squared error of the posterior mean against the truth, lower is better",
                   LOG_PREDICTIVE: "the mean log predictive likelihood per step, log p(z_k | z_1:k-1) (no truth "
                                   "known), higher is better"}
HIGHER_IS_BETTER = {MSE: False, LOG_PREDICTIVE: True}

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
observation file with the filter's seed S). The metric of a run is its mean squared error against
the truth when the truth is known, else its mean log predictive likelihood per step. The table gives,
per variant: the mean over seeds with its 95% interval (z = 1.96, sample sd / sqrt(S)); the
difference to the baseline paired by seed with its 95% interval; that difference in % of the
baseline's mean (delta-method interval); the verdict, 'better' or 'worse' when the difference's
interval excludes 0, else 'not significantly different'; and the wall time per filter step.

With --csv each finished run is appended as a row at once; the same command again runs only the
(variant, seed) pairs the file does not hold (Ctrl-C, then re-run, goes on where it stopped). A file
that is not a compare CSV, or that holds a label run with other settings, is refused."""


class Plan:
    """What a compare will do: the variants, each one's run of seed 0, the seeds, the baseline, the metric."""

    def __init__(self, variants: list[Variant], configs: dict[str, RunConfig], seeds: list[int], baseline: str,
                 metric: str):
        self.variants, self.configs, self.seeds, self.baseline, self.metric = variants, configs, seeds, baseline, metric

    @property
    def labels(self) -> list[str]:
        return [variant.label for variant in self.variants]

    def settings(self) -> dict[str, str]:
        """Each label's settings (its run but the seed), as the CSV keeps them."""
        return {label: settings_of(config) for label, config in self.configs.items()}

    def tasks(self, done: set[tuple[str, int]]) -> list[Task]:
        """The runs not in ``done`` (label, seed), seed by seed (every variant of a seed before the next)."""
        settings = self.settings()
        return [Task(variant.label, variant.spec, settings[variant.label],
                     self.configs[variant.label].model_copy(update={"seed": seed}))
                for seed in self.seeds for variant in self.variants if (variant.label, seed) not in done]


def parse_seeds(count: int | None, listed: str | None) -> list[int]:
    """The seeds: ``listed`` ('0,5,9' or ranges '100-199', comma-separated) or 0 .. count-1."""
    if listed is None:
        if count is None or count < 1:
            raise RunInputError(f"--seeds: at least 1, got {count}")
        return list(range(count))
    seeds: list[int] = []
    for part in listed.split(","):
        first, dash, last = part.strip().partition("-")
        try:
            seeds += list(range(int(first), int(last) + 1)) if dash else [int(first)]
        except ValueError:
            raise RunInputError(f"--seed-list: {part.strip()!r} is not a seed or a range FIRST-LAST") from None
    if not seeds or min(seeds) < 0:
        raise RunInputError(f"--seed-list: seeds are integers >= 0, got {listed!r}")
    return list(dict.fromkeys(seeds))


def plan(args: argparse.Namespace) -> Plan:
    """The plan of parsed arguments; RunInputError (one line, naming the variant) for anything wrong, before
    any run starts: every variant's run of seed 0 is built and its model loaded and checked."""
    if args.seed is not None:
        raise RunInputError("--seed: each run's seed comes from --seeds or --seed-list")
    variants = [parse_variant(text) for text in args.variant]
    labels = [variant.label for variant in variants]
    repeated = sorted({label for label in labels if labels.count(label) > 1})
    if repeated:
        raise RunInputError(f"--variant: label {repeated[0]!r} is given twice")
    baseline = labels[0] if args.baseline is None else args.baseline
    if baseline not in labels:
        raise RunInputError(f"--baseline {baseline!r} is none of the variants ({', '.join(labels)})")
    seeds = parse_seeds(args.seeds, args.seed_list)
    base = config_from_args(args)
    steps_given = args.steps is not None or bool(args.config and "steps" in read_config_file(args.config))
    configs, metrics = {}, {}
    for variant in variants:
        config = variant.config(base, seed=0)
        try:
            config, metrics[variant.label] = _checked(config, steps_given or "steps" in variant.fields)
        except (DtpfError, ValueError) as error:
            raise RunInputError(f"variant {variant.label!r}: {error}") from None
        configs[variant.label] = config
    if len(set(metrics.values())) > 1:
        kinds = "; ".join(f"{label}: {'MSE' if metric == MSE else 'log predictive, no truth'}"
                          for label, metric in metrics.items())
        raise RunInputError(f"the variants are judged by different metrics ({kinds}): give them all truth or none")
    return Plan(variants, configs, seeds, baseline, metrics[baseline])


def _checked(config: RunConfig, steps_given: bool) -> tuple[RunConfig, str]:
    """The run of seed 0 with its model loaded and checked and its filter built on the first observation (so
    a user's resampler, move or policy is loaded), simulated steps held to the model's most; and its metric
    (MSE where the truth is known)."""
    from dtpf.entity import sources
    from dtpf.scripts.inprocess import build

    if config.live:
        raise RunInputError("live observations need dtpf launch; compare filters a file or a simulation")
    model = sources.load_model(config)
    first = sources.observations_of(config.model_copy(update={"steps": 1}), model)
    build(config, first.observations, model)
    if config.simulated:
        most = getattr(model, "max_steps", None)
        if most is not None and config.steps > most:
            if steps_given:
                raise RunInputError(f"steps: the {config.model_ref} scenario can simulate at most {most} steps, "
                                    f"got {config.steps}")
            config = config.model_copy(update={"steps": most})
        return config, MSE
    return config, MSE if first.known_truth is not None else LOG_PREDICTIVE


def comparisons(plan: Plan, rows: dict[tuple[str, int], RunRow]) -> list[tuple[str, Comparison, float]]:
    """(label, comparison against the baseline, mean ms per step) of each variant, over the seeds every
    variant has a row for (all of them unless the compare was cut short)."""
    seeds = [seed for seed in plan.seeds if all((label, seed) in rows for label in plan.labels)]
    base = [rows[(plan.baseline, seed)].value for seed in seeds]
    out = []
    for label in plan.labels:
        values = [rows[(label, seed)].value for seed in seeds]
        ms = float(np.mean([rows[(label, seed)].ms_per_step for seed in seeds])) if seeds else math.nan
        out.append((label, compare(values, base, HIGHER_IS_BETTER[plan.metric], is_baseline=label == plan.baseline),
                    ms))
    return out


def table(plan: Plan, rows: dict[tuple[str, int], RunRow]) -> str:
    """The Markdown report: a line on what was compared, the table, and each variant's settings."""
    found = comparisons(plan, rows)
    runs = found[0][1].runs if found else 0
    base_config = plan.configs[plan.baseline]
    lines = [f"{len(plan.variants)} variants x {runs} seeds ({_seeds_text(plan.seeds)}); "
             f"metric: {METRIC_MEANINGS[plan.metric]}; mean ± 95% interval over seeds (z = 1.96); difference = "
             f"variant - {plan.baseline}, paired by seed, ± its 95% interval; change = the difference in % of "
             f"{plan.baseline}'s mean (delta method); ms / step: wall time of one filter step with its layers, "
             f"in the worker process that ran it.", "",
             f"| variant | runs | {METRIC_TITLES[plan.metric]} | difference vs {_cell(plan.baseline)} "
             f"| change | verdict | ms / step |",
             "|---|---|---|---|---|---|---|"]
    for label, row, ms in found:
        is_base = label == plan.baseline
        lines.append(f"| {_cell(label)} | {row.runs} | {format_interval(row.mean, row.mean_half)} "
                     f"| {'-' if is_base else format_interval(row.difference, row.difference_half)} "
                     f"| {'-' if is_base else format_change(row.change, row.change_half)} | {row.verdict} "
                     f"| {ms:.2f} |")
    lines += ["", f"Variants over the run options ({base_config.model_ref}, N = {base_config.particles}, "
                  f"T = {base_config.steps if base_config.steps is not None else 'every row'}):", ""]
    lines += [f"- {_cell(variant.label)}: `{variant.spec or '(the run options unchanged)'}`" for variant in plan.variants]
    return "\n".join(lines)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _seeds_text(seeds: list[int]) -> str:
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"seed {seeds[0]}" if len(seeds) == 1 else f"seeds {seeds[0]}-{seeds[-1]}"
    shown = ", ".join(str(seed) for seed in seeds[:8])
    return f"seeds {shown}{', ...' if len(seeds) > 8 else ''}"


def cmd_compare(args: argparse.Namespace) -> int:
    the_plan = plan(args)
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    if workers < 1:
        raise RunInputError(f"--workers: at least 1, got {workers}")
    store = CompareCsv(args.csv) if args.csv is not None else None
    rows: dict[tuple[str, int], RunRow] = {}
    if store is not None:
        held, note = store.read()
        if note:
            print(f"dtpf compare: note: {note}", file=sys.stderr)
        store.check(held, the_plan.settings())
        rows = {key: row for key, row in held.items() if key[0] in the_plan.labels and key[1] in the_plan.seeds}
        store.start()
    tasks = the_plan.tasks(set(rows))
    total = len(the_plan.labels) * len(the_plan.seeds)
    if store is not None and rows:
        print(f"dtpf compare: {args.csv} holds {len(rows)} of the {total} runs ({len(the_plan.labels)} variants x "
              f"{len(the_plan.seeds)} seeds); skipping them, "
              f"{'nothing to run' if not tasks else f'running the other {len(tasks)}'}", file=sys.stderr, flush=True)
    progress = TaskProgress("dtpf compare", len(tasks))
    finished = []

    def keep(row: RunRow) -> None:
        if store is not None:
            store.append(row)
        rows[(row.variant, row.seed)] = row
        finished.append(row)
        progress(len(finished))

    # Ctrl-C and SIGTERM stop the compare, also when it was started in the background of a script (a
    # non-interactive shell starts such a job with SIGINT ignored, and Python then installs no handler).
    before = signal.signal(signal.SIGTERM, _interrupt), signal.signal(signal.SIGINT, signal.default_int_handler)
    start = time.perf_counter()
    try:
        run_all(tasks, workers, [the_plan.configs[label] for label in the_plan.labels], keep)
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
    report = table(the_plan, rows)
    print(report)
    if args.markdown is not None:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(report + "\n")
    if args.plot is not None:
        from dtpf.scripts.compare_plot import plot_differences

        plot_differences(args.plot, [(label, row) for label, row, _ in comparisons(the_plan, rows)],
                         the_plan.baseline, METRIC_TITLES[the_plan.metric].split(" (")[0],
                         HIGHER_IS_BETTER[the_plan.metric], len(the_plan.seeds))
        print(f"dtpf compare: wrote {args.plot}", file=sys.stderr)
    return 0


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def register(subparsers) -> None:
    """``dtpf compare``."""
    parser = subparsers.add_parser(
        "compare", help="run variants of a run over many seeds and say which differ from a baseline (95% intervals)",
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
