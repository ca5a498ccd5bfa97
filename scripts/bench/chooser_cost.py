"""What the choosing policy costs: time per step of the default twin against the plain filter and the paper's.

Four runs of the same scenario, N and seed, side by side:

- plain    ``--no-preprocess``: the entity alone, systematic resampling (no twin consulted);
- paper    the paper's twin: DT preprocessing at PS 0.81 (``--policy fixed``), the layers every step;
- choose   ``--policy choose``: the system layer runs the five arms' copies, on roughening (docs/guides/policies.md);
- default  what ``dtpf launch`` and ``dtpf run`` take when no policy is named: ``--policy choose --choose-base
           rehearse``, the copies of the arms its rehearsal kept, on the base it chose.

Each is timed two ways: in one process (``dtpf run``'s pipeline, :func:`dtpf.scripts.bench.pipeline.inprocess_times`:
wall time per step over steps FIRST_TIMED..T after an untimed warm-up), and through ``dtpf launch`` (the layers as
processes over Zenoh, no recorder): the CPU seconds of all the twin's processes (entity, information, system) between
the estimates of step FIRST_TIMED and T, sampled from /proc (:class:`dtpf.scripts.bench.cpu.RssSampler`), per step.
The default's rehearsal comes before step 1, outside the timed window; ``--rehearsal`` times it on its own. The runs
are interleaved in random order in every repetition; the table shows medians over repetitions, and the ratios are
medians of the per-repetition ratios. Targets (printed PASS/FAIL, no exit code): the default at most 2 x plain at
N = 100 and 1.5 x at N = 1000, in process and through launch; "paper / plain" is their floor, the paper's twin alone::

    python -m dtpf.scripts.bench.chooser_cost                       # N = 100 and 1000, 3 repetitions
    python -m dtpf.scripts.bench.chooser_cost --repeats 5 --steps 400
    python -m dtpf.scripts.bench.chooser_cost --where inprocess     # in process only (seconds)
    python -m dtpf.scripts.bench.chooser_cost --copies 250 100      # and choose with smaller copies (in process)
    python -m dtpf.scripts.bench.chooser_cost --rehearsal ungm range-bearing   # and the default's rehearsal, once
                                                                    # per run, on these scenarios

The rehearsal of ``--rehearsal`` is computed afresh each time (wall seconds of one rehearsal of min(T, 100) steps at
each N, median over the repetitions), beside what the plain filter takes for the run's T steps. The default's own
runs read the rehearsal from the cache (:func:`dtpf.system.rehearse.cache_folder`) after the first.
"""
from __future__ import annotations

import argparse
import os
import platform
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from dtpf.messages.config import RunConfig
from dtpf.scripts.bench.cpu import RssSampler
from dtpf.scripts.bench.pipeline import FIRST_TIMED, inprocess_times, window_time

#: The runs compared, by label: their RunConfig fields ("default": what dtpf launch and dtpf run take when no policy
#: is named, the choosing policy on a rehearsed base; its rehearsal comes before the timed window).
MODES = {"plain": dict(preprocess=False), "paper": dict(), "choose": dict(policy="choose"),
         "default": dict(policy="choose", choose_base="rehearse")}
#: Targets: choose / plain at most this at N.
TARGETS = {100: 2.0, 1000: 1.5}
#: The twin's processes whose CPU a launch counts (the launcher's embedded router is not the twin's).
LAYERS = ("entity", "information", "system")


def config_of(mode: str, n: int, steps: int, seed: int) -> RunConfig:
    return RunConfig(particles=n, steps=steps, seed=seed, run_id="bench", twin=f"cost-{mode}-{n}", **MODES[mode])


def inprocess_ms(config: RunConfig, copies: int | None = None) -> float:
    """Wall ms per step of the in-process pipeline over the timed window, after an untimed warm-up run;
    ``copies``: choose's copies of M particles each instead of its default (``ChoosePS(particles=M)``)."""
    if copies is None:
        if not config.rehearses:   # a warm-up run (a rehearsing one would rehearse its shorter T first)
            inprocess_times(config.model_copy(update={"steps": FIRST_TIMED + 2}))
        return 1e3 * inprocess_times(config)[0]
    from dtpf.scripts.inprocess import build, simulate
    from dtpf.system.layer import SystemLayer

    for steps in (FIRST_TIMED + 2, config.steps):  # a warm-up run, then the timed one
        run = config.model_copy(update={"steps": steps})
        _, observations = simulate(run)
        pf = build(run, observations)
        pf.preprocessor.system = SystemLayer.from_config(run, policy_options={"particles": copies})
        walls = []
        for _ in pf:
            walls.append(time.perf_counter())
    return 1e3 * window_time(walls)


