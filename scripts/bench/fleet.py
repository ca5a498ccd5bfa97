"""A fleet's throughput, step latency and memory: K twins on shared layers against K solo launches.

For each (N, K): (f) ``dtpf.scripts.fleet.launch_fleet`` (K twins in one entity
process per CPU, one information, one system service, one recorder), and,
where it fits (``--solo-max``), (k) K solo ``dtpf.scripts.launch.launch`` at once
(4 processes per twin). Figures:

- twin-steps/s: every estimate of every twin, divided by the time from the
  first estimate of the fleet to its last;
- step latency p50 / p99: per twin, the time between two consecutive
  estimates (one lockstep step: particles out, preprocessed set back,
  resampled, estimate out), steps 10..T of every twin pooled;
- RSS: the largest resident set of each child process, sampled every 0.25 s
  from /proc (the launcher's own process is not counted), summed by kind;
  "shared per twin" is (RSS of the information + system services at K minus
  at K = 1) / (K - 1), the growth the fleet target bounds at 2 MB per twin at N = 1e3;
- CPU per twin-step (fleets): each process's CPU time (utime + stime from
  /proc, sampled with the RSS) between the fleet's first and last estimate,
  interpolated between samples, summed by kind and divided by the twin-steps
  of that window; "launcher" is this process (the router, the fleet's progress
  and the sampler). Less moved by other load than twin-steps/s, and it says
  which process to make cheaper.

Beside each fleet, in the same run (``--no-floor`` leaves them out):

- (f) the floor: ``dtpf.scripts.bench.fleet_floor`` with the same K, steps (at
  least 3,000 twin-steps, so the CPU samples span its window) and entity processes: the fleet's messages (topics and sizes from the log of a
  short solo launch at the same N with the fleet's point clouds) between
  stand-in processes that do no work, its CPU per twin-step counted the same
  way;
- (a) the in-process step's CPU: ``dtpf.scripts.bench.pipeline``'s in-process
  pipeline at the same N and steps, CPU time (``time.process_time``) per step
  over steps 10..T after a warm-up run, in a child process with the layers'
  settings (one BLAS thread, large blocks kept).

The message path's target: at K = 100, N = 1e3, CPU per twin-step at most
2 x ((a) + (f)'s CPU per twin-step); the ratio CPU / ((a) + (f)) is printed
for every fleet (PASS/FAIL where it is the target's case).

Run from the repository root::

    python -m dtpf.scripts.bench.fleet                              # K = 1, 10, 100 at 1e3; 1, 10 at 1e5
    python -m dtpf.scripts.bench.fleet --quick                      # K = 100 at 1e3 and its floor: about 1 min
    python -m dtpf.scripts.bench.fleet --cases 1e3:1,10 --steps 100
"""
from __future__ import annotations

import argparse
import functools
import os
import platform
import random
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from dtpf.messages.config import RunConfig
from dtpf.messages.family import POLICIES
from dtpf.scripts.bench import fleet_floor
from dtpf.scripts.bench.cpu import RssSampler, _descendants  # noqa: F401 (_descendants: imported from here too)
from dtpf.scripts.bench.pipeline import inprocess_step
from dtpf.scripts.fleet import FLEET_CLOUD_POINTS, launch_fleet
from dtpf.scripts.launch import launch

#: (N, K) measured by default, and the steps of each run.
DEFAULT_CASES = {1_000: (1, 10, 100), 100_000: (1, 10)}
DEFAULT_STEPS = {1_000: 200, 100_000: 60}
FIRST_TIMED = 10
TARGET_K, TARGET_N, TARGET_RATE = 100, 1_000, 1_000.0
TARGET_SHARED_MB_PER_TWIN = 2.0
#: CPU per twin-step at (TARGET_N, TARGET_K) at most this many times (in-process step CPU + the floor's).
FLOOR_FACTOR = 2.0
#: Twin-steps a floor run takes at least (more steps per twin than the fleet's when K is small).
FLOOR_TWIN_STEPS = 3_000
#: Floor runs tried before a fleet case gives up on its floor (a run stalls when a stand-in's sample is lost).
FLOOR_ATTEMPTS = 3
#: --quick: the target's case alone, no solo launches, these steps per twin.
QUICK_STEPS = 100


