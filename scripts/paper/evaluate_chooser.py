"""Does the twin pick the right cure? The choosing policy against every fixed choice.

For each scenario, N and seed (each seed its own simulated data set, shared by every variant, so all
comparisons are paired by seed) the in-process pipeline runs:

- the four traditional resamplers, no preprocessing;
- each fixed cure, at every step: DT preprocessing with the paper's rule (Eq. 29-30, PS 0.81, inherit
  weights), DT preprocessing with the relative rule (PS 0, likelihood weights), roughening (K = 0.2)
  and the regularised kernel (h_opt), each after systematic resampling;
- ``guard-observed`` with the relative rule (PS 0, likelihood weights);
- ``choose``: every step the system layer runs the five arms on its copy of the entity's set and
  puts in force the one the real observations favour (``--policy choose``, docs/guides/policies.md;
  its copies are scored and propagated in one call over all arms, with the numbers of one call per
  copy, so the figures of a CSV written before that change stand, and ``--resume`` may go on from it);
- the Kalman filter where it is exact (``drift``, ``drift+100``, ``switching``).

Beside them, a reference that is not a method: per seed, the arm (plain, either DT rule, roughening,
regularised) whose fixed filter gave the seed's observations the highest likelihood (the sum over the run of
log p(z_k | z_1:k-1), which every run records), and that arm's error. It chooses with hindsight, once per run,
from the observations' likelihood alone: what that score would pick, for better (where the runs differ by
luck) or worse (where a wide cloud explains the observations while its mean is far off).

Scenarios: ``ungm``, ``drift``, ``drift+100``, ``range-bearing`` and ``video`` as in
:mod:`dtpf.scripts.paper.evaluate_guard`, and ``switching`` (:class:`dtpf.entity.models.SensorSwitchModel`:
a drifting constant whose sensor's sd drops from 1 to 0.01 at step 51, so the best cure changes).
Targets, per cell: ``choose`` never significantly worse than systematic (95% interval of the paired
difference); where some fixed method is significantly better than systematic, ``choose`` closes at
least 80% of the gap to the best of them; on ``switching``, significantly better than every fixed
method::

    python -m dtpf.scripts.paper.evaluate_chooser --csv runs/chooser.csv     # 1000 seeds per cell
    python -m dtpf.scripts.paper.evaluate_chooser --csv runs/chooser.csv --resume  # go on after a cut
    python -m dtpf.scripts.paper.evaluate_chooser --quick                     # 6 seeds, T = 25
    python -m dtpf.scripts.paper.evaluate_chooser --csv runs/chooser.csv --resume --cells drift+100:100 \
        --from-step 2 4 11 --from-arms dt-relative    # an arm from step J on, without evidence (not causal)

Progress goes to stderr, the tables to stdout; ``--csv`` keeps every run's figures, and
``--from-csv`` rebuilds the tables from such a file.

The variants are ``dtpf compare`` variants (:data:`VARIANT_SPECS`) and the intervals and paired differences
:mod:`dtpf.scripts.compare_stats`' (at the exact normal quantile): a cell's error and "difference vs
systematic" columns are what the ``dtpf compare`` command printed at the end gives (``--baseline choose`` for
"variant - choose"). The loop stays this script's own: the share of steps a chooser left its base arm
needs the twin's decisions, which a compare row does not keep; ``--tune`` and ``--from-step`` replace a
built filter's system layer, which no run setting does; the hindsight row and the Kalman filter are not
runs of a variant.
"""
from __future__ import annotations

import argparse
import csv
import io
import math
import sys
import time
from dataclasses import dataclass, replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from dtpf.entity import models
from dtpf.messages.config import RunConfig
from dtpf.scripts.compare_stats import BETTER, WORSE, mean_interval, paired_difference
from dtpf.scripts.compare_stats import verdict as judged
from dtpf.scripts.compare_variants import Variant, parse_variant
from dtpf.scripts.console import TaskProgress
from dtpf.scripts.inprocess import build, simulate
from dtpf.scripts.paper import evaluate_guard
from dtpf.scripts.paper.common import Z95
from dtpf.system.layer import SystemLayer
from dtpf.system.policy import ChoosePS

TRADITIONAL = evaluate_guard.TRADITIONAL
#: The fixed cures, by label (``dtpf compare`` variants, evaluate_guard's).
CURES: dict[str, Variant] = {label: evaluate_guard.VARIANTS[label] for label in
                             ("DT paper rule, PS 0.81", "DT relative rule, PS 0", "roughening", "regularised")}
