"""The kernels and the in-process step on one thread and on every core (:mod:`dtpf.entity.cores`).

Part 1, kernels, at each N, on the blocks of a new run (B = ``BLOCK_PARTICLES``), in this process with
``cores.set_threads(t)`` and glibc keeping large blocks (as the layers' processes do): the radix select (W of Eq. 28 and the mirror's quantiles), the mirror's summary
(ESS, entropy, quantiles), DT preprocessing (Eq. 28-30), the propagation of the growth model (its noise block
by block, Eq. 35), its likelihood (Eq. 36), the normalisation with the ESS (Eq. 23, 25), the moments,
systematic resampling and the gather. A cell is the time per call, calls repeated to at least 50 ms a sample:
in samples of 10 ms the second thread of this 2-vCPU VM added nothing to most kernels (after it slept, it
takes milliseconds to run at speed), in 50 ms samples it does.

Part 2, the in-process step (``dtpf.scripts.inprocess.build``, scenario ``ungm``, preprocessing on, seed 0),
each run in a fresh child process with the layers' settings (one BLAS thread, glibc keeping large blocks)
after a warm-up run: the time per step from step 10 to the last. ``--before PATH`` also times the step of
a checkout from before blocks (a ``git worktree``; its children run with ``PYTHONPATH=PATH`` and numba on
one thread), so that N = 1e3 shows what the change costs where it does not apply.

Method: the cells run interleaved, in a new random order in every repetition (part 1: the thread counts in a
random order, the kernels in a random order under each); cells are medians over repetitions, and a ratio is the median of per-repetition ratios (2 threads / 1 thread of the same
repetition). Run from the repository root::

    python -m dtpf.scripts.bench.cores                          # N = 1e3, 1e5, 1e6
    python -m dtpf.scripts.bench.cores --quick                  # a smoke run, seconds
    git worktree add /tmp/before <commit> && python -m dtpf.scripts.bench.cores --before /tmp/before
"""
from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import time

import numpy as np

__all__ = ["main"]

#: Part 2: steps of the timed run at each N (the window starts at step 10).
STEPS = {1_000: 200, 100_000: 60, 1_000_000: 30}
#: Targets: the in-process step on every core / on one, at these N.
TARGET_RATIO = 0.6
TARGET_SIZES = (100_000, 1_000_000)
#: N = 1e3 (one block): the step on every core, and the step before blocks, against one thread; at most this.
SMALL_N, SMALL_SLOWER = 1_000, 1.05

#: The child's code: only names that a checkout from before blocks has too.
CHILD = """
import json, sys, time
import numpy as np
from threadpoolctl import threadpool_limits
threadpool_limits(limits=1, user_api="blas")
from dtpf.shell.service import keep_large_blocks
keep_large_blocks()
try:
    from dtpf.entity import cores
    cores.set_threads(int(sys.argv[3]))
except ImportError:  # a checkout from before blocks
    pass
from dtpf.entity import sources
from dtpf.messages.config import RunConfig
from dtpf.scripts.inprocess import build
n, steps = int(sys.argv[1]), int(sys.argv[2])
config = RunConfig(particles=n, steps=steps, preprocess=True, seed=0, run_id="bench")
_, z = sources.load_model(config, check=False).simulate(steps, np.random.default_rng(0))
for _ in build(config, z[:12]):
    pass
ends = []
for _ in build(config, z):
    ends.append(time.perf_counter())
print(json.dumps({"ms": 1e3 * (ends[-1] - ends[9]) / (len(ends) - 10)}))
"""


def step_ms(n: int, threads: int, before: str | None = None) -> float:
    """ms per in-process step at N in a fresh child (``before``: that checkout, numba on one thread)."""
    env = dict(os.environ)
    if before is not None:
        env["PYTHONPATH"] = before
        env["NUMBA_NUM_THREADS"] = "1"
    out = subprocess.run([sys.executable, "-c", CHILD, str(n), str(STEPS.get(n, 40)), str(threads)], env=env,
                         check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])["ms"]


def kernels(n: int, block: int):
    """(name, call) of every kernel at N on one data set (the weights of a propagated set's likelihood)."""
    from dtpf.entity import blocks, models, resampling
    from dtpf.information import mirror, rules, select

    model = models.get("ungm")
    rng = np.random.default_rng(1)
    x = model.initial_particles(n, rng)
    z = 5.0
    lw = model.log_likelihood(x, z, 2)
    w = np.exp(lw - lw.max())
    w /= w.sum()
    ancestors = resampling.systematic(w, np.random.default_rng(2))
    out = np.empty_like(x)
    ranks = np.sort(np.concatenate([[n - int(round(1.0 / np.dot(w, w))) - 1],
                                    np.floor(np.array([0.1, 0.5, 0.9, 0.99]) * (n - 1)).astype(int)]))
    for a in (x, w):
        a.flags.writeable = False  # as a decoded message's

    def propagate():
        g = np.random.default_rng(3)
        model.propagate(x, 2, g, noise=blocks.noise(model, n, 2, g, block, (0, "bench")))

    return [
        ("radix select (W and 4 quantiles)", lambda: select.order_statistics(w, ranks)),
        ("mirror (ESS, entropy, quantiles)", lambda: mirror.summarise(x, w, "neff", n // 2, checked=True,
                                                                     block=block)),
        ("DT preprocessing (Eq. 28-30)", lambda: rules.preprocess(x, w, 0.81, np.random.default_rng(4),
                                                                  checked=True, block=block)),
        ("propagation (noise by block, Eq. 35)", propagate),
        ("likelihood (Eq. 36)", lambda: model.log_likelihood(x, z, 2)),
        ("normalise + ESS (Eq. 23, 25)", lambda: blocks.normalise(lw, block, float(lw.max()))),
        ("moments", lambda: blocks.moments(x, w, block)),
        ("systematic (by block)", lambda: resampling.systematic_blocks(w, np.random.default_rng(5), block)),
        ("gather", lambda: resampling.gather(x, ancestors, out)),
    ]