def step_latencies(estimates_by_twin: dict[str, list]) -> list[float]:
    """Seconds between consecutive estimates of each twin, from step FIRST_TIMED on, pooled."""
    gaps = []
    for estimates in estimates_by_twin.values():
        stamps = [e.stamp.to_ns() * 1e-9 for e in sorted(estimates, key=lambda e: e.step) if e.step >= FIRST_TIMED]
        gaps += list(np.diff(stamps))
    return gaps


def run_fleet(n: int, k: int, steps: int, folder: Path, entities: int | None = None) -> dict:
    config = RunConfig(particles=n, steps=steps, twin=f"b{n}k{k}", run_id="bench")
    with RssSampler() as rss:
        result = launch_fleet(config, k, log_path=folder / f"fleet-{n}-{k}.mcap", timeout=10.0, keep_estimates=True,
                              entities=entities)
    if result.failures or result.twin_steps != k * steps:
        raise RuntimeError(f"fleet N={n} K={k} incomplete: {result.twin_steps} of {k * steps} twin-steps, "
                           f"{result.failures}")
    by_twin = {twin: tally.estimates for twin, tally in result.tallies.items()}
    stamps = [e.stamp.to_ns() * 1e-9 for estimates in by_twin.values() for e in estimates]
    window = sum(1 for estimates in by_twin.values() for e in estimates) - 1  # twin-steps after the first
    cpu = rss.cpu_between(min(stamps), max(stamps))
    return {"rate": result.twin_steps / result.stepping, "gaps": step_latencies(by_twin), "rss": rss.by_kind(),
            "degraded": sum(t.degraded for t in result.tallies.values()), "rejected": sum(result.rejected.values()),
            "cpu_ms": {kind: 1e3 * seconds / max(window, 1) for kind, seconds in cpu.items()}}


