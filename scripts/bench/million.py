"""A million particles at sensor rate: where a step's time goes, on one core and on all, by reference and as bytes.

Modes, interleaved in random order in every repetition, at each N (the default scenario, preprocessing on):

(a1) in-process, one thread     ``dtpf.scripts.inprocess.build`` with ``cores.set_threads(1)``
(a)  in-process, every core     the same with ``cores.set_threads(None)``
(b)  dtpf launch                three processes and the recorder, every core, sets by reference
                                (shared-memory slots between the processes of the host)
(b0) dtpf launch, before        the same on one thread a layer, sets as bytes (``DTPF_SHARED_SETS=0``):
                                the product before its sets were shared and its kernels used every core
(c)  dtpf launch, no recorder   (b) without the recorder
(f)  floor, by reference        the same hops with stand-ins that do no work
                                (``dtpf.scripts.bench.fleet_floor``, one twin), sets by reference
(f0) floor, as bytes            the same, sets as bytes
(fn) floor, no recorder         (f) without the recorder's stand-in (which copies every message out, on the
                                same 2 cores)
(w)  the disk                   what the recorder writes each step (the two sets), written to a file in the
                                logs' folder as the recorder does (buffered writes, no fsync), ms per step:
                                the floor under (b) that no transport removes
(m)  the memory                 a step's two sets, each copied once into a ring of shared-memory slots as
                                its publisher copies it (``dtpf.shell.slots.SlotWriter``, the product's ring
                                size), one after the other as the lockstep does: with (f) at N = 1e3 (the
                                step's small messages), the floor under (f) that no transport removes

The floor's modes take at least 300 steps (a window of 290): at N = 1e6 its 30-step window varied 2x
between runs.

Targets (printed with PASS/FAIL; they decide no exit code): at N = 1e6 and 1e5, (f)/(a1) <= 0.1,
(a)/(a1) <= 0.6 and (b)/(a1) <= 1.0; at N = 1e6, (b) at least 10 steps per second; at N = 1e3, (b) no
slower than (b0). Ratios are medians of per-repetition ratios. Run from the repository root::

    python -m dtpf.scripts.bench.million                              # N = 1e3, 1e5, 1e6; 3 repetitions
    python -m dtpf.scripts.bench.million --sizes 1e6 --repeats 1
"""
from __future__ import annotations

import argparse
import contextlib
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

from dtpf.entity import cores
from dtpf.messages.config import RunConfig
from dtpf.scripts.bench import fleet_floor
from dtpf.scripts.bench.pipeline import (FIRST_TIMED, default_steps, fmt_ms, fmt_n, parse_size, run_floor,
                                         run_inprocess, run_launched)
from dtpf.shell.service import keep_large_blocks
from dtpf.shell.shared_sets import slots_for
from dtpf.shell.slots import SlotWriter

MODES = ("a1", "a", "b", "b0", "c", "f", "f0", "fn", "w", "m")
NAMES = {"a1": "(a1) in-process, 1 thread", "a": "(a) in-process, every core", "b": "(b) launch",
         "b0": "(b0) launch, before", "c": "(c) launch, no recorder", "f": "(f) floor, by reference",
         "f0": "(f0) floor, as bytes", "fn": "(fn) floor, no recorder", "w": "(w) the disk",
         "m": "(m) the memory"}
#: (f)'s CPU seconds per step over all its processes, by N, one per repetition.
FLOOR_CPU: dict[int, list[float]] = {}
#: Fewest steps of the floor's modes (f, f0, m): they cost little, and a short window is noisy.
FLOOR_STEPS = 300
#: Targets: (f)/(a1), (a)/(a1), (b)/(a1) at these N; (b) steps per second at 1e6; (b)/(b0) at 1e3.
TARGET_SIZES = (100_000, 1_000_000)
FLOOR_SHARE, CORES_SHARE, LAUNCH_SHARE = 0.1, 0.6, 1.0
RATE_N, RATE = 1_000_000, 10.0
SMALL_N = 1_000


@contextlib.contextmanager
def sets_as_bytes(enabled: bool):
    """Child processes started inside send their sets as bytes (``DTPF_SHARED_SETS=0``) if ``enabled``."""
    before = os.environ.get("DTPF_SHARED_SETS")
    if enabled:
        os.environ["DTPF_SHARED_SETS"] = "0"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("DTPF_SHARED_SETS", None)
        else:
            os.environ["DTPF_SHARED_SETS"] = before


