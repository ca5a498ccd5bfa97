"""Steady-state time per filter step: in-process pipeline against three processes over Zenoh.

(a) in-process  the three layers in one process (``dtpf.scripts.inprocess.build``:
                the filter calls the information and system layers directly),
                RunConfig with preprocess=True.
(b) three-process  ``dtpf.scripts.launch.launch``: an embedded Zenoh router in this
                process, the recorder, system, information and entity services
                as child processes, lockstep over Zenoh (the product's real
                configuration).
(c) no recorder  the same without the MCAP recorder: the split alone, like
                (a), which writes no log either (``--recorder with`` or
                ``without`` runs only (b) or only (c)).
(s) secured      (b) with ``launch(secure=...)``: the router listens on
                ``tls/`` with mutual TLS and enforces the access control of
                ``dtpf secure init`` (made in a temporary folder); (u) the same
                with user/password over tcp/ (``--secure`` picks which; the
                ratio (s)/(b) is the cost of securing the twin).
(n) no cloud     (b) with ``--cloud-points 0``: no foxglove.PointCloud per
                step (``--cloud-cost``; the ratio (b)/(n) is the cloud's cost).
(f) floor        the same hops with stand-ins that do no work
                (``dtpf.scripts.bench.fleet_floor`` with one twin): an entity,
                an information, a system and a recorder stand-in, clients of a
                router in this process as (b)'s layers are of the launcher's,
                receive with ``dtpf.shell.bus.Inbox`` and publish with the
                product's publishers the messages of (b)'s step, of the sizes
                and on the topics a short launch at the same N logged (measured
                before the repetitions, statuses left out): entity -> information
                (the set), information -> entity (the answer) and -> system (the
                weight state), system -> information (the PS decision, which the
                information stand-in waits for before it answers the next set,
                as the information layer does; under the fixed policy, the
                default, neither waits),
                the entity's estimate and point cloud to the recorder and this
                process; the recorder stand-in takes every message. Its time per
                step is the round trip of those hops (``--no-floor`` leaves it out).

All run the same RunConfig (same seed, so the same numbers). Only the steady
state is timed: for (b), the time per step is taken from the ``stamp`` of the
Estimate messages between step 10 and the last step, so process start-up, JIT
loading and liveliness discovery are excluded; for (a), the same window of
steps is timed with ``perf_counter`` in a run that follows an untimed warm-up
run at the same N; for (f), the same window of estimates as this process
receives them. The modes are interleaved in every repetition, in random
order; the table shows medians over repetitions, and (b)/(a) is the median of
the per-repetition ratios of time per step.

The message path's targets against the floor (printed with their ratios,
PASS/FAIL; they decide no exit code): at N = 1e3, (b) at most 2 x ((a) + (f)),
the in-process step plus the floor's round trip, both measured in the same
repetition; at N = 1e5, (b)/(a) at most 1.3 with the recorder.

Run from the repository root::

    python -m dtpf.scripts.bench.pipeline                          # N = 1e3 .. 1e6, 3 repetitions: about 5 minutes
    python -m dtpf.scripts.bench.pipeline --quick                  # 1e3 and 1e5, (a), (b), (c), (f): 1-2 minutes
    python -m dtpf.scripts.bench.pipeline --sizes 1e5 --steps 200 --repeats 5
    python -m dtpf.scripts.bench.pipeline --recorder with         # (a), (b) and (f) only
    python -m dtpf.scripts.bench.pipeline --sizes 1e3 1e5 --recorder with --secure tls   # secured against plain
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import random
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from dtpf.messages.config import RunConfig
from dtpf.scripts import launch as launch_module
from dtpf.scripts.bench import fleet_floor
from dtpf.scripts.inprocess import build, simulate
from dtpf.shell.service import keep_large_blocks

#: Steps per run at the default sizes (the timed window is steps FIRST_TIMED .. T).
DEFAULT_STEPS = {1_000: 400, 10_000: 300, 100_000: 150, 1_000_000: 40}
#: First step of the timed window: steps before it (start-up, discovery, JIT) are not timed.
FIRST_TIMED = 10
#: Targets: (b) steps per second at N = 1e3, and (b)/(a) at N = 1e5.
TARGET_RATE_N, TARGET_RATE = 1_000, 200.0
TARGET_RATIO_N, TARGET_RATIO = 100_000, 1.5
#: The message path's targets for one twin, with the recorder: (b) / ((a) + (f)) at N = 1e3 (the in-process step plus
#: the floor's round trip) and (b)/(a) at N = 1e5. Printed beside the targets above; they decide no exit code.
FLOOR_N, FLOOR_FACTOR = 1_000, 2.0
PATH_RATIO_N, PATH_RATIO = 100_000, 1.3
#: --quick: sizes, steps at each, repetitions.
QUICK_SIZES, QUICK_STEPS, QUICK_REPEATS = (1_000, 100_000), (200, 60), 2
#: Target of a secured launch: (s)/(b) at N = 1e5.
TARGET_SECURED_N, TARGET_SECURED = 100_000, 1.2
#: Target of the per-step point cloud at its default cap: (b)/(n) at N = 1e5.
TARGET_CLOUD_N, TARGET_CLOUD = 100_000, 1.10
#: Environment variables that change the figures; shown in the output.
TUNING_PREFIXES = ("MALLOC_", "OPENBLAS_", "OMP_", "MKL_")
#: 1-min load average above which the output warns that the machine was busy.
BUSY_LOAD = 1.0


def default_steps(n: int) -> int:
    """Steps per run at N: the table above, or the entry of the nearest default size."""
    nearest = min(DEFAULT_STEPS, key=lambda size: abs(np.log10(size) - np.log10(n)))
    return DEFAULT_STEPS[nearest]


def parse_size(text: str) -> int:
    """'1e5' or '100000' -> 100000."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if value < 1 or value != int(value):
        raise argparse.ArgumentTypeError(f"N must be a positive integer, got {text!r}")
    return int(value)