#: The chooser as --policy choose runs it (its base arm roughening), and the one on plain resampling.
CHOOSE, CHOOSE_PLAIN, CHOOSE_REHEARSED = "choose", "choose, plain base", "choose, rehearsed base"
#: The choosers, and the base arm of each ("rehearse": the arm its rehearsal of the model chose, per cell).
CHOOSERS = {CHOOSE: "roughening", CHOOSE_PLAIN: "plain", CHOOSE_REHEARSED: "rehearse"}
#: The variants, as ``dtpf compare --variant`` reads them (LABEL:FIELD=VALUE,...).
VARIANT_SPECS = (
    *(spec for spec in evaluate_guard.VARIANT_SPECS if spec.split(":")[0] in (*TRADITIONAL, *CURES)),
    next(spec for spec in evaluate_guard.VARIANT_SPECS if spec.startswith("guard-observed, relative rule:")),
    f"{CHOOSE}:policy=choose",
    f"{CHOOSE_PLAIN}:policy=choose,choose_base=plain",
    f"{CHOOSE_REHEARSED}:policy=choose,choose_base=rehearse",
)
#: Variants by label (the traditional resamplers, the cures, guard-observed, the choosers; and those the options
#: add).
VARIANTS: dict[str, Variant] = {variant.label: variant for variant in map(parse_variant, VARIANT_SPECS)}
#: The variants of a dtpf compare cell.
COMPARE_LABELS = tuple(VARIANTS)
KALMAN = "Kalman (exact)"
#: Not a method: per seed, the arm whose fixed filter gave the run's observations the highest likelihood.
HINDSIGHT = "hindsight: the arm that predicted the run best"
#: The fixed filters of the chooser's arms (plain, the two DT rules, roughening, regularised), by label.
ARM_VARIANTS = {"systematic": "plain", "DT relative rule, PS 0": "dt-relative", "DT paper rule, PS 0.81": "dt-paper",
                "roughening": "roughening", "regularised": "regularised"}


def add_base(arm: str) -> str:
    """Add the chooser on base ``arm`` (``--choose-base ARM``) to the variants (``--bases``): its label."""
    from dtpf.messages.names import ARMS

    if arm not in ARMS:
        raise ValueError(f"unknown arm {arm!r}; expected one of {', '.join(ARMS)}")
    label = CHOOSE if arm == CHOOSERS[CHOOSE] else CHOOSE_PLAIN if arm == "plain" else f"choose, {arm} base"
    VARIANTS[label] = parse_variant(f"{label}:policy=choose,choose_base={arm}")
    CHOOSERS[label] = arm
    return label


#: Not methods: "ARM from step J" puts ARM in force from step J on and the chooser's base before it, without
#: looking at any evidence (``--from-step``): label -> (ARM, J).
FROM_STEP: dict[str, tuple[str, int]] = {}


class ArmFromStep(ChoosePS):
    """The base arm up to step j - 1 and ``arm`` from step j on, decided without evidence (no copies run).

    A chooser's decision at step k applies from k + 1 and rests on observations scored by then, so no chooser
    that waits for evidence puts an arm in force before step 3; this is what such a chooser would get from
    that arm had it known the arm in advance and entered it at step j for good.
    """

    simulates = False
    uses_evidence = False

    def __init__(self, arm: str, start: int, base: str = CHOOSERS[CHOOSE]):
        super().__init__(arms=(arm,), base=base)
        self.target, self.start = arm, int(start)

    def decide(self, step: int, forecast) -> object:
        arm = self.target if step + 1 >= self.start else self.base
        return self._decision(step, arm, f"{self.target} from step {self.start}", {})


def add_from_step(arm: str, start: int) -> str:
    """Add "ARM from step J" (``--from-step``) to the variants: its label."""
    from dtpf.messages.names import ARMS

    if arm not in ARMS or int(start) < 2:
        raise ValueError(f"an arm of {', '.join(ARMS)} from a step >= 2 (step 1 runs the base arm), got "
                         f"{arm!r} from {start!r}")
    label = f"{arm} from step {int(start)}"
    VARIANTS[label] = parse_variant(f"{label}:policy=choose")
    FROM_STEP[label] = (arm, int(start))
    return label


#: The chooser with other settings of ChoosePS (``--tune``): label -> its keyword arguments.
TUNED: dict[str, dict] = {}
#: The settings --tune may change, and their types.
TUNABLE = {"enter": float, "leave": float, "window": int, "steady": float, "particles": int}


