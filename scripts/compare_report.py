"""The report of ``dtpf compare``: per cell, each variant against the baseline over the seeds every variant has
a row for, as a Markdown table (one per cell of a grid), with the line that says what was compared::

    found = comparisons(plan, rows)      # [(label, Comparison, ms per step), ...]
    text = report(plans, rows)
"""
from __future__ import annotations

import math

import numpy as np

from dtpf.scripts.compare_csv import RunRow
from dtpf.scripts.compare_plan import Plan
from dtpf.scripts.compare_stats import Comparison, compare, format_change, format_interval

__all__ = ["comparisons", "table", "report"]

Rows = dict[tuple[str, str, int], RunRow]


def comparisons(plan: Plan, rows: Rows) -> list[tuple[str, Comparison, float]]:
    """(label, comparison against the baseline, mean ms per step) of each variant of the plan's cell, over the
    seeds every variant has a row for (all of them unless the compare was cut short)."""
    seeds = [seed for seed in plan.seeds if all((plan.cell, label, seed) in rows for label in plan.labels)]
    base = [rows[(plan.cell, plan.baseline, seed)].value for seed in seeds]
    out = []
    for label in plan.labels:
        values = [rows[(plan.cell, label, seed)].value for seed in seeds]
        ms = float(np.mean([rows[(plan.cell, label, seed)].ms_per_step for seed in seeds])) if seeds else math.nan
        out.append((label, compare(values, base, plan.metric.higher_is_better, is_baseline=label == plan.baseline),
                    ms))
    return out


def table(plan: Plan, rows: Rows) -> list[str]:
    """The Markdown table of one cell: its lines."""
    lines = [f"| variant | runs | {plan.metric.title} | difference vs {_cell(plan.baseline)} "
             f"| change | verdict | ms / step |",
             "|---|---|---|---|---|---|---|"]
    for label, row, ms in comparisons(plan, rows):
        is_base = label == plan.baseline
        lines.append(f"| {_cell(label)} | {row.runs} | {format_interval(row.mean, row.mean_half)} "
                     f"| {'-' if is_base else format_interval(row.difference, row.difference_half)} "
                     f"| {'-' if is_base else format_change(row.change, row.change_half)} | {row.verdict} "
                     f"| {ms:.2f} |")
    return lines


def report(plans: list[Plan], rows: Rows) -> str:
    """The Markdown report: a line on what was compared, the table of each cell (under its name when there is a
    grid), and each variant's settings."""
    first = plans[0]
    runs = min((found[0][1].runs for found in (comparisons(plan, rows) for plan in plans) if found), default=0)
    grid = len(plans) > 1 or bool(first.cell)
    cells = f" x {len(plans)} cells" if grid else ""
    lines = [f"{len(first.variants)} variants x {runs} seeds{cells} ({_seeds_text(first.seeds)}); "
             f"metric: {first.metric.meaning}; mean ± 95% interval over seeds (z = 1.96); difference = "
             f"variant - {first.baseline}, paired by seed, ± its 95% interval; change = the difference in % of "
             f"{first.baseline}'s mean (delta method); ms / step: wall time of one filter step with its layers, "
             f"in the worker process that ran it.", ""]
    for plan in plans:
        if grid:
            lines += [f"**{plan.cell}**", ""]
        lines += table(plan, rows)
        if grid:
            lines.append("")
    if grid:
        lines += ["Variants over the run options of each cell:", ""]
    else:
        config = first.configs[first.baseline]
        lines += ["", f"Variants over the run options ({config.model_ref}, N = {config.particles}, "
                      f"T = {config.steps if config.steps is not None else 'every row'}):", ""]
    lines += [f"- {_cell(variant.label)}: `{variant.spec or '(the run options unchanged)'}`"
              for variant in first.variants]
    return "\n".join(lines)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _seeds_text(seeds: list[int]) -> str:
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"seed {seeds[0]}" if len(seeds) == 1 else f"seeds {seeds[0]}-{seeds[-1]}"
    shown = ", ".join(str(seed) for seed in seeds[:8])
    return f"seeds {shown}{', ...' if len(seeds) > 8 else ''}"