def window_time(times: list[float]) -> float:
    """Seconds per step between step FIRST_TIMED and the last step; ``times[k - 1]`` is the end of step k."""
    last = len(times)
    return (times[last - 1] - times[FIRST_TIMED - 1]) / (last - FIRST_TIMED)


# --- (a) in-process -----------------------------------------------------------

def run_inprocess(config: RunConfig) -> float:
    """Seconds per step of the in-process pipeline over the timed window.

    The same code as ``dtpf.scripts.inprocess.run`` (``simulate`` + ``build``), but
    the steps are not kept: the entity service does not keep them either.
    """
    return inprocess_times(config)[0]


def inprocess_times(config: RunConfig) -> tuple[float, float]:
    """(wall seconds, CPU seconds of this process) per step of the in-process pipeline over the timed window."""
    _, observations = simulate(config)
    pf = build(config, observations)
    walls, cpus = [], []
    for _ in pf:
        walls.append(time.perf_counter())
        cpus.append(time.process_time())
    return window_time(walls), window_time(cpus)


def inprocess_step(n: int, steps: int, seed: int = 0) -> dict[str, float]:
    """(a) at N in a child process with the layers' settings (one BLAS thread, large blocks kept), after
    a warm-up run: ``{"wall_s": ..., "cpu_s": ...}`` per step. For the benchmarks whose own process must
    keep its allocator (the fleet's launcher, the live benchmark's sensor)."""
    out = subprocess.run([sys.executable, "-P", "-m", "dtpf.scripts.bench.pipeline", "--inprocess", str(n),
                          str(steps), str(seed)], check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _inprocess_child(n: int, steps: int, seed: int) -> int:
    keep_large_blocks()
    threadpool_limits(limits=1, user_api="blas")
    config = RunConfig(particles=n, steps=steps, preprocess=True, seed=seed, run_id="bench")
    run_inprocess(config.model_copy(update={"steps": FIRST_TIMED + 2}))
    wall, cpu = inprocess_times(config)
    print(json.dumps({"wall_s": wall, "cpu_s": cpu}))
    return 0


# --- (f) the floor: the same hops, stand-ins that do no work -----------------

def run_floor(config: RunConfig, plan: dict[str, int], recorder: bool = True, cpu: list | None = None) -> float:
    """Seconds per step of one twin's stand-ins passing ``plan``'s messages (steps 10..T), with the recorder's
    stand-in or without; ``cpu``: a list to append the stand-ins' CPU seconds per step to (all processes)."""
    from dtpf.messages import family
    result = fleet_floor.one_run(1, "inbox", config.steps, 1, plan=plan, recorder=recorder,
                                 waits=not family.POLICIES.trait(config.policy, "constant", False))
    if "stalled" in result:
        raise RuntimeError(f"floor at N={config.particles} stalled after {result['stalled']} of {config.steps} "
                           "estimates")
    if cpu is not None:
        cpu.append(sum(result["cpu_ms"].values()) / 1e3)
    return result["step_s"]


# --- (b) three processes over Zenoh -------------------------------------------

def run_launched(config: RunConfig, *, recorder: bool, timeout: float, folder: Path,
                 cloud_points: int | None = None, secure: Path | None = None,
                 threads: int | None = None) -> tuple[float, float, int]:
    """(seconds per step over the timed window, wall seconds of the whole launch, degraded steps);
    ``threads``: each layer's thread count (None: every core)."""
    log_path = folder / f"bench-{config.particles}-{time.monotonic_ns()}.mcap"
    start = time.perf_counter()
    result = launch_module.launch(config, log_path=log_path, timeout=timeout, child_output=None, record=recorder,
                                  cloud_points=cloud_points, notify=lambda text: None, secure=secure,
                                  threads=threads)
    wall = time.perf_counter() - start
    with contextlib.suppress(FileNotFoundError):
        log_path.unlink()
    stamps = {e.step: e.stamp.to_ns() * 1e-9 for e in result.estimates}
    missing = [k for k in range(1, config.steps + 1) if k not in stamps]
    if missing or any(code != 0 for code in result.exit_codes.values()):
        raise RuntimeError(f"three-process run at N={config.particles} incomplete: {len(missing)} estimates "
                           f"missing, exit codes {result.exit_codes}")
    times = [stamps[k] for k in range(1, config.steps + 1)]
    return window_time(times), wall, sum(e.degraded for e in result.estimates)


# --- report -------------------------------------------------------------------

def fmt_n(n: int) -> str:
    """1000 -> '1e3'; other values as integers."""
    exponent = int(round(np.log10(n)))
    return f"1e{exponent}" if 10 ** exponent == n else str(n)


def fmt_ms(seconds: float) -> str:
    ms = 1e3 * seconds
    return f"{ms:.3g}" if ms < 100 else f"{ms:.0f}"


def fmt_rate(seconds: float) -> str:
    rate = 1.0 / seconds
    return f"{rate:.3g}" if rate < 1000 else f"{rate:.0f}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m dtpf.scripts.bench.pipeline",
        description=__doc__,
        epilog="Start-up, JIT loading and liveliness discovery are excluded: only steps "
               f"{FIRST_TIMED}..T are timed. Environment variables (e.g. MALLOC_MMAP_THRESHOLD_) are "
               "inherited by the child services. Exit code 1 when a target fails (the message path's targets are "
               "reported, not in the exit code).",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help=f"a short run: N = {' '.join(fmt_n(n) for n in QUICK_SIZES)}, "
                             f"{', '.join(str(t) for t in QUICK_STEPS)} steps, {QUICK_REPEATS} repetitions, "
                             "--secure off (options given as well override these)")
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=None, metavar="N",
                        help="numbers of particles (default: 1e3 1e4 1e5 1e6)")
    parser.add_argument("--steps", type=int, nargs="+", default=None, metavar="T",
                        help="steps per run: one value for every N, or one per N "
                             f"(default: {', '.join(f'{t} at {fmt_n(n)}' for n, t in DEFAULT_STEPS.items())})")
    parser.add_argument("--repeats", type=int, default=None, help="repetitions per N (default: 3)")
    parser.add_argument("--recorder", choices=("both", "with", "without"), default="both",
                        help="three-process runs with the MCAP recorder (b, as dtpf launch runs), without it "
                             "(c, the split alone), or both (default: %(default)s)")
    parser.add_argument("--timeout", type=float, default=10.0, metavar="SECONDS",
                        help="lockstep timeout of the services; large, so no step degrades (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every run and of the order (default: %(default)s)")
    parser.add_argument("--cloud-points", type=int, default=None, metavar="K",
                        help="the entity's foxglove.PointCloud of each step: at most K particles, 0 none "
                             "(default: the entity's default, 1000)")
    parser.add_argument("--cloud-cost", action="store_true",
                        help="also run (n), (b) without the per-step point cloud, and print (b)/(n)")
    parser.add_argument("--secure", choices=("off", "tls", "usrpwd", "both"), default=None,
                        help="also run (b) secured: (s) mutual TLS and access control, (u) user/password and "
                             "access control, both, or off (default: tls)")
    parser.add_argument("--no-floor", dest="floor", action="store_false",
                        help="leave out (f), the floor: the same hops and messages as (b) between stand-in "
                             "processes that do no work (dtpf.scripts.bench.fleet_floor with one twin), whose "
                             "time per step is the round trip the (b) <= 2 x ((a) + (f)) target adds to (a)")
    parser.add_argument("--inprocess", nargs=3, type=int, metavar=("N", "T", "SEED"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.inprocess:
        return _inprocess_child(*args.inprocess)
    if args.quick:
        if args.sizes is None:
            args.sizes = list(QUICK_SIZES)
            args.steps = list(QUICK_STEPS) if args.steps is None else args.steps
        args.repeats = QUICK_REPEATS if args.repeats is None else args.repeats
        args.secure = "off" if args.secure is None else args.secure
    args.sizes = sorted(DEFAULT_STEPS) if args.sizes is None else args.sizes
    args.repeats = 3 if args.repeats is None else args.repeats
    args.secure = "tls" if args.secure is None else args.secure
    if args.steps is None:
        steps = [default_steps(n) for n in args.sizes]
    elif len(args.steps) == 1:
        steps = args.steps * len(args.sizes)
    elif len(args.steps) == len(args.sizes):
        steps = args.steps
    else:
        parser.error(f"--steps takes one value or one per N ({len(args.sizes)}), got {len(args.steps)}")
    if min(steps) < FIRST_TIMED + 2:
        parser.error(f"--steps must be at least {FIRST_TIMED + 2}: steps {FIRST_TIMED}..T are timed")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    # (a) runs in this process: give it the allocator and BLAS settings every layer process of (b)
    # gets (dtpf.shell.service.run_service), so the ratio compares the split, not the settings.
    # Without it, (a) at N = 1e5 took 7.3-8.2 ms alone and 6.05 ms after larger N had grown the heap.
    keep_large_blocks()
    threadpool_limits(limits=1, user_api="blas")

    configs = {n: RunConfig(particles=n, steps=t, preprocess=True, seed=args.seed, run_id="bench")
               for n, t in zip(args.sizes, steps)}
    order = random.Random(args.seed)
    launched = {"both": "bc", "with": "b", "without": "c"}[args.recorder]
    launched += {"off": "", "tls": "s", "usrpwd": "u", "both": "su"}[args.secure]
    launched += "n" if args.cloud_cost else ""
    if args.cloud_cost and "b" not in launched:
        parser.error("--cloud-cost compares with (b): use --recorder with or both")
    floor = "f" if args.floor else ""
    per_step: dict[tuple[int, str], list[float]] = {(n, m): [] for n in configs for m in "a" + floor + launched}
    walls: dict[tuple[int, str], list[float]] = {(n, m): [] for n in configs for m in launched}
    degraded: dict[int, int] = {n: 0 for n in configs}
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    # Warm-up of (a): imports, numba caches, the first large allocations.
    for n, config in configs.items():
        print(f"warm-up N={n}", file=sys.stderr)
        run_inprocess(config.model_copy(update={"steps": FIRST_TIMED + 2}))
    plans: dict[int, dict[str, int]] = {}
    with tempfile.TemporaryDirectory(prefix="dtpf-bench-") as folder:
        if set("su") & set(launched):
            from dtpf.scripts.secure import init
            init(Path(folder) / "secure")
        secure_of = {"s": Path(folder) / "secure" / "tls", "u": Path(folder) / "secure" / "usrpwd"}
        if floor:  # the messages of (b)'s step, from the log of a short launch at each N
            for n, config in configs.items():
                print(f"the floor's messages at N={n}: a launch of {FIRST_TIMED + 2} steps", file=sys.stderr)
                plans[n] = fleet_floor.plan_of_launch(config, folder, steps=FIRST_TIMED + 2,
                                                      cloud_points=args.cloud_points)
        for repeat in range(args.repeats):
            for n, config in configs.items():
                modes = ["a", *floor, *launched]
                order.shuffle(modes)
                for mode in modes:
                    print(f"repeat {repeat + 1}/{args.repeats} N={n} T={config.steps} ({mode})", file=sys.stderr)
                    if mode == "a":
                        per_step[n, "a"].append(run_inprocess(config))
                    elif mode == "f":
                        per_step[n, "f"].append(run_floor(config, plans[n]))
                    else:
                        seconds, wall, bad = run_launched(config, recorder=mode != "c", timeout=args.timeout,
                                                          cloud_points=0 if mode == "n" else args.cloud_points,
                                                          folder=Path(folder), secure=secure_of.get(mode))
                        per_step[n, mode].append(seconds)
                        walls[n, mode].append(wall)
                        degraded[n] += bad
    total = time.perf_counter() - start

    tuning = {k: v for k, v in sorted(os.environ.items()) if k.startswith(TUNING_PREFIXES)}
    command = "python -m dtpf.scripts.bench.pipeline" + (" " + " ".join(sys.argv[1:]) if sys.argv[1:] else "")
    print(f"`{command}`: Python {platform.python_version()}, numpy {np.__version__}, {os.cpu_count()} CPUs, "
          f"all with one BLAS thread and large blocks kept (dtpf.shell.service), environment "
          f"{' '.join(f'{k}={v}' for k, v in tuning.items()) if tuning else 'untuned'} "
          f"(inherited by the services); {total:.0f} s in all; 1-min load average {load_before:.2f} before the run.\n")
    if load_before > BUSY_LOAD:
        print(f"WARNING: the machine was busy before the run (load {load_before:.2f} on {os.cpu_count()} CPUs): "
              "other processes compete with the five of (b); the figures are unreliable.\n")
    names = {"b": "(b) 3-process + recorder", "c": "(c) 3-process, no recorder", "s": "(s) secured, mTLS",
             "u": "(u) secured, user/password", "n": "(n) (b) without cloud"}
    header = "| N | steps (timed) | (a) in-process steps/s | (a) ms/step |"
    for mode in launched:
        header += f" {names[mode]} steps/s | ({mode}) ms/step | ({mode})/(a) |"
    against_floor = launched[0] if floor else ""
    if floor:
        header += f" (f) floor ms/step | ({against_floor})/((a)+(f)) |"
    print(header + f" ({launched[0]}) launch wall s |")
    print("|---" * (4 + 3 * len(launched) + 2 * len(floor) + 1) + "|")
    ratio_of, rate_of = {}, {}
    for n, config in configs.items():
        a = per_step[n, "a"]
        ma = statistics.median(a)
        row = f"| {fmt_n(n)} | {config.steps} ({config.steps - FIRST_TIMED}) | {fmt_rate(ma)} | {fmt_ms(ma)} |"
        for mode in launched:
            b = per_step[n, mode]
            ratios = [y / x for x, y in zip(a, b)]
            ratio_of[n, mode] = statistics.median(ratios)
            mb = statistics.median(b)
            rate_of[n, mode] = 1.0 / mb
            row += (f" {fmt_rate(mb)} | {fmt_ms(mb)} | {ratio_of[n, mode]:.2f} "
                    f"({min(ratios):.2f}-{max(ratios):.2f}) |")
        if floor:
            f = per_step[n, "f"]
            ratios = [y / (x + z) for x, y, z in zip(a, per_step[n, against_floor], f)]
            ratio_of[n, "floor"] = statistics.median(ratios)
            row += (f" {fmt_ms(statistics.median(f))} | {ratio_of[n, 'floor']:.2f} "
                    f"({min(ratios):.2f}-{max(ratios):.2f}) |")
        print(row + f" {statistics.median(walls[n, launched[0]]):.1f} |")
    secured = [mode for mode in "su" if mode in launched]
    against_b = secured + (["n"] if "n" in launched else [])
    if against_b and "b" in launched:
        print("\n| N | " + " | ".join(f"({mode})/(b) per step" if mode != "n" else "(b)/(n): the cloud's cost"
                                     for mode in against_b) + " |")
        print("|---" * (1 + len(against_b)) + "|")
        for n in configs:
            cells = []
            for mode in against_b:
                pairs = zip(per_step[n, "b"], per_step[n, mode])
                ratios = [y / x for x, y in pairs] if mode != "n" else [x / y for x, y in pairs]
                ratio_of[n, mode + "/b"] = statistics.median(ratios)
                cells.append(f"{ratio_of[n, mode + '/b']:.2f} ({min(ratios):.2f}-{max(ratios):.2f})")
            print(f"| {fmt_n(n)} | " + " | ".join(cells) + " |")
    print(f"\nMedians over {args.repeats} repetitions, the modes interleaved in random order. Time per step "
          f"= time from the end of step {FIRST_TIMED} to the end of the last step / (T - {FIRST_TIMED}): "
          "for (b) and (c) from the stamps of the entity's Estimate messages, so process start-up, JIT loading "
          "and liveliness discovery are excluded; for (a) with perf_counter, after an untimed warm-up run. "
          "Ratios are the median (min-max) of per-repetition ratios of time per step. "
          "'launch wall' is the whole dtpf launch, start-up and shutdown included."
          + (" (f): the same hops with stand-ins that do no work (dtpf.scripts.bench.fleet_floor, one twin), "
             "time per step from the estimates this process receives; its messages per step, from a launch of "
             f"{FIRST_TIMED + 2} steps at each N: "
             + "; ".join(f"{fmt_n(n)}: " + ", ".join(f"{topic} {size:,}" for topic, size in plan.items())
                         for n, plan in plans.items()) + " bytes." if floor else ""))
    if any(degraded.values()):
        print("\nWARNING: degraded steps in (b) (no preprocessed answer within the timeout): "
              + ", ".join(f"N={fmt_n(n)}: {d}" for n, d in degraded.items() if d))

    print("\nTargets (on the product's configuration, (b) when it ran; (c) for the split alone):")
    failed = False
    for mode in launched.replace("s", "").replace("u", "").replace("n", ""):
        label = names[mode].split(" ", 1)[0]
        if TARGET_RATE_N in configs:
            rate = rate_of[TARGET_RATE_N, mode]
            ok = rate >= TARGET_RATE
            failed |= not ok and mode == launched[0]
            print(f"- N = {fmt_n(TARGET_RATE_N)}: {label} at least {TARGET_RATE:.0f} steps/s: {rate:.0f} steps/s, "
                  f"{'PASS' if ok else 'FAIL'}")
        if TARGET_RATIO_N in configs:
            ratio = ratio_of[TARGET_RATIO_N, mode]
            ok = ratio <= TARGET_RATIO
            failed |= not ok and mode == launched[0]
            print(f"- N = {fmt_n(TARGET_RATIO_N)}: {label}/(a) at most {TARGET_RATIO}: {ratio:.2f}, "
                  f"{'PASS' if ok else 'FAIL'}")
    for mode in secured:
        if TARGET_SECURED_N in configs and "b" in launched:
            ratio = ratio_of[TARGET_SECURED_N, mode + "/b"]
            ok = ratio <= TARGET_SECURED
            failed |= not ok
            print(f"- N = {fmt_n(TARGET_SECURED_N)}: ({mode})/(b) at most {TARGET_SECURED}: {ratio:.2f}, "
                  f"{'PASS' if ok else 'FAIL'}")
    if "n" in launched and TARGET_CLOUD_N in configs:
        ratio = ratio_of[TARGET_CLOUD_N, "n/b"]
        ok = ratio <= TARGET_CLOUD
        failed |= not ok
        print(f"- N = {fmt_n(TARGET_CLOUD_N)}: (b)/(n), the point cloud's cost, at most {TARGET_CLOUD}: {ratio:.3f}, "
              f"{'PASS' if ok else 'FAIL'}")
    if "b" in launched and (FLOOR_N in configs or PATH_RATIO_N in configs):
        print("\nThe message path's targets for one twin, (b), with the recorder (reported, not in the exit code):")
        if FLOOR_N in configs and floor:
            a, b, f = (statistics.median(per_step[FLOOR_N, mode]) for mode in "abf")
            ratio = ratio_of[FLOOR_N, "floor"]
            print(f"- N = {fmt_n(FLOOR_N)}: (b) at most {FLOOR_FACTOR:g} x ((a) in-process step + (f) floor round "
                  f"trip): (b) {fmt_ms(b)} ms against {FLOOR_FACTOR:g} x ({fmt_ms(a)} + {fmt_ms(f)}) = "
                  f"{fmt_ms(FLOOR_FACTOR * (a + f))} ms; (b)/((a)+(f)) {ratio:.2f} (at most {FLOOR_FACTOR:g}), "
                  f"{'PASS' if ratio <= FLOOR_FACTOR else 'FAIL'}")
        elif FLOOR_N in configs:
            print(f"- N = {fmt_n(FLOOR_N)}: (b) at most {FLOOR_FACTOR:g} x ((a) + (f)): not measured (--no-floor)")
        if PATH_RATIO_N in configs:
            ratio = ratio_of[PATH_RATIO_N, "b"]
            print(f"- N = {fmt_n(PATH_RATIO_N)}: (b)/(a) at most {PATH_RATIO}: {ratio:.2f}, "
                  f"{'PASS' if ratio <= PATH_RATIO else 'FAIL'}")
    if not {TARGET_RATE_N, TARGET_RATIO_N, FLOOR_N, PATH_RATIO_N} <= set(configs):
        print(f"- (N = {fmt_n(TARGET_RATE_N)} and N = {fmt_n(TARGET_RATIO_N)} carry the targets; not all measured)")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