def add_tuned(setting: str) -> str:
    """Add the chooser (on its default base) with one setting of ChoosePS changed, ``KEY=VALUE``: its label."""
    key, _, value = setting.partition("=")
    if key not in TUNABLE:
        raise ValueError(f"KEY=VALUE with KEY one of {', '.join(TUNABLE)}, got {setting!r}")
    try:
        parsed = TUNABLE[key](value)
    except ValueError:
        raise ValueError(f"{key} takes a number, got {value!r}") from None
    ChoosePS(**{key: parsed})  # a value the policy refuses is refused here, before any run
    label = f"choose, {key} {value}"
    VARIANTS[label] = parse_variant(f"{label}:policy=choose")
    TUNED[label] = {key: parsed}
    CHOOSERS[label] = CHOOSERS[CHOOSE]
    return label


#: The fixed methods the chooser is compared with (the traditional resamplers and the cures).
FIXED = (*TRADITIONAL, *CURES)
#: (scenario, N) cells of the evaluation.
CELLS = (("ungm", 100), ("drift", 100), ("drift+100", 100), ("range-bearing", 100), ("video", 100),
         ("switching", 100), ("moving", 100), ("range-bearing", 1000))
#: The scenarios where the best cure changes during the run: the chooser must beat every fixed method there.
CHANGING = ("switching", "moving")
SCENARIOS = tuple(dict.fromkeys(sc for sc, _ in CELLS))
PILOT_SEED = 10_000


@dataclass(frozen=True)
class Task:
    scenario: str
    particles: int
    seed: int
    steps: int
    #: The variants to run (empty: every one of VARIANTS, and the Kalman filter where it is exact).
    labels: tuple[str, ...] = ()


def scenario_model(name: str):
    """(RunConfig options, model object) of a scenario of this evaluation."""
    if name in CHANGING:
        return dict(scenario=name), models.get(name)
    return evaluate_guard.scenario_model(name)


def task_config(task: Task, options: dict, **variant) -> RunConfig:
    return RunConfig(particles=task.particles, seed=task.seed, steps=task.steps, twin="choose-1", **options,
                     **variant)


def build_variant(task: Task, label: str, model, options: dict, observations: np.ndarray):
    """The in-process filter of one variant on the task's observations."""
    config = VARIANTS[label].config(task_config(task, options), seed=task.seed)
    pf = build(config, observations, model)
    if label in TUNED:
        pf.preprocessor.system = SystemLayer.from_config(config, model=model, policy_options=TUNED[label])
    if label in FROM_STEP:  # the same twin, its system layer replaced by one that decides without evidence
        pf.preprocessor.system = SystemLayer(ArmFromStep(*FROM_STEP[label]), seed=task.seed,
                                             twin=pf.preprocessor.system.twin)
    return pf


def run_variant(task: Task, label: str, model, options: dict, truth: np.ndarray, observations: np.ndarray) -> dict:
    """One variant on the task's data set (shared by every variant)."""
    pf = build_variant(task, label, model, options, observations)
    start = time.perf_counter()
    steps = list(pf)
    elapsed = time.perf_counter() - start
    means = np.array([s.mean for s in steps])
    # sum_k log p(z_k | z_1:k-1): the filter's estimate of the log-likelihood of the run's observations.
    evidence = float(np.sum([s.log_predictive for s in steps]))
    figures = dict(error=evaluate_guard._errors(task.scenario, means, truth[: len(steps)]),
                   ms=1e3 * elapsed / len(steps), evidence=evidence if not math.isnan(evidence) else -math.inf)
    twin = pf.preprocessor
    if label in CHOOSERS and twin is not None:
        arms = [d.arm for d in twin.decisions[:-1]]  # the arm in force at steps 2 .. T
        base = getattr(twin.system.policy, "base", CHOOSERS[label])  # a rehearsed base: the rehearsal's arm
        figures["off_plain"] = float(np.mean([a != base for a in arms])) if arms else 0.0
    return figures


_MODELS: dict[str, tuple[dict, object]] = {}


def run_task(task: Task) -> tuple[Task, dict[str, dict]]:
    if task.scenario not in _MODELS:
        _MODELS[task.scenario] = scenario_model(task.scenario)
    options, model = _MODELS[task.scenario]
    truth, observations = simulate(task_config(task, options), model)
    results = {label: run_variant(task, label, model, options, truth, observations)
               for label in (task.labels or VARIANTS)}
    if isinstance(model, models.DriftModel) and not task.labels:  # the exact posterior mean
        results[KALMAN] = dict(error=float(np.mean((model.kalman(observations) - truth) ** 2)))
    return task, results


def _warm_up(scenarios) -> None:
    for scenario in scenarios:
        run_task(Task(scenario, 20, 0, 3))


def _num(value: float) -> str:
    return f"{value:.4g}"