def run_solo(n: int, k: int, steps: int, folder: Path) -> dict:
    results: dict[int, object] = {}

    def one(i: int) -> None:
        config = RunConfig(particles=n, steps=steps, twin=f"s{n}k{k}-{i}", run_id="bench")
        results[i] = launch(config, log_path=folder / f"solo-{n}-{k}-{i}.mcap", timeout=10.0,
                            notify=lambda text: None)

    with RssSampler() as rss:
        threads = [threading.Thread(target=one, args=(i,)) for i in range(1, k + 1)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    estimates = [e for r in results.values() for e in r.estimates]
    if len(estimates) != k * steps:
        raise RuntimeError(f"solo N={n} K={k} incomplete: {len(estimates)} of {k * steps} estimates")
    stamps = [e.stamp.to_ns() * 1e-9 for e in estimates]
    by_twin = {str(i): r.estimates for i, r in results.items()}
    return {"rate": len(estimates) / (max(stamps) - min(stamps)), "gaps": step_latencies(by_twin),
            "rss": rss.by_kind(), "degraded": sum(e.degraded for e in estimates),
            "rejected": sum(sum(r.rejected.values()) for r in results.values())}


#: The floor's messages at each N, from the first floor run's launch.
_plans: dict[int, dict[str, int]] = {}


def run_floor(n: int, k: int, steps: int, folder: Path, entities: int | None = None) -> dict:
    """The floor of a fleet of K twins at N (``dtpf.scripts.bench.fleet_floor``, the product's receivers),
    with the messages of a short solo launch at N with the fleet's point clouds."""
    plan = _plans.get(n)
    if plan is None:
        config = RunConfig(particles=n, steps=steps, twin=f"p{n}", run_id="bench")
        plan = _plans[n] = fleet_floor.plan_of_launch(config, folder, cloud_points=FLEET_CLOUD_POINTS)
    # At least FLOOR_TWIN_STEPS in its window: the CPU samples, 0.25 s apart, must span it (a floor of 10 twins
    # of 40 steps took 0.18 s and read no CPU at all).
    steps = max(steps, -(-FLOOR_TWIN_STEPS // k))
    stalls = []
    while len(stalls) < FLOOR_ATTEMPTS:
        # The fleet runs the fixed policy, whose decisions its information layer does not wait for.
        result = fleet_floor.one_run(k, "inbox", steps, entities or os.cpu_count() or 1, plan=plan,
                                     waits=not POLICIES.trait(RunConfig().policy, "constant", False))
        if "stalled" not in result:
            return {**result, "plan": plan, "stalls": stalls}
        # A stand-in's sample lost now and then (fleet_floor's inbox receivers, on a loaded machine): run again.
        stalls.append(result["stalled"])
        print(f"  the floor stalled after {result['stalled']} of {k * steps} twin-steps (none for 30 s); again",
              file=sys.stderr, flush=True)
    raise RuntimeError(f"floor N={n} K={k} stalled {FLOOR_ATTEMPTS} times, after {stalls} of {k * steps} twin-steps")


def parse_cases(texts: list[str]) -> dict[int, tuple[int, ...]]:
    cases = {}
    for text in texts:
        n, _, ks = text.partition(":")
        cases[int(float(n))] = tuple(int(k) for k in ks.split(","))
    return cases


def _median_run(runs: list[dict]) -> dict:
    """One run's figures of several: the run of median rate, its CPU per kind the median of each kind's
    (``cpu_all``: the median of the runs' sums)."""
    if len(runs) == 1:
        return {**runs[0], "cpu_all": sum(runs[0].get("cpu_ms", {}).values())}
    chosen = sorted(runs, key=lambda r: r["rate"])[len(runs) // 2]
    result = dict(chosen)
    if "cpu_ms" in chosen:
        kinds = {kind for r in runs for kind in r["cpu_ms"]}
        result["cpu_ms"] = {kind: statistics.median(r["cpu_ms"].get(kind, 0.0) for r in runs) for kind in kinds}
        result["cpu_all"] = statistics.median(sum(r["cpu_ms"].values()) for r in runs)
    return result


def _mb(values) -> str:
    return f"{sum(values) / 2**20:.0f}" if values else "-"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.fleet", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="+", default=None, metavar="N:K,K",
                        help="the (N, K) to measure, e.g. 1e3:1,10,100 1e5:1,10 (the default)")
    parser.add_argument("--steps", type=int, default=None, help="steps per twin (default: 200 at 1e3, 60 at 1e5)")
    parser.add_argument("--solo-max", type=int, default=None,
                        help="run K solo launches for comparison when K is at most this (default: 10; 0 with "
                             "--quick)")
    parser.add_argument("--entities", type=int, default=None, metavar="E",
                        help="entity processes hosting a fleet's twins, as dtpf launch --entities (default: one "
                             "per CPU)")
    parser.add_argument("--no-floor", dest="floor", action="store_false",
                        help="leave out, beside each fleet, (f) its floor (dtpf.scripts.bench.fleet_floor: the same "
                             "K, steps and messages between stand-ins that do no work) and (a) the in-process step's "
                             "CPU, and the target CPU per twin-step <= 2 x ((a) + (f))")
    parser.add_argument("--repeats", type=int, default=1,
                        help="runs of each fleet and of its floor, interleaved in random order; the tables give "
                             "medians (default: %(default)s)")
    parser.add_argument("--quick", action="store_true",
                        help=f"a short run: the target's case alone (K = {TARGET_K}, N = 1e3), "
                             f"{QUICK_STEPS} steps, no solo launches (options given as well override these)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the run order (default: %(default)s)")
    args = parser.parse_args(argv)
    if args.entities is not None and args.entities < 1:
        parser.error(f"--entities must be at least 1, got {args.entities}")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    if args.quick:
        args.cases = args.cases or [f"{TARGET_N}:{TARGET_K}"]
        args.steps = args.steps or QUICK_STEPS
        args.solo_max = 0 if args.solo_max is None else args.solo_max
    args.solo_max = 10 if args.solo_max is None else args.solo_max
    cases = parse_cases(args.cases) if args.cases else DEFAULT_CASES
    rows = []
    floors: dict[tuple[int, int], dict] = {}
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    order = random.Random(args.seed)
    with tempfile.TemporaryDirectory(prefix="dtpf-bench-fleet-") as folder:
        for n, ks in cases.items():
            steps = args.steps or DEFAULT_STEPS.get(n, 100)
            for k in ks:
                runs: dict[str, list[dict]] = {"fleet": [], "floor": [], "solo": []}
                for repeat in range(args.repeats):
                    modes = ["fleet"] + (["floor"] if args.floor else []) + (["solo"] if k <= args.solo_max else [])
                    order.shuffle(modes)
                    for mode in modes:
                        run = {"fleet": functools.partial(run_fleet, entities=args.entities), "solo": run_solo,
                               "floor": functools.partial(run_floor, entities=args.entities)}[mode]
                        print(f"N={n} K={k} {mode} ({steps} steps), run {repeat + 1}/{args.repeats}", file=sys.stderr)
                        runs[mode].append(run(n, k, steps, Path(folder)))
                        for path in Path(folder).glob("*.mcap"):
                            path.unlink()
                for mode in ("fleet", "solo"):
                    if runs[mode]:
                        rows.append((n, k, mode, _median_run(runs[mode])))
                if args.floor:
                    print(f"N={n} in-process step CPU ({steps} steps)", file=sys.stderr)
                    floors[n, k] = {"floor": _median_run(runs["floor"]), "runs": runs,
                                    "a_ms": 1e3 * statistics.median(inprocess_step(n, steps)["cpu_s"]
                                                                    for _ in range(args.repeats))}
    print(f"`python -m dtpf.scripts.bench.fleet{' ' + ' '.join(sys.argv[1:]) if sys.argv[1:] else ''}`: Python "
          f"{platform.python_version()}, {os.cpu_count()} CPUs, {time.perf_counter() - start:.0f} s in all, "
          f"1-min load {load_before:.2f} before.\n")
    print("| N | K | mode | twin-steps/s | step p50 ms | step p99 ms | RSS MB: entity | information | system | "
          "recorder | degraded | rejected |")
    print("|---" * 12 + "|")
    shared_at: dict[tuple[int, int], float] = {}
    for n, k, mode, r in rows:
        gaps = r["gaps"]
        p50, p99 = (1e3 * float(np.percentile(gaps, q)) for q in (50, 99))
        rss = r["rss"]
        if mode == "fleet":
            shared_at[n, k] = (sum(rss.get("information", [])) + sum(rss.get("system", []))) / 2**20
        print(f"| {n:.0e} | {k} | {mode} | {r['rate']:.0f} | {p50:.2f} | {p99:.2f} | {_mb(rss.get('entity', []))} | "
              f"{_mb(rss.get('information', []))} | {_mb(rss.get('system', []))} | {_mb(rss.get('recorder', []))} | "
              f"{r['degraded']} | {r['rejected']} |")
    print("\nRSS: the peak of each process, summed over the processes of a kind (K solo launches have K of each).")
    kinds = ("entity", "information", "system", "recorder", "launcher")
    print("\n| N | K | CPU ms per twin-step: " + " | ".join(kinds) + " | all |\n" + "|---" * (len(kinds) + 3) + "|")
    for n, k, mode, r in rows:
        if "cpu_ms" in r:
            cpu = r["cpu_ms"]
            print(f"| {n:.0e} | {k} | " + " | ".join(f"{cpu.get(kind, 0.0):.3f}" for kind in kinds)
                  + f" | {r['cpu_all']:.3f} |")
    print("\nCPU: utime + stime from /proc between the fleet's first and last estimate, by kind of process "
          "(launcher: this process, the router in it), per twin-step of that window"
          + (f"; medians over {args.repeats} runs." if args.repeats > 1 else "."))
    target_ratio = None
    if floors:
        print("\n| N | K | fleet CPU ms per twin-step | (a) in-process step CPU ms | (f) floor CPU ms per twin-step "
              "| (f) floor twin-steps/s | fleet twin-steps/s | CPU / ((a) + (f)) (range) |\n" + "|---" * 8 + "|")
        for n, k, mode, r in rows:
            if mode != "fleet" or (n, k) not in floors:
                continue
            f, a_ms = floors[n, k]["floor"], floors[n, k]["a_ms"]
            pairs = zip(floors[n, k]["runs"]["fleet"], floors[n, k]["runs"]["floor"])
            ratios = [sum(x["cpu_ms"].values()) / (a_ms + sum(y["cpu_ms"].values())) for x, y in pairs]
            ratio = statistics.median(ratios)
            if (n, k) == (TARGET_N, TARGET_K):
                target_ratio = (r["cpu_all"], a_ms, f["cpu_all"], ratio)
            print(f"| {n:.0e} | {k} | {r['cpu_all']:.3f} | {a_ms:.3f} | {f['cpu_all']:.3f} | {f['rate']:.0f} | "
                  f"{r['rate']:.0f} | {ratio:.2f} ({min(ratios):.2f}-{max(ratios):.2f}) |")
        plans = {n: floor["floor"]["plan"] for (n, k), floor in floors.items()}
        print("\n(f): dtpf.scripts.bench.fleet_floor with the same K, steps (at least "
              f"{FLOOR_TWIN_STEPS:,} twin-steps) and entity processes, receivers as the "
              "product's (one subscriber per twin and topic), CPU counted as the fleet's; its messages per twin-step, "
              "from a 12-step solo launch at N with the fleet's point clouds: "
              + "; ".join(f"{n:.0e}: " + ", ".join(f"{topic} {size:,}" for topic, size in plan.items())
                          for n, plan in plans.items())
              + " bytes. (a): the in-process pipeline's CPU time per step (steps 10..T, one BLAS thread). "
              "The ratio is the median of the runs' (fleet, floor) pairs.")
        stalls = [(n, k, len(r["stalls"])) for (n, k), floor in floors.items() for r in floor["runs"]["floor"]
                  if r["stalls"]]
        if stalls:
            print("Floor runs that stalled (a stand-in's sample lost) and ran again: "
                  + ", ".join(f"N = {n:.0e}, K = {k}: {count}" for n, k, count in stalls) + ".")
    failed = False
    for (n, k), shared in sorted(shared_at.items()):
        if k > 1 and (n, 1) in shared_at:
            per_twin = (shared - shared_at[n, 1]) / (k - 1)
            line = f"- N = {n:.0e}: shared services grow {per_twin:.2f} MB per twin from K = 1 to K = {k}"
            if n == TARGET_N:
                ok = per_twin <= TARGET_SHARED_MB_PER_TWIN
                failed |= not ok
                line += f" (target at most {TARGET_SHARED_MB_PER_TWIN}: {'PASS' if ok else 'FAIL'})"
            print(line)
    for n, k, mode, r in rows:
        if (n, k, mode) == (TARGET_N, TARGET_K, "fleet"):
            ok = r["rate"] >= TARGET_RATE
            failed |= not ok
            print(f"- N = {n:.0e}, K = {k}: {r['rate']:.0f} twin-steps/s (target at least {TARGET_RATE:.0f}: "
                  f"{'PASS' if ok else 'FAIL'})")
    if target_ratio is not None:
        cpu, a_ms, f_ms, ratio = target_ratio
        ok = ratio <= FLOOR_FACTOR
        print(f"- N = 1e3, K = {TARGET_K}: CPU per twin-step at most {FLOOR_FACTOR:g} x (in-process step "
              f"CPU + floor CPU per twin-step): {cpu:.3f} ms against {FLOOR_FACTOR:g} x ({a_ms:.3f} + {f_ms:.3f}) = "
              f"{FLOOR_FACTOR * (a_ms + f_ms):.3f} ms; CPU / ((a) + (f)) {ratio:.2f} (at most {FLOOR_FACTOR:g}): "
              f"{'PASS' if ok else 'FAIL'} (reported, not in the exit code)")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