def time_call(call, least: float = 50e-3) -> float:
    """Seconds per call, calls repeated until one sample lasts ``least``."""
    calls, start = 0, time.perf_counter()
    while True:
        call()
        calls += 1
        spent = time.perf_counter() - start
        if spent >= least:
            return spent / calls


def fmt(ms: float) -> str:
    return f"{ms:.3g} ms" if ms >= 0.01 else f"{ms * 1e3:.3g} us"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.cores", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[1e3, 1e5, 1e6], help="N of the step")
    parser.add_argument("--kernel-sizes", type=float, nargs="+", default=[1e5, 1e6], help="N of the kernels")
    parser.add_argument("--repeats", type=int, default=7, help="repetitions of each cell")
    parser.add_argument("--before", default=None, metavar="PATH",
                        help="a checkout from before blocks (git worktree) whose step is timed too")
    parser.add_argument("--quick", action="store_true", help="N = 1e5 only, 2 repetitions")
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes, args.kernel_sizes, args.repeats = [1e5], [1e5], 2
    from dtpf.entity import cores
    from dtpf.messages.config import BLOCK_PARTICLES
    from dtpf.shell.service import keep_large_blocks

    keep_large_blocks()  # as a layer's process: freed arrays stay on the heap, no page faults on reuse

    most = cores.available()
    counts = sorted({1, most})
    load = os.getloadavg()[0]
    print(f"# dtpf kernels on 1 and {most} threads; B = {BLOCK_PARTICLES}; {os.cpu_count()} CPUs; load average "
          f"(1 min) {load:.2f} at the start")
    started = time.perf_counter()

    # Part 1: kernels.
    rows = []
    for n in map(int, args.kernel_sizes):
        calls = kernels(n, BLOCK_PARTICLES)
        for t in counts:  # warm-up: every JIT, on every thread count
            cores.set_threads(t)
            for _, call in calls:
                call()
        times = {(name, t): [] for name, _ in calls for t in counts}
        for _ in range(args.repeats):
            # The thread counts in a new order each repetition, the kernels in a new order under each: numba's
            # thread count is switched once a phase (its first parallel loop after a switch is slow).
            for t in random.sample(counts, len(counts)):
                cores.set_threads(t)
                for name, call in random.sample(calls, len(calls)):
                    times[name, t].append(1e3 * time_call(call))
        for name, _ in calls:
            rows.append((name, n, times, counts))
    cores.set_threads(None)
    print(f"\n## Kernels (n = {args.repeats} repetitions)\n")
    print(f"| kernel | N | 1 thread | {most} threads | {most} / 1 |")
    print("|---|---|---|---|---|")
    for name, n, times, _ in rows:
        one, every = times[name, 1], times[name, most]
        ratios = [b / a for a, b in zip(one, every)]
        print(f"| {name} | {n:.0e} | {fmt(statistics.median(one))} | {fmt(statistics.median(every))} | "
              f"×{statistics.median(ratios):.2f} ({min(ratios):.2f}-{max(ratios):.2f}) |")

    # Part 2: the in-process step, in children.
    variants = [(t, None) for t in counts] + ([(1, args.before)] if args.before else [])
    steps = {(n, v): [] for n in map(int, args.sizes) for v in variants}
    for _ in range(args.repeats):
        cells = list(steps)
        random.shuffle(cells)
        for n, (t, before) in cells:
            steps[n, (t, before)].append(step_ms(n, t, before))
    print(f"\n## In-process step (ungm, preprocessing on; n = {args.repeats} repetitions)\n")
    head = "| N | 1 thread | " + f"{most} threads | {most} / 1 |" + (" before blocks, 1 thread | 1 / before |"
                                                                     if args.before else "")
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    verdicts = []
    for n in map(int, args.sizes):
        one, every = steps[n, (1, None)], steps[n, (most, None)]
        ratios = [b / a for a, b in zip(one, every)]
        line = (f"| {n:.0e} | {fmt(statistics.median(one))} | {fmt(statistics.median(every))} | "
                f"×{statistics.median(ratios):.2f} ({min(ratios):.2f}-{max(ratios):.2f}) |")
        if args.before:
            old = steps[n, (1, args.before)]
            against = [a / b for a, b in zip(one, old)]
            line += f" {fmt(statistics.median(old))} | ×{statistics.median(against):.2f} " \
                    f"({min(against):.2f}-{max(against):.2f}) |"
            if n == SMALL_N:
                verdicts.append((f"N = {n:.0e}: step 1 thread / before blocks <= {SMALL_SLOWER}",
                                 statistics.median(against), SMALL_SLOWER))
        print(line)
        if n in TARGET_SIZES and most > 1:
            verdicts.append((f"N = {n:.0e}: step {most} threads / 1 thread <= {TARGET_RATIO}",
                             statistics.median(ratios), TARGET_RATIO))
        if n == SMALL_N and most > 1:
            verdicts.append((f"N = {n:.0e}: step {most} threads / 1 thread <= {SMALL_SLOWER}",
                             statistics.median(ratios), SMALL_SLOWER))
    print("\nTargets:")
    for text, value, bound in verdicts:
        print(f"- {text}: ×{value:.2f}, {'PASS' if value <= bound else 'FAIL'}")
    print(f"\n{time.perf_counter() - started:.0f} s; load average (1 min) {os.getloadavg()[0]:.2f} at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