def hindsight(by_seed: dict[int, dict[str, dict]]) -> tuple[dict[int, float], dict[str, float]] | None:
    """Per seed, the error of the arm whose fixed filter gave that seed's observations the highest likelihood
    (its sum of log p(z_k | z_1:k-1)), and the share of seeds each arm was picked on; None without those sums.

    Not a method a run can use (it picks after seeing every observation, from five filters run to the end):
    it is what the likelihood alone would pick, once per run.
    """
    picks: dict[int, str] = {}
    for seed, runs in by_seed.items():
        if not all("evidence" in runs.get(label, {}) for label in ARM_VARIANTS):
            return None
        picks[seed] = max(ARM_VARIANTS, key=lambda label: runs[label]["evidence"])  # ties: the first, systematic
    share = {ARM_VARIANTS[label]: sum(p == label for p in picks.values()) / len(picks) for label in ARM_VARIANTS}
    return {seed: by_seed[seed][label]["error"] for seed, label in picks.items()}, share


def cell_rows(by_seed: dict[int, dict[str, dict]]) -> list[dict]:
    """One row per variant of one (scenario, N) cell: error, difference vs systematic (paired) with CIs."""
    seeds = sorted(by_seed)
    labels = [label for label in [*VARIANTS, KALMAN] if label in by_seed[seeds[0]]]
    error = {label: np.array([by_seed[s][label]["error"] for s in seeds]) for label in labels}
    picked = hindsight(by_seed)
    if picked is not None:
        labels.append(HINDSIGHT)
        error[HINDSIGHT] = np.array([picked[0][s] for s in seeds])
    rows = []
    for label in labels:
        m, h = mean_interval(error[label], Z95)
        d, dh = paired_difference(error[label], error["systematic"], Z95)
        c, ch = paired_difference(error[label], error[CHOOSE], Z95)
        # label - chooser, paired by seed: +1 where the chooser is significantly better.
        significant_vs = {chooser: significance(*paired_difference(error[label], error[chooser], Z95))
                          if label != chooser else 0 for chooser in CHOOSERS if chooser in error}
        ms = [by_seed[s][label].get("ms") if label != HINDSIGHT else None for s in seeds]
        rows.append(dict(variant=label, error=m, error_ci=h, vs_systematic=d, vs_systematic_ci=dh,
                         significant=significance(d, dh) if label != "systematic" else 0,
                         vs_choose=c, vs_choose_ci=ch, significant_vs=significant_vs,
                         ms=float(np.mean(ms)) if ms[0] is not None else math.nan,
                         off_plain=float(np.mean([by_seed[s].get(label, {}).get("off_plain", math.nan)
                                                  for s in seeds])),
                         share=picked[1] if label == HINDSIGHT else None,
                         per_seed=error[label] - error["systematic"]))
    return rows


def share_interval(closed: np.ndarray, gap: np.ndarray, z: float = Z95) -> tuple[float, float]:
    """The 95% (Fieller) interval of the share mean(closed) / mean(gap) of two per-seed differences against
    systematic (a chooser's and the best fixed method's), paired by seed: the shares r whose paired difference
    closed - r gap has an interval that holds 0. (-inf, inf) where mean(gap) is not itself told apart from 0.
    """
    a, b = np.asarray(closed, dtype=np.float64), np.asarray(gap, dtype=np.float64)
    n = a.size
    if n < 2:
        return -math.inf, math.inf
    ma, mb = float(a.mean()), float(b.mean())
    q = z * z / n
    saa, sbb, sab = float(a.var(ddof=1)), float(b.var(ddof=1)), float(np.cov(a, b, ddof=1)[0, 1])
    # (ma - r mb)^2 <= q (saa - 2 r sab + r^2 sbb): c2 r^2 - 2 c1 r + c0 <= 0
    c2, c1, c0 = mb * mb - q * sbb, ma * mb - q * sab, ma * ma - q * saa
    if c2 <= 0:
        return -math.inf, math.inf
    root = math.sqrt(max(c1 * c1 - c2 * c0, 0.0))
    return (c1 - root) / c2, (c1 + root) / c2


def significance(difference: float, half: float) -> int:
    """-1 where the interval lies below 0 (lower error: better), +1 above, 0 where it holds 0 or is unknown."""
    return {BETTER: -1, WORSE: 1}.get(judged(difference, half, higher_is_better=False), 0)