def launched_ms(config: RunConfig, folder: Path, timeout: float = 10.0) -> float:
    """CPU ms per step of the twin's processes (:data:`LAYERS`) through ``dtpf launch`` (no recorder), between the
    estimates of steps FIRST_TIMED and T."""
    from dtpf.scripts import launch as launch_module

    with RssSampler(interval=0.02) as sampler:
        result = launch_module.launch(config, log_path=folder / f"{config.twin}-{time.monotonic_ns()}.mcap",
                                      timeout=timeout, child_output=None, record=False, notify=lambda text: None)
    stamps = {e.step: e.stamp.to_ns() * 1e-9 for e in result.estimates}
    if len(stamps) < config.steps:  # a layer stopped at the end (an exit code of 130 on shutdown) spoils nothing
        raise RuntimeError(f"launch of {config.twin} incomplete: {len(stamps)} of {config.steps} estimates, "
                           f"exit codes {result.exit_codes}")
    first, last = stamps[FIRST_TIMED], stamps[config.steps]
    cpu = sampler.cpu_between(first, last)
    return 1e3 * sum(cpu.get(kind, 0.0) for kind in LAYERS) / (config.steps - FIRST_TIMED)


def measure(sizes, wheres, repeats: int, steps: int, seed: int, progress=print, copies=()) -> dict:
    """{(where, n, mode): [ms per step of each repetition]}, the runs interleaved in random order; ``copies``:
    in process, choose with copies of M particles as well (mode "choose, M = ...")."""
    order = random.Random(seed)
    figures: dict[tuple[str, int, str], list[float]] = {}
    with tempfile.TemporaryDirectory() as folder:
        for repeat in range(repeats):
            runs = [(where, n, mode) for where in wheres for n in sizes for mode in MODES]
            runs += [("inprocess", n, f"choose, M = {m}") for n in sizes for m in copies if "inprocess" in wheres]
            order.shuffle(runs)
            for where, n, mode in runs:
                if mode.startswith("choose, M = "):
                    m = int(mode.rsplit(" ", 1)[1])
                    ms = inprocess_ms(config_of("choose", n, steps, seed), copies=m)
                    figures.setdefault((where, n, mode), []).append(ms)
                    progress(f"repetition {repeat + 1}: {where} N = {n} {mode}: {ms:.3f} ms / step")
                    continue
                config = config_of(mode, n, steps, seed)
                ms = inprocess_ms(config) if where == "inprocess" else launched_ms(config, Path(folder))
                figures.setdefault((where, n, mode), []).append(ms)
                progress(f"repetition {repeat + 1}: {where} N = {n} {mode}: {ms:.3f} ms / step")
    return figures


def ratio(figures: dict, where: str, n: int, mode: str, against: str) -> float:
    """Median over repetitions of ``mode``'s time over ``against``'s (the same repetition)."""
    return statistics.median(a / b for a, b in zip(figures[where, n, mode], figures[where, n, against]))