def write_floor(config: RunConfig, plan: dict[str, int], folder: Path) -> float:
    """Seconds per step of writing a step's two particle sets (their sizes in ``plan``, else 16 bytes a
    particle) to a new file in ``folder`` through a buffered file, over the timed window; the file is removed."""
    size = sum(plan.get(topic, 16 * config.particles) for topic in ("entity/particles", "information/preprocessed"))
    data = np.random.default_rng(0).bytes(size // 2)
    path = folder / f"disk-{time.monotonic_ns()}.bin"
    ends = []
    try:
        with open(path, "wb") as file:
            for _ in range(config.steps):
                file.write(data)
                file.write(data)
                ends.append(time.perf_counter())
    finally:
        path.unlink(missing_ok=True)
    return (ends[-1] - ends[FIRST_TIMED - 1]) / (len(ends) - FIRST_TIMED)


def memory_floor(config: RunConfig, plan: dict[str, int]) -> float:
    """Seconds per step of copying a step's two particle sets (their sizes in ``plan``, else 16 bytes a
    particle) once each into its own ring of shared-memory slots, as their publishers do, over the window."""
    sizes = [plan.get(topic, 16 * config.particles) for topic in ("entity/particles", "information/preprocessed")]
    rings = [SlotWriter(slots=slots_for(size)) for size in sizes]
    parts = [[b"\0" * 1024, np.random.default_rng(0).random((size - 1024) // 8)] for size in sizes]
    ends = []
    try:
        for _ in range(config.steps):
            for ring, payload in zip(rings, parts):
                ring.write(payload)
            ends.append(time.perf_counter())
    finally:
        for ring in rings:
            ring.close()
    return (ends[-1] - ends[FIRST_TIMED - 1]) / (len(ends) - FIRST_TIMED)


def run_mode(mode: str, config: RunConfig, plan: dict[str, int], folder: Path, timeout: float) -> float:
    """Seconds per step of ``mode`` over the timed window."""
    if mode in ("a1", "a"):
        cores.set_threads(1 if mode == "a1" else None)
        try:
            return run_inprocess(config)
        finally:
            cores.set_threads(None)
    if mode == "w":
        return write_floor(config, plan, folder)
    if mode in ("f", "f0", "fn", "m"):
        config = config.model_copy(update={"steps": max(config.steps, FLOOR_STEPS)})
    if mode == "m":
        return memory_floor(config, plan)
    if mode in ("f", "f0", "fn"):
        with sets_as_bytes(mode == "f0"):
            return run_floor(config, plan, recorder=mode != "fn",
                             cpu=FLOOR_CPU.setdefault(config.particles, []) if mode == "f" else None)
    with sets_as_bytes(mode == "b0"):
        seconds, _, _ = run_launched(config, recorder=mode != "c", timeout=timeout, folder=folder,
                                     threads=1 if mode == "b0" else None)
    return seconds


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.million", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=[1_000, 100_000, 1_000_000], metavar="N",
                        help="numbers of particles (default: 1e3 1e5 1e6)")
    parser.add_argument("--repeats", type=int, default=3, help="repetitions (default: %(default)s)")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES),
                        help="modes to run (default: all)")
    parser.add_argument("--timeout", type=float, default=10.0, metavar="SECONDS",
                        help="lockstep timeout of the services (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every run and of the order")
    parser.add_argument("--parallel-min", type=parse_size, default=None, metavar="N",
                        help="the in-process modes' kernels share a set among the threads from N particles on "
                             f"(default: {cores.PARALLEL_MIN}, dtpf.entity.cores.PARALLEL_MIN): what a lower "
                             "threshold would give; the launched modes keep the default")
    args = parser.parse_args(argv)
    if args.parallel_min is not None:
        from dtpf.entity import resampling
        cores.PARALLEL_MIN = resampling.PARALLEL_GATHER = args.parallel_min
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    keep_large_blocks()
    threadpool_limits(limits=1, user_api="blas")
    configs = {n: RunConfig(particles=n, steps=default_steps(n), preprocess=True, seed=args.seed, run_id="bench")
               for n in sorted(args.sizes)}
    order = random.Random(args.seed)
    times: dict[tuple[int, str], list[float]] = {(n, m): [] for n in configs for m in args.modes}
    load = os.getloadavg()[0]
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="dtpf-million-") as folder:
        plans = {}
        for n, config in configs.items():
            print(f"warm-up and the floor's messages at N={n}", file=sys.stderr)
            run_inprocess(config.model_copy(update={"steps": FIRST_TIMED + 2}))
            if {"f", "f0", "fn", "w", "m"} & set(args.modes):
                plans[n] = fleet_floor.plan_of_launch(config, folder, steps=FIRST_TIMED + 2)
        for repeat in range(args.repeats):
            for n, config in configs.items():
                modes = list(args.modes)
                order.shuffle(modes)
                for mode in modes:
                    print(f"repeat {repeat + 1}/{args.repeats} N={n} ({mode})", file=sys.stderr)
                    times[n, mode].append(run_mode(mode, config, plans.get(n, {}), Path(folder), args.timeout))
    total = time.perf_counter() - start

    command = "python -m dtpf.scripts.bench.million" + (" " + " ".join(sys.argv[1:]) if sys.argv[1:] else "")
    print(f"`{command}`: Python {platform.python_version()}, numpy {np.__version__}, {os.cpu_count()} CPUs "
          f"({cores.available()} usable), {total:.0f} s in all, 1-min load average {load:.2f} before the run.\n")
    print("| N | steps | " + " | ".join(f"{NAMES[m]} ms/step" for m in args.modes) + " |")
    print("|---" * (2 + len(args.modes)) + "|")
    for n, config in configs.items():
        print(f"| {fmt_n(n)} | {config.steps} | "
              + " | ".join(fmt_ms(statistics.median(times[n, m])) for m in args.modes) + " |")

    def ratio(n: int, top: str, bottom: str) -> tuple[float, float, float] | None:
        if (n, top) not in times or (n, bottom) not in times:
            return None
        ratios = [y / x for x, y in zip(times[n, bottom], times[n, top])]
        return statistics.median(ratios), min(ratios), max(ratios)

    pairs = [("f", "a1"), ("f0", "a1"), ("fn", "a1"), ("a", "a1"), ("b", "a1"), ("b0", "a1"), ("b", "b0"), ("c", "a1"),
             ("w", "a1"), ("m", "a1")]
    shown = [(top, bottom) for top, bottom in pairs if top in args.modes and bottom in args.modes]
    print("\n| N | " + " | ".join(f"({t})/({b})" for t, b in shown) + " |")
    print("|---" * (1 + len(shown)) + "|")
    for n in configs:
        cells = [ratio(n, t, b) for t, b in shown]
        print(f"| {fmt_n(n)} | " + " | ".join(f"{r[0]:.2f} ({r[1]:.2f}-{r[2]:.2f})" for r in cells) + " |")
    print(f"\nMedians over {args.repeats} repetitions, modes interleaved in random order; time per step from the "
          f"end of step {FIRST_TIMED} to the end of the last (launches: the Estimate stamps; the floor: its "
          "estimates as this process receives them). Ratios: median (min-max) of per-repetition ratios.")

    def floor_of(n: int, top: str) -> str:
        """What bounds (f) and (b) from below at N, measured in this run: (m) + (f) at 1e3, and (w)."""
        medians = {m: statistics.median(times[n, m]) for m in args.modes if (n, m) in times}
        a1 = medians.get("a1")
        if a1 is None:
            return ""
        if top == "f" and "m" in medians and (SMALL_N, "f") in times:
            small = statistics.median(times[SMALL_N, "f"])
            spread = ""
            if FLOOR_CPU.get(n):
                per_core = statistics.median(FLOOR_CPU[n]) / cores.available()
                spread = (f"; its processes' CPU, {fmt_ms(statistics.median(FLOOR_CPU[n]))} ms a step, over "
                          f"{cores.available()} cores: {per_core / a1:.2f} of (a1)")
            return (f" (its floor: (m) {fmt_ms(medians['m'])} ms + (f) at N = {fmt_n(SMALL_N)} {fmt_ms(small)} ms = "
                    f"{(medians['m'] + small) / a1:.2f} of (a1){spread})")
        if top == "b" and "w" in medians:
            return f" (its floor: (w) {medians['w'] / a1:.2f} of (a1))"
        return ""

    print("\nTargets:")
    for n in TARGET_SIZES:
        for (top, bottom), share in ((("f", "a1"), FLOOR_SHARE), (("a", "a1"), CORES_SHARE),
                                     (("b", "a1"), LAUNCH_SHARE)):
            r = ratio(n, top, bottom) if n in configs else None
            if r is not None:
                print(f"- N = {fmt_n(n)}: ({top})/({bottom}) at most {share}: {r[0]:.2f}, "
                      f"{'PASS' if r[0] <= share else 'FAIL'}" + floor_of(n, top))
    if RATE_N in configs and "b" in args.modes:
        rate = 1.0 / statistics.median(times[RATE_N, "b"])
        print(f"- N = {fmt_n(RATE_N)}: (b) at least {RATE:.0f} steps/s: {rate:.1f}, {'PASS' if rate >= RATE else 'FAIL'}")
    r = ratio(SMALL_N, "b", "b0") if SMALL_N in configs else None
    if r is not None:
        print(f"- N = {fmt_n(SMALL_N)}: (b) no slower than (b0): (b)/(b0) {r[0]:.2f}, {'PASS' if r[0] <= 1.0 else 'FAIL'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