def compare_command(scenario: str, n: int, steps: int, seeds: int, first_seed: int = 0) -> str:
    """The ``dtpf compare`` command that gives the error and "difference vs systematic" columns of a cell for
    the variants of :data:`COMPARE_LABELS` (``--baseline choose`` for "variant - choose")."""
    options = " ".join(f"--{name} {value}" for name, value in
                       evaluate_guard.scenario_options(scenario, printed=True).items())
    metric, components = evaluate_guard.metric_of(scenario)
    judged_by = "" if metric == "mse" else f" --metric {metric} --components {components}"
    seeded = f"--seeds {seeds}" if first_seed == 0 else f"--seed-list {first_seed}-{first_seed + seeds - 1}"
    steps = min(steps, evaluate_guard.FRAMES) if scenario == "video" else steps
    return " \\\n      ".join([f"dtpf compare {options} -n {n} -T {steps} --twin choose-1 {seeded}{judged_by}",
                               *(f"--variant '{label}:{VARIANTS[label].spec}'" for label in COMPARE_LABELS),
                               "--baseline systematic"])


def table(scenario: str, n: int, seeds: int, rows: list[dict]) -> str:
    lines = [f"**{scenario}, N = {n}** ({seeds} seeds)", "",
             "| variant | error | difference vs systematic | variant - choose | ms / step |", "|---|---|---|---|---|"]
    marks = {-1: " (better)", 1: " (worse)", 0: ""}
    for row in rows:
        vs = "-" if row["variant"] == "systematic" else \
            f"{_num(row['vs_systematic'])} ± {_num(row['vs_systematic_ci'])}{marks[row['significant']]}"
        vc = "-" if row["variant"] == CHOOSE else \
            f"{_num(row['vs_choose'])} ± {_num(row['vs_choose_ci'])}"
        ms = "-" if math.isnan(row["ms"]) else f"{row['ms']:.2f}"
        name = row["variant"]
        if name in CHOOSERS and not math.isnan(row["off_plain"]):
            base = CHOOSERS[name] if CHOOSERS[name] != "rehearse" else "its base"
            name += f" (not {base} at {100 * row['off_plain']:.0f}% of steps)"
        if name in FROM_STEP:
            name += f" ({CHOOSERS[CHOOSE]} before; not causal)"
        if row.get("share"):
            name += " (" + ", ".join(f"{arm} {100 * share:.0f}%" for arm, share in row["share"].items() if share) + \
                " of runs; not causal)"
        lines.append(f"| {name} | {_num(row['error'])} ± {_num(row['error_ci'])} | {vs} | {vc} | {ms} |")
    return "\n".join(lines)


def verdict(scenario: str, n: int, rows: list[dict], chooser: str = CHOOSE) -> tuple[str, dict[str, bool]]:
    """The targets of ``chooser`` in one cell, in words, and whether each is met."""
    by = {row["variant"]: row for row in rows}
    me = by[chooser]
    met: dict[str, bool] = {}
    words = [f"{scenario}, N = {n}: {chooser} {_num(me['vs_systematic'])} ± {_num(me['vs_systematic_ci'])} "
             f"against systematic"]
    met["not worse"] = me["significant"] <= 0
    words.append("(significantly worse: target missed)." if not met["not worse"] else
                 "(significantly better)." if me["significant"] < 0 else "(within the noise).")
    better = [by[label] for label in FIXED if label in by and by[label]["significant"] < 0]
    if better:
        best = min(better, key=lambda row: row["vs_systematic"])
        gap = -best["vs_systematic"]
        closed = -me["vs_systematic"] / gap if gap > 0 else math.nan
        met["80% of the gap"] = closed >= 0.8
        words.append(f"Best fixed method significantly better than systematic: {best['variant']} "
                     f"({_num(best['vs_systematic'])}); it closes {100 * closed:.0f}% of that gap "
                     f"({'target met' if met['80% of the gap'] else 'short of 80%'}).")
        if me.get("per_seed") is not None and best.get("per_seed") is not None:
            low, high = share_interval(me["per_seed"], best["per_seed"])
            d, dh = mean_interval(me["per_seed"] - 0.8 * best["per_seed"], Z95)
            words.append(f"The share's 95% interval: {100 * low:.0f}% to {100 * high:.0f}% "
                         f"({chooser} - systematic - 0.8 x ({best['variant']} - systematic): {_num(d)} ± {_num(dh)}, "
                         + ("80% inside the interval: not told apart)." if low <= 0.8 <= high else
                            "80% outside the interval).")
                         )
        if HINDSIGHT in by and gap > 0:
            after = by[HINDSIGHT]["vs_systematic"]
            words.append(f"The arm chosen with hindsight by each run's likelihood closes {100 * -after / gap:.0f}%."
                         if after <= 0 else f"The arm chosen with hindsight by each run's likelihood is worse than "
                         f"systematic ({_num(after)}).")
    else:
        words.append("No fixed method is significantly better than systematic.")
    worse_than = [label for label in ("roughening", "DT paper rule, PS 0.81")
                  if label in by and label != chooser and by[label]["significant_vs"].get(chooser, 0) < 0]
    met["not worse than roughening and the paper's DT"] = not worse_than
    if worse_than:
        words.append(f"Significantly worse than {', '.join(worse_than)}: target missed.")
    if scenario in CHANGING:
        not_beaten = [label for label in FIXED if label in by and by[label]["significant_vs"][chooser] <= 0]
        met["beats every fixed method"] = not not_beaten
        words.append("Significantly better than every fixed method." if not not_beaten else
                     f"Not significantly better than: {', '.join(not_beaten)}.")
    return " ".join(words), met