def table(figures: dict, sizes, wheres) -> str:
    header = ("| measured | N | plain, ms / step | paper (PS 0.81) | choose (roughening base) | default (choose, "
              "rehearsed) | default / plain | paper / plain: the floor | default / paper | choose / plain | target "
              "(default / plain) | verdict |")
    rows = [header, "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    labels = {"inprocess": "in process (wall)", "launch": "dtpf launch (CPU of entity + information + system)"}
    for where in wheres:
        for n in sizes:
            ms = {mode: statistics.median(figures[where, n, mode]) for mode in MODES}
            cost = ratio(figures, where, n, "default", "plain")
            target = TARGETS.get(n)
            verdict = "-" if target is None else "PASS" if cost <= target else "FAIL"
            rows.append(f"| {labels[where]} | {n} | {ms['plain']:.3f} | {ms['paper']:.3f} | {ms['choose']:.3f} | "
                        f"{ms['default']:.3f} | {cost:.2f} | {ratio(figures, where, n, 'paper', 'plain'):.2f} | "
                        f"{ratio(figures, where, n, 'default', 'paper'):.2f} | "
                        f"{ratio(figures, where, n, 'choose', 'plain'):.2f} | "
                        f"{'-' if target is None else f'<= {target:g}'} | {verdict} |")
    extra = sorted({mode for (_, _, mode) in figures if mode not in MODES}, key=lambda m: int(m.rsplit(" ", 1)[1]))
    if extra:
        rows += ["", "| in process (wall), choose with copies of M particles | N | ms / step | / plain | / choose |",
                 "|---|---|---|---|---|"]
        for mode in extra:
            for n in sizes:
                rows.append(f"| {mode} | {n} | {statistics.median(figures['inprocess', n, mode]):.3f} | "
                            f"{ratio(figures, 'inprocess', n, mode, 'plain'):.2f} | "
                            f"{ratio(figures, 'inprocess', n, mode, 'choose'):.2f} |")
    return "\n".join(rows)


#: The scenarios --rehearsal takes beyond the built-in ones: the drifting constant 100 from the origin, and the
#: range-bearing target of docs/examples.
EXTRA_SCENARIOS = ("drift+100", "range-bearing")


def scenario_model(name: str):
    """The model of a scenario --rehearsal names: a built-in one, or one of :data:`EXTRA_SCENARIOS`."""
    from dtpf.entity import model_ref, models

    if name == "drift+100":
        return models.DriftModel(prior_mean=100.0)
    if name == "range-bearing":
        examples = Path(__file__).resolve().parents[2] / "docs" / "examples"
        return model_ref.resolve(f"{examples / 'range_bearing.py'}:RangeBearingTarget")
    return models.get(name)


def rehearsal_seconds(scenarios, sizes, repeats: int, steps: int, progress=print) -> dict:
    """{(scenario, n): [(wall seconds of one rehearsal, its runs, its base), per repetition]}, each computed
    afresh (an empty cache folder each time), on the cores of this process."""
    from dtpf.information.layer import ARMS
    from dtpf.system import rehearse

    figures: dict[tuple[str, int], list[float]] = {}
    for repeat in range(repeats):
        for scenario in scenarios:
            model = scenario_model(scenario)
            for n in sizes:
                rehearse._CACHE.clear()
                before = os.environ.get("XDG_CACHE_HOME")
                with tempfile.TemporaryDirectory() as folder:   # an empty cache: nothing read, made afresh
                    os.environ["XDG_CACHE_HOME"] = folder
                    start = time.perf_counter()
                    result = rehearse.rehearse(model, tuple(ARMS), n=n, steps=steps)
                    seconds = time.perf_counter() - start
                if before is None:
                    os.environ.pop("XDG_CACHE_HOME", None)
                else:
                    os.environ["XDG_CACHE_HOME"] = before
                figures.setdefault((scenario, n), []).append((seconds, result.runs, result.arm))
                progress(f"repetition {repeat + 1}: rehearsal {scenario} N = {n}: {seconds:.1f} s, base {result.arm}")
    return figures


def rehearsal_table(figures: dict, plain: dict, steps: int) -> str:
    rows = [f"| rehearsal (once a run; runs of {min(steps, 100)} steps) | N | runs | base | seconds | ms a run | "
            f"the plain filter's {steps} steps in process, seconds |", "|---|---|---|---|---|---|---|"]
    for (scenario, n), done in figures.items():
        seconds = statistics.median(s for s, _, _ in done)
        _, runs, arm = done[0]   # the same in every repetition: the rehearsal is deterministic
        run = plain.get(("inprocess", n, "plain"))
        rows.append(f"| {scenario} | {n} | {runs} | {arm} | {seconds:.1f} | {1e3 * seconds / runs:.0f} | "
                    f"{'-' if not run else f'{statistics.median(run) * steps / 1e3:.3f}'} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=sorted(TARGETS))
    parser.add_argument("--where", choices=("inprocess", "launch", "both"), default="both")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--copies", type=int, nargs="+", default=(), metavar="M",
                        help="in process, also choose with copies of M particles each (default M: min(N, 1000))")
    parser.add_argument("--rehearsal", nargs="+", default=(), metavar="SCENARIO",
                        help="also time --choose-base rehearse's rehearsal at each N on these scenarios (ungm, drift, "
                             "drift+100, range-bearing, moving, switching)")
    parser.add_argument("--quiet", "-q", action="store_true", help="no line per run on stderr")
    args = parser.parse_args(argv)
    if args.steps <= FIRST_TIMED + 1:
        parser.error(f"--steps must exceed {FIRST_TIMED + 1}")
    wheres = ("inprocess", "launch") if args.where == "both" else (args.where,)
    progress = (lambda text: None) if args.quiet else (lambda text: print(text, file=sys.stderr, flush=True))
    start = time.perf_counter()
    with threadpool_limits(limits=1, user_api="blas"):
        figures = measure(args.sizes, wheres, args.repeats, args.steps, args.seed, progress, args.copies)
        rehearsals = rehearsal_seconds(args.rehearsal, args.sizes, args.repeats, args.steps, progress)
    print(f"`python -m dtpf.scripts.bench.chooser_cost {' '.join(argv if argv is not None else sys.argv[1:])}`"
          f": ungm, T = {args.steps} (timed from step {FIRST_TIMED}), seed {args.seed}, median of {args.repeats} "
          f"interleaved repetitions; Python {platform.python_version()}, numpy {np.__version__}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}; {time.perf_counter() - start:.0f} s")
    print()
    print(table(figures, args.sizes, wheres))
    if rehearsals:
        print()
        print(rehearsal_table(rehearsals, figures, args.steps))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