CSV_FIELDS = ("scenario", "particles", "seed", "variant", "error", "ms", "off_plain", "evidence")
#: The figures of a run kept in the CSV ("evidence": its log-likelihood of the observations; absent in older files).
FIGURES = CSV_FIELDS[4:]


def _whole_rows(path: Path) -> list[list[str]]:
    """The CSV's rows, header first, without a last row a killed run cut short."""
    text = path.read_text()
    if not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    return list(csv.reader(io.StringIO(text, newline="")))


def read_csv(path: Path) -> dict[tuple[str, int], dict[int, dict]]:
    cells: dict[tuple[str, int], dict[int, dict]] = {}
    rows = _whole_rows(path)
    if rows:
        for row in (dict(zip(rows[0], values)) for values in rows[1:]):
            try:  # a row cut short by a killed run is skipped (its seed is run again on --resume)
                figures = {f: float(row[f]) for f in FIGURES if row.get(f) not in (None, "")}
                int(row["particles"]), int(row["seed"])
            except (KeyError, TypeError, ValueError):
                continue
            if "error" not in figures:
                continue
            cells.setdefault((row["scenario"], int(row["particles"])), {}).setdefault(int(row["seed"]), {})[
                row["variant"]] = figures
    return cells


def _drop_variants(path: Path, labels: set[str], cells=None) -> None:
    """Rewrite the CSV at ``path`` without the rows of ``labels`` in ``cells`` ((scenario, N) pairs; None: every
    cell), and without a last row cut short."""
    rows = _whole_rows(path)
    chosen = None if cells is None else {(scenario, str(n)) for scenario, n in cells}
    kept = [row for i, row in enumerate(rows) if i == 0 or len(row) < 4 or row[3] not in labels
            or (chosen is not None and (row[0], row[1]) not in chosen)]
    with open(path, "w", newline="") as handle:
        csv.writer(handle).writerows(kept)


def _upgrade_header(path: Path) -> None:
    """Rewrite a CSV written before a figure was added (an older header) with today's header, its rows
    padded, so that rows appended on --resume sit under the header their fields match."""
    rows = _whole_rows(path)
    if not rows or tuple(rows[0]) == CSV_FIELDS:
        return
    header = rows[0]
    if not set(header) <= set(CSV_FIELDS):
        raise ValueError(f"{path}: not a CSV of this evaluation (its columns: {', '.join(header)})")
    kept = [CSV_FIELDS, *([dict(zip(header, row)).get(f, "") for f in CSV_FIELDS] for row in rows[1:])]
    with open(path, "w", newline="") as handle:
        csv.writer(handle).writerows(kept)


def report(cells: dict[tuple[str, int], dict[int, dict]]) -> tuple[str, bool]:
    """The tables and verdicts of ``cells``, and whether every chooser meets every target."""
    out, verdicts, all_met = [], [], dict.fromkeys(CHOOSERS, True)
    for (scenario, n), by_seed in cells.items():
        complete = {s: r for s, r in by_seed.items() if all(label in r for label in VARIANTS)}
        if len(complete) < 2:
            continue
        rows = cell_rows(complete)
        out.append(table(scenario, n, len(complete), rows) + "\n")
        for chooser in CHOOSERS:
            words, met = verdict(scenario, n, rows, chooser)
            verdicts.append(words)
            all_met[chooser] &= all(met.values())
    out.append("Verdicts:\n")
    out.extend(f"- {line}" for line in verdicts)
    out.append("\n" + "; ".join(f"every target met by {chooser}: {'yes' if ok else 'no'}"
                                for chooser, ok in all_met.items()) + ".")
    return "\n".join(out), all(all_met.values())


def cost(sizes=(1000, 100_000), scenarios=("drift", "ungm"), steps: int = 30) -> list[str]:
    """The system layer's time per step with ``choose`` against the entity filter's own, median over
    steps 6 .. ``steps``, one process: lines of text."""
    from dtpf.entity.filter import ParticleFilter
    from dtpf.information.mirror import summarise
    from dtpf.system.layer import SystemLayer
    from dtpf.system.predict import Snapshot

    lines = []
    for scenario in scenarios:
        model = models.get(scenario)
        for n in sizes:
            config = RunConfig(scenario=scenario, policy="choose", particles=n, steps=steps, seed=1)
            _, z = model.simulate(steps, np.random.default_rng(1))
            pf = ParticleFilter(model, z, n, seed=1)
            layer = SystemLayer.from_config(config, model=model)
            system, entity = [], []
            for k in range(steps):
                t0 = time.perf_counter()
                s = next(pf)
                entity.append(time.perf_counter() - t0)
                summary = summarise(s.particles, s.weights, "neff", n)
                t0 = time.perf_counter()
                layer.observe(s.step, summary, Snapshot.of(s.particles, s.weights, z[k]))
                system.append(time.perf_counter() - t0)
            lines.append(f"{scenario}, N = {n}: system layer {1e3 * np.median(system[5:]):.2f} ms / step "
                         f"(M = {min(n, 1000)} particles per arm), entity filter {1e3 * np.median(entity[5:]):.2f} "
                         f"ms / step")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.paper.evaluate_chooser",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=1000, help="data sets per cell (default: %(default)s)")
    parser.add_argument("--first-seed", type=int, default=0, help="first seed (default: %(default)s; a pilot: "
                                                                   f"{PILOT_SEED})")
    parser.add_argument("--cells", nargs="+", default=None, metavar="SCENARIO:N",
                        help="cells to run (default: " + " ".join(f"{s}:{n}" for s, n in CELLS) + ")")
    parser.add_argument("--steps", type=int, default=100, help="T (default: %(default)s; the video has 50 frames)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default: %(default)s)")
    parser.add_argument("--csv", type=Path, default=None, help="write every run's figures to this CSV file")
    parser.add_argument("--resume", action="store_true",
                        help="with --csv: keep what that file holds, run only the variants it lacks for each seed "
                             "and append them (a long run cut short goes on where it stopped)")
    parser.add_argument("--rerun", nargs="+", default=(), metavar="VARIANT",
                        help="with --csv and --resume: drop these variants' rows from the file first, so that they "
                             "are run again for every seed (after a change to one of them, e.g. --rerun choose)")
    parser.add_argument("--from-csv", type=Path, default=None, help="only rebuild the tables from this CSV file")
    parser.add_argument("--bases", nargs="+", default=(), metavar="ARM",
                        help="also run the chooser on these base arms (--choose-base ARM), each a variant "
                             "'choose, ARM base' with its verdicts")
    parser.add_argument("--from-step", nargs="+", type=int, default=(), metavar="J",
                        help="also run each arm of --from-arms put in force from step J on (roughening before, no "
                             "evidence looked at): what a chooser that must wait for evidence would get from it")
    parser.add_argument("--from-arms", nargs="+", default=("dt-relative", "regularised"), metavar="ARM",
                        help="the arms of --from-step (default: dt-relative regularised)")
    parser.add_argument("--tune", nargs="+", default=(), metavar="KEY=VALUE",
                        help="also run the chooser with one setting of ChoosePS changed, each a variant 'choose, KEY "
                             "VALUE' with its verdicts (KEY: " + ", ".join(TUNABLE) + "; enter in nats, e.g. "
                             "enter=4.595 for odds of 99 to 1)")
    parser.add_argument("--quick", action="store_true", help="6 seeds, T = 25, N = 50 on every scenario: a smoke run")
    parser.add_argument("--cost", action="store_true",
                        help="only time the system layer per step at N = 1e3 and 1e5 against the entity's filter")
    args = parser.parse_args(argv)
    for arm in args.bases:
        try:
            add_base(arm)
        except ValueError as error:
            parser.error(f"--bases: {error}")
    for setting in args.tune:
        try:
            add_tuned(setting)
        except (ValueError, TypeError) as error:
            parser.error(f"--tune: {error}")
    for start in args.from_step:
        for arm in args.from_arms:
            try:
                add_from_step(arm, start)
            except ValueError as error:
                parser.error(f"--from-step: {error}")
    if args.cost:
        print("\n".join(cost()))
        return 0
    if args.from_csv is not None:
        text, met = report(read_csv(args.from_csv))
        print(text)
        return 0
    cells = list(CELLS)
    if args.cells:
        cells = []
        for item in args.cells:
            scenario, _, n = item.partition(":")
            if scenario not in SCENARIOS or not n.isdigit():
                parser.error(f"--cells takes SCENARIO:N with SCENARIO one of {', '.join(SCENARIOS)}, got {item!r}")
            cells.append((scenario, int(n)))
    if args.quick:
        args.seeds, args.steps = 6, 25
        cells = [(sc, 50) for sc in SCENARIOS]
    if args.seeds < 2:
        parser.error("--seeds must be at least 2 (confidence intervals)")
    frames = 50
    # Seeds outermost: a run cut short holds every cell for the seeds done.
    tasks = [Task(sc, n, seed, min(args.steps, frames) if sc == "video" else args.steps)
             for seed in range(args.first_seed, args.first_seed + args.seeds) for sc, n in cells]
    results: dict[tuple[str, int], dict[int, dict]] = {cell: {} for cell in cells}
    if args.resume and args.csv is None:
        parser.error("--resume needs --csv FILE")
    unknown = [label for label in args.rerun if label not in VARIANTS]
    if unknown or (args.rerun and not args.resume):
        parser.error(f"--rerun takes variants of {', '.join(VARIANTS)} and needs --resume"
                     + (f"; unknown: {', '.join(unknown)}" if unknown else ""))
    resumed = args.resume and args.csv.exists()
    if resumed:
        try:
            _upgrade_header(args.csv)
        except ValueError as error:
            parser.error(f"--resume: {error}")
        if args.rerun:
            _drop_variants(args.csv, set(args.rerun), cells)  # the cells run now, the others as they are
        for cell, by_seed in read_csv(args.csv).items():
            if cell in results:
                results[cell].update(by_seed)
        kept, tasks = tasks, []
        for t in kept:
            have = results[(t.scenario, t.particles)].get(t.seed, {})
            missing = tuple(label for label in VARIANTS if label not in have)
            if missing:
                tasks.append(t if len(missing) == len(VARIANTS) else replace(t, labels=missing))
        print(f"resuming {args.csv}: {len(kept) - len(tasks)} cell-seeds done, {len(tasks)} to run "
              f"({sum(1 for t in tasks if t.labels)} of them only for the variants they lack)", file=sys.stderr)
    progress = TaskProgress("evaluate_chooser", len(tasks))
    start = time.perf_counter()
    writer = handle = None
    if args.csv is not None:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        if resumed and not args.csv.read_bytes().endswith(b"\n"):  # a last row cut short: end its line
            args.csv.open("a").write("\n")
        handle = open(args.csv, "a" if resumed else "w", newline="")
        writer = csv.writer(handle)
        if not resumed:
            writer.writerow(CSV_FIELDS)

    def keep(done: Task, figures: dict[str, dict]) -> None:
        results[(done.scenario, done.particles)].setdefault(done.seed, {}).update(figures)
        if writer is not None:
            for label, f in figures.items():
                writer.writerow([done.scenario, done.particles, done.seed, label,
                                 *(f.get(name, "") for name in FIGURES)])
            handle.flush()

    scenarios = sorted({sc for sc, _ in cells})
    try:
        if args.workers <= 1:
            _warm_up(scenarios)
            for i, task in enumerate(tasks, 1):
                keep(*run_task(task))
                progress(i)
        else:
            with get_context("fork").Pool(args.workers, initializer=_warm_up, initargs=(scenarios,)) as pool:
                for i, done in enumerate(pool.imap(run_task, tasks, chunksize=2), 1):
                    keep(*done)
                    progress(i)
    finally:
        if handle is not None:
            handle.close()
    elapsed = time.perf_counter() - start
    given = list(argv if argv is not None else sys.argv[1:])
    command = " ".join(["python -m dtpf.scripts.paper.evaluate_chooser", *given])
    print(f"`{command}`: T = {args.steps} (video: its {frames} frames), {args.seeds} seeds per cell (from seed "
          f"{args.first_seed}), {len(VARIANTS)} variants, {args.workers} worker processes; error mean ± 95% CI "
          f"over seeds; differences paired by seed ± their 95% CI, marked where the interval excludes 0.\n")
    text, met = report(results)
    print(text)
    scenario, n = cells[0]
    print(f"\nThe error and the difference against systematic of a cell (here {scenario}, N = {n}, run from the "
          f"repository's root) with dtpf compare, for every variant but the hindsight row and the Kalman filter "
          f"(--baseline choose for the other column; its intervals use z = 1.96):\n\n    "
          f"{compare_command(scenario, n, args.steps, args.seeds, args.first_seed)}")
    print(f"\n({elapsed:.0f} s on {args.workers} workers)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
