"""Resampling kernels and one filter step: dtpf beside particles, filterpy and the memory floors.

Part 1, kernels: normalised weights -> N ancestor indices, at each N.

- the floors, timed in the same repetitions: one pass over the weights
  (``np.cumsum(W, out=)``), one gather of the particles by sorted ancestors
  (``np.take(X, A, axis=0, out=)``), N uniforms from the run's generator
  (``rng.random(N, out=)``);
- dtpf: ``dtpf.entity.resampling.RESAMPLERS[scheme](W, rng, out=, checked=True)``, as
  the filter calls it (numba, into a buffer, weights checked where they were
  made), and the public call that checks W and allocates;
- particles: ``particles.resampling.<scheme>(W)`` (numba; global ``np.random``,
  seeded before it is timed); SSP and killing too (``particles.resampling.ssp``,
  ``.killing``), which filterpy does not have;
- filterpy: ``filterpy.monte_carlo.<scheme>_resample(W)`` (Python loops; at
  N >= 1e6 timed in one repetition only);
- systematic + gather: dtpf's systematic, then ``dtpf.entity.resampling.gather`` on
  1 thread and on every core (numba's parallel loop), against the two floors;
- DT preprocessing: ``dtpf.information.rules.preprocess(X, W, 0.81, rng, checked=True)``
  with X of shape (N, 1) (Eq. 28-30), against dtpf's systematic.

Each dtpf kernel gets its ratio to the floor that bounds it (``BOUNDS``), to
the weight pass alone, and to particles' kernel; the targets
(``TARGETS``, ``TARGET_FILTER``) are checked at the end.

W is proportional to exp(lw) with lw ~ N(0, 1) i.i.d. (ESS/N about 0.37), fresh
in every repetition and shared by every implementation in it. Fast calls are
repeated until one sample lasts at least 2 ms; a cell is the time per call.

Part 2, one full filter step on the growth model ``ungm`` (Eq. 35 with 25,
process variance 10, observation variance 1), systematic resampling at every
step, one data set of 100 steps for every implementation:

(a) dtpf ``ParticleFilter`` without preprocessing (reference),
(b) dtpf with the in-process digital twin (``dtpf.scripts.inprocess.build``,
    ``RunConfig(preprocess=True)``: fixed PS 0.81),
(c) ``particles.SMC`` of a ``Bootstrap`` Feynman-Kac model of the same
    state-space model (:func:`particles_growth_model`), ESSrmin=1,
    ``resampling='systematic'``, ``store_history=False``, ``collect=[Moments()]``,
(d) a plain numpy loop with ``filterpy.monte_carlo.systematic_resample``.

Per-step time = (construction + run) / steps. Every implementation computes
the weighted mean at every step; its RMSE against the true path is printed,
as a check that all four filter the same model.

Method: implementations run interleaved, in a
new random order in every repetition, after an untimed warm-up at each N that
takes every numba JIT; cells are medians over repetitions, and ratios (xR) are
medians of per-repetition ratios against the reference of the same repetition.

Run from the repository root::

    python -m dtpf.scripts.bench.resampling                       # N = 1e3 .. 1e6, 2-4 minutes
    python -m dtpf.scripts.bench.resampling --quick               # smoke run, a few seconds
    python -m dtpf.scripts.bench.resampling --sizes 1e5 --repeats 5

particles and filterpy are optional (``pip install -e '.[bench]'``); their
rows read "not installed" without them.
"""
from __future__ import annotations

import argparse
import functools
import gc
import importlib
import importlib.metadata
import math
import os
import platform
import random
import resource
import statistics
import sys
import time
from typing import Callable

import numba
import numpy as np

from dtpf.entity import models, resampling
from dtpf.information import rules
from dtpf.information.select import kth_largest
from dtpf.messages.config import RunConfig
from dtpf.scripts.inprocess import build, simulate

SCHEMES = ("multinomial", "stratified", "systematic", "residual", "ssp", "killing")
#: The schemes filterpy.monte_carlo has (``<scheme>_resample``).
FILTERPY_SCHEMES = ("multinomial", "stratified", "systematic", "residual")
#: PS of the DT preprocessing, in part 1 and in (b).
PS = 0.81
#: Repetitions per N at the default sizes: part 1 (kernels) and part 2 (filter).
KERNEL_REPEATS = {1_000: 51, 10_000: 51, 100_000: 31, 1_000_000: 21}
FILTER_REPEATS = {1_000: 21, 10_000: 15, 100_000: 7, 1_000_000: 5}
#: Steps per filter run; (d) runs FILTERPY_STEPS_1E6 steps from N = 1e6 on.
STEPS = 100
STEPS_1E6 = 30
FILTERPY_STEPS_1E6 = 10
#: One kernel sample repeats the call until it lasts this long.
MIN_SAMPLE = 2e-3
#: From this N on, filterpy's kernels (Python loops) run in one repetition only.
FILTERPY_ONCE = 1_000_000
QUICK_SIZES = [1_000, 10_000]

Thunk = Callable[[], object]
#: perf_counter at import, for the progress lines.
STARTED = time.perf_counter()


# --- optional libraries -------------------------------------------------------

@functools.cache
def optional(name: str):
    """The module ``name``, or None when it is not installed."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


def version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


@functools.cache
def particles_growth_model(model: models.GrowthModel):
    """``model`` (Eq. 35, 36) as a particles state-space model; t = 0 is dtpf's k = 1.

    X_0 ~ N(prior_mean, prior_var); X_t = 0.5 X + c X / (1 + X^2) + 8 cos(1.2 t) + U,
    U ~ N(0, process_var); Y_t ~ N(X_t^2 / 20, observation_var).
    """
    from particles import distributions as dists
    from particles import state_space_models as ssm

    class Growth(ssm.StateSpaceModel):
        default_params = {"c": model.growth, "sigmaX": math.sqrt(model.process_var),
                          "sigmaY": math.sqrt(model.observation_var), "x0": model.prior_mean,
                          "sigma0": math.sqrt(model.prior_var)}

        def PX0(self):
            return dists.Normal(loc=self.x0, scale=self.sigma0)

        def PX(self, t, xp):
            return dists.Normal(loc=0.5 * xp + self.c * xp / (1.0 + xp ** 2) + 8.0 * np.cos(1.2 * t),
                                scale=self.sigmaX)

        def PY(self, t, xp, x):
            return dists.Normal(loc=x ** 2 / 20.0, scale=self.sigmaY)

    return Growth()


# --- part 1: kernels ----------------------------------------------------------

#: The floors, timed with the kernels: one pass over the weights, one gather of the particles by
#: sorted ancestors, N uniforms from the run's generator; all into preallocated arrays. DT
#: preprocessing's two: selecting W of Eq. 28 (the (k+1)-th largest weight, k = round(ESS), as
#: preprocess selects it: dtpf.information.select's radix select, below rules.SMALL_SET numba's
#: np.partition in compiled code) and reading each small particle's
#: partner (Eq. 29), N - k rows at random among the k large ones, in a compiled loop.
FLOORS = ("weight pass", "gather", "uniforms", "select", "partners")
#: The floor each dtpf kernel is bounded by (the times of the floors of a repetition are added).
BOUNDS = {
    "systematic": ("weight pass",),
    "stratified": ("weight pass", "uniforms"),
    "multinomial": ("weight pass", "uniforms"),
    "residual": ("weight pass", "uniforms"),
    "ssp": ("weight pass", "uniforms"),
    "killing": ("weight pass", "uniforms"),
    "systematic + gather": ("weight pass", "gather"),
    "preprocess": ("select", "partners"),
}
#: Targets: (row, measure, reference rows summed, limit, N).
TARGETS = [
    ("systematic", "weight pass", ("weight pass",), 2.0, 1_000_000),
    ("stratified", "weight pass", ("weight pass",), 2.0, 1_000_000),
    ("multinomial", "weight pass", ("weight pass",), 3.0, 1_000_000),
    ("residual", "weight pass", ("weight pass",), 3.0, 1_000_000),
    ("systematic + gather", "weight pass + gather", ("weight pass", "gather"), 1.5, 1_000_000),
    ("preprocess", "dtpf systematic", ("systematic",), 1.2, 1_000_000),
    ("preprocess", "dtpf systematic", ("systematic",), 2.0, 1_000),
]
#: Filter step: dtpf (a) / particles.SMC (c) at every N.
TARGET_FILTER = 0.5


def kernel_entries(with_filterpy: bool, threads: tuple[int, ...]) -> dict[tuple[str, str], Callable]:
    """(row, implementation) -> make(W, X, A, seed) -> thunk; make seeds and allocates, the thunk is timed.

    W: weights, X: particles (N, 1), A: sorted ancestors (for the gather floor). dtpf kernels write
    into buffers made once (``out=``) and take the weights as checked (``checked=True``), as the
    filter calls them; "dtpf, checking" is the public call that validates W and allocates.
    """
    prs, fmc = optional("particles.resampling"), optional("filterpy.monte_carlo")
    entries = {}

    def weight_pass(w, x, a, seed):
        out = np.empty_like(w)
        return lambda: np.cumsum(w, out=out)

    def gather(w, x, a, seed):
        out = np.empty_like(x)
        return lambda: np.take(x, a, axis=0, out=out)

    def uniforms(w, x, a, seed):
        rng, out = np.random.default_rng(seed), np.empty_like(w)
        return lambda: rng.random(w.size, out=out)

    def select(w, x, a, seed):
        k = large_count(w)
        if w.size < rules.SMALL_SET:  # as preprocess selects there: numba's np.partition, in compiled code
            return lambda: _partition_at(w, w.size - k - 1)
        return lambda: kth_largest(w, k + 1)

    def partners(w, x, a, seed):
        k = large_count(w)
        rows, at = x[:k].copy(), np.random.default_rng(seed).integers(0, k, w.size - k).astype(np.uint64)
        out = np.empty((at.size, x.shape[1]))
        return lambda: _read_rows(rows, at, out)

    entries["weight pass", "floor"] = weight_pass
    entries["gather", "floor"] = gather
    entries["uniforms", "floor"] = uniforms
    entries["select", "floor"] = select
    entries["partners", "floor"] = partners
    for scheme in SCHEMES:
        def ours(w, x, a, seed, f=resampling.RESAMPLERS[scheme]):
            rng, out = np.random.default_rng(seed), np.empty(w.size, dtype=np.int64)
            return lambda: f(w, rng, out=out, checked=True)

        def checking(w, x, a, seed, f=resampling.RESAMPLERS[scheme]):
            rng = np.random.default_rng(seed)
            return lambda: f(w, rng)
        entries[scheme, "dtpf"] = ours
        entries[scheme, "dtpf, checking"] = checking
        if prs is not None:
            def theirs(w, x, a, seed, f=getattr(prs, scheme)):
                np.random.seed(seed)
                return lambda: f(w)
            entries[scheme, "particles"] = theirs
        if fmc is not None and with_filterpy and scheme in FILTERPY_SCHEMES:
            def loop(w, x, a, seed, f=getattr(fmc, f"{scheme}_resample")):
                np.random.seed(seed)
                return lambda: f(w)
            entries[scheme, "filterpy"] = loop

    for t in threads:
        def systematic_gather(w, x, a, seed, t=t):
            rng, out, moved = np.random.default_rng(seed), np.empty(w.size, dtype=np.int64), np.empty_like(x)
            return lambda: resampling.gather(x, resampling.systematic(w, rng, out=out, checked=True), moved,
                                             threads=t)
        entries["systematic + gather", threads_label(t)] = systematic_gather
    if prs is not None:
        def their_gather(w, x, a, seed):
            np.random.seed(seed)
            return lambda: x[prs.systematic(w)]
        entries["systematic + gather", "particles"] = their_gather

    def preprocess(w, x, a, seed):
        rng = np.random.default_rng(seed)
        return lambda: rules.preprocess(x, w, PS, rng, checked=True)
    entries["preprocess", "dtpf"] = preprocess
    return entries


def large_count(weights: np.ndarray) -> int:
    """k = round(ESS), clipped to [1, N - 1]: the particles DT preprocessing counts as large (Eq. 25, 28)."""
    return min(max(round(1.0 / float(np.dot(weights, weights))), 1), weights.size - 1)


@numba.njit(cache=True, nogil=True)
def _partition_at(weights, rank):  # pragma: no cover - compiled
    return np.partition(weights, rank)[rank]


@numba.njit(cache=True, nogil=True)
def _read_rows(rows, at, out):  # pragma: no cover - compiled
    # The partners' floor: out[j] = rows[at[j]] for random at (unsigned: no check for negative indices).
    for j in range(at.shape[0]):
        out[j, 0] = rows[at[j], 0]


def threads_label(threads: int) -> str:
    return f"dtpf, {threads} thread{'s' if threads > 1 else ''}"


def test_weights(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """W proportional to exp(lw), lw ~ N(0, 1); particles X ~ N(0, 1), shape (N, 1); systematic ancestors of W."""
    lw = rng.standard_normal(n)
    w = np.exp(lw - lw.max())
    w /= w.sum()
    return w, rng.standard_normal((n, 1)), resampling.systematic(w, rng)


def calls_for(thunk: Thunk) -> int:
    """Calls per sample so that one sample lasts at least MIN_SAMPLE, measured after one untimed call."""
    thunk()  # JIT or cache load, first touch of memory
    calls = 1
    while True:
        start = time.perf_counter()
        for _ in range(calls):
            thunk()
        elapsed = time.perf_counter() - start
        if elapsed >= MIN_SAMPLE:
            return calls
        if elapsed >= MIN_SAMPLE / 8:
            return math.ceil(calls * MIN_SAMPLE / elapsed)
        calls *= 8


def time_calls(thunk: Thunk, calls: int) -> tuple[float, float]:
    """(seconds per call, minor page faults per call)."""
    gc.collect()
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    start = time.perf_counter()
    for _ in range(calls):
        thunk()
    seconds = time.perf_counter() - start
    return seconds / calls, (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / calls


def kernel_references(key: tuple[str, str]) -> dict[str, tuple[tuple[str, str], ...]]:
    """What the row ``key`` is divided by, per repetition: {label: rows whose times are added}."""
    row, impl = key
    if impl == "floor":
        return {}
    refs = {}
    if row == "preprocess":
        refs["floor"] = tuple((f, "floor") for f in BOUNDS[row])
        refs["dtpf systematic"] = (("systematic", "dtpf"),)
        refs["weight pass"] = (("weight pass", "floor"),)  # systematic itself moved: the fixed measure
    elif impl != "particles":
        refs["floor"] = tuple((f, "floor") for f in BOUNDS[row])
        refs["weight pass"] = (("weight pass", "floor"),)
        refs["particles"] = ((row, "particles"),)
    return refs


def bench_kernels(n: int, repeats: int, seed: int, order: random.Random, threads: tuple[int, ...]):
    """{key: [seconds per call]}, {(key, label): [ratio]}, {key: [faults per call]} at N."""
    data = np.random.default_rng([seed, n])
    entries = kernel_entries(with_filterpy=True, threads=threads)
    w, x, a = test_weights(n, data)
    calls = {}
    for key, make in entries.items():  # warm-up: numba JIT, first touch of memory, calls per sample
        if key[1] == "filterpy" and n >= FILTERPY_ONCE:
            calls[key] = 1
        else:
            calls[key] = calls_for(make(w, x, a, seed))
    times = {key: [] for key in entries}
    faults = {key: [] for key in entries}
    ratios: dict[tuple[tuple[str, str], str], list[float]] = {}
    for repeat in range(repeats):
        print(f"{time.perf_counter() - STARTED:.0f} s: kernels N={n} repeat {repeat + 1}/{repeats}", file=sys.stderr)
        w, x, a = test_weights(n, data)
        keys = [k for k in entries if not (k[1] == "filterpy" and n >= FILTERPY_ONCE and repeat > 0)]
        order.shuffle(keys)
        now = {}
        for key in keys:
            now[key], f = time_calls(entries[key](w, x, a, seed + repeat), calls[key])
            times[key].append(now[key])
            faults[key].append(f)
        for key in keys:
            for label, refs in kernel_references(key).items():
                if all(ref in now for ref in refs):
                    ratios.setdefault((key, label), []).append(now[key] / sum(now[ref] for ref in refs))
        for row, _, refs, _, _ in TARGETS:
            for impl in [k[1] for k in keys if k[0] == row and k[1].startswith("dtpf")]:
                rows = [(r, "floor") if r in FLOORS else (r, "dtpf") for r in refs]
                ratios.setdefault(((row, impl), "target"), []).append(
                    now[row, impl] / sum(now[r] for r in rows))
        floor = [(f, "floor") for f in BOUNDS["preprocess"]]
        if all(f in now for f in floor) and ("systematic", "dtpf") in now:  # what any preprocessing must pay
            ratios.setdefault((("preprocess", "floor"), "dtpf systematic"), []).append(
                sum(now[f] for f in floor) / now["systematic", "dtpf"])
    return times, ratios, faults


# --- part 2: one filter step --------------------------------------------------

def run_dtpf(config: RunConfig, observations: np.ndarray) -> list[float]:
    pf = build(config, observations)
    return [float(step.mean[0]) for step in pf]


def run_particles(model: models.GrowthModel, observations: np.ndarray, n: int, seed: int) -> list[float]:
    import particles
    from particles import state_space_models as ssm
    from particles.collectors import Moments

    np.random.seed(seed)
    fk = ssm.Bootstrap(ssm=particles_growth_model(model), data=observations[:, 0])
    smc = particles.SMC(fk=fk, N=n, resampling="systematic", ESSrmin=1.0, store_history=False,
                        collect=[Moments()])
    smc.run()
    if not all(smc.summaries.rs_flags[1:]):
        raise RuntimeError("particles.SMC skipped a resampling with ESSrmin=1")
    return [float(m["mean"]) for m in smc.summaries.moments]


def run_filterpy(model: models.GrowthModel, observations: np.ndarray, n: int, seed: int) -> list[float]:
    """Bootstrap filter as a plain numpy loop; resampling by filterpy (global np.random)."""
    from filterpy.monte_carlo import systematic_resample

    rng = np.random.default_rng(seed)
    np.random.seed(seed)
    sd_x, var_y = math.sqrt(model.process_var), model.observation_var
    x = model.prior_mean + math.sqrt(model.prior_var) * rng.standard_normal(n)
    means = []
    for k, z in enumerate(observations[:, 0], start=1):
        if k > 1:
            x = x[systematic_resample(w)]
            x = 0.5 * x + model.growth * x / (1.0 + x * x) + 8.0 * math.cos(1.2 * (k - 1)) \
                + sd_x * rng.standard_normal(n)
        residual = z - x * x / 20.0
        lw = -0.5 * residual * residual / var_y
        w = np.exp(lw - lw.max())
        w /= w.sum()
        means.append(float(w @ x))
    return means


FILTERS = {
    "a": "(a) dtpf ParticleFilter, no preprocessing (reference)",
    "b": f"(b) dtpf + in-process DT (preprocess=True, PS={PS} fixed)",
    "c": "(c) particles.SMC, Bootstrap, ESSrmin=1, systematic",
    "d": "(d) numpy loop + filterpy systematic_resample",
}


def filter_steps(n: int, steps: int | None) -> tuple[int, int]:
    """Steps of (a)-(c) and of (d) at N."""
    if steps is not None:
        return steps, steps
    if n >= 1_000_000:
        return STEPS_1E6, FILTERPY_STEPS_1E6
    return STEPS, STEPS


def bench_filter(n: int, repeats: int, steps: tuple[int, int], seed: int, order: random.Random,
                 truth: np.ndarray, observations: np.ndarray):
    """{mode: [s/step]}, {mode: [ratio to (a)]}, {mode: [RMSE]}, {mode: [faults/step]} at N."""
    model = models.get("ungm")
    runners = {
        "a": lambda t, s: run_dtpf(RunConfig(particles=n, steps=t, preprocess=False, seed=s, ps=PS),
                                   observations[:t]),
        "b": lambda t, s: run_dtpf(RunConfig(particles=n, steps=t, preprocess=True, seed=s, ps=PS),
                                   observations[:t]),
    }
    if optional("particles") is not None:
        runners["c"] = lambda t, s: run_particles(model, observations[:t], n, s)
    if optional("filterpy") is not None:
        runners["d"] = lambda t, s: run_filterpy(model, observations[:t], n, s)
    steps_of = {mode: steps[1] if mode == "d" else steps[0] for mode in runners}
    for mode, runner in runners.items():  # warm-up: numba JIT (ours and particles'), first touch
        runner(2, seed)
    per_step = {m: [] for m in runners}
    ratios = {m: [] for m in runners}
    rmse = {m: [] for m in runners}
    faults = {m: [] for m in runners}
    for repeat in range(repeats):
        modes = list(runners)
        order.shuffle(modes)
        now = {}
        for mode in modes:
            t = steps_of[mode]
            print(f"{time.perf_counter() - STARTED:.0f} s: filter N={n} repeat {repeat + 1}/{repeats} ({mode}, {t} steps)", file=sys.stderr)
            gc.collect()
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            start = time.perf_counter()
            means = runners[mode](t, seed + 1 + repeat)
            now[mode] = (time.perf_counter() - start) / t
            faults[mode].append((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / t)
            per_step[mode].append(now[mode])
            rmse[mode].append(float(np.sqrt(np.mean((np.asarray(means) - truth[:t, 0]) ** 2))))
        for mode in modes:
            ratios[mode].append(now[mode] / now["a"])
        if "c" in now:
            ratios["a/c"] = ratios.get("a/c", []) + [now["a"] / now["c"]]
    return per_step, ratios, rmse, faults, steps_of


# --- report -------------------------------------------------------------------

def parse_size(text: str) -> int:
    """'1e5' or '100000' -> 100000."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if value < 1 or value != int(value):
        raise argparse.ArgumentTypeError(f"N must be a positive integer, got {text!r}")
    return int(value)


def fmt_n(n: int) -> str:
    exponent = int(round(math.log10(n)))
    return f"1e{exponent}" if 10 ** exponent == n else str(n)


def fmt_ms(seconds: float) -> str:
    ms = 1e3 * seconds
    return f"{ms:.3g}" if ms < 100 else f"{ms:.0f}"


def cell(times: list[float], ratios: list[float], reference: bool, usual: int) -> str:
    if not times:
        return "-"
    text = f"{fmt_ms(statistics.median(times))} ms"
    if reference:
        text += " (ref)"
    elif ratios:
        text += f" (×{statistics.median(ratios):.2f})"
    if len(times) != usual:
        text += f" n={len(times)}"
    return text


def kernel_cell(times: list[float], ratios: dict, key: tuple[str, str], usual: int) -> str:
    """'3.05 ms (×0.95 floor, ×0.95 W, ×0.29 p)': the median time and the ratios of row ``key``."""
    if not times:
        return "-"
    short = {"floor": "floor", "weight pass": "W", "particles": "p", "dtpf systematic": "sys"}
    parts = [f"×{statistics.median(ratios[key, label]):.2f} {tag}" for label, tag in short.items()
             if ratios.get((key, label)) and (label != "weight pass" or kernel_references(key).get("floor") !=
                                              kernel_references(key)["weight pass"])]
    text = f"{fmt_ms(statistics.median(times))} ms" + (f" ({', '.join(parts)})" if parts else "")
    if len(times) != usual:
        text += f" n={len(times)}"
    return text


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def repeats_for(n: int, table: dict[int, int], override: int | None) -> int:
    if override is not None:
        return override
    nearest = min(table, key=lambda size: abs(math.log10(size) - math.log10(n)))
    return table[nearest]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m dtpf.scripts.bench.resampling",
        description="Resampling kernels (dtpf, particles, filterpy, DT preprocessing) and one full filter "
                    "step on the growth model (dtpf with and without the in-process twin, particles.SMC, a "
                    "numpy loop with filterpy), interleaved in shuffled order; prints Markdown tables of "
                    "medians and ratios, RMSE against the truth, and PASS/FAIL against the targets.",
        epilog="particles and filterpy are optional: pip install -e '.[bench]'. Progress goes to stderr. "
               "Exit code 1 when a target fails.")
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=None, metavar="N",
                        help="numbers of particles (default: 1e3 1e4 1e5 1e6; with --quick 1e3 1e4)")
    parser.add_argument("--repeats", type=int, default=None,
                        help="repetitions per N in both parts (default: kernels "
                             f"{', '.join(f'{r} at {fmt_n(n)}' for n, r in KERNEL_REPEATS.items())}; filter "
                             f"{', '.join(f'{r} at {fmt_n(n)}' for n, r in FILTER_REPEATS.items())})")
    parser.add_argument("--steps", type=int, default=None,
                        help=f"filter steps per run, every N (default: {STEPS}; {STEPS_1E6} from N = 1e6 on, "
                             f"{FILTERPY_STEPS_1E6} for (d))")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: N = 1e3 1e4 unless --sizes, 3 repetitions, 20 steps")
    parser.add_argument("--seed", type=int, default=0, help="seed of data, runs and order (default: %(default)s)")
    parser.add_argument("--kernels", action="store_true",
                        help="part 1 only (the kernels and their targets), no filter step: for iterating on a kernel")
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes = args.sizes or QUICK_SIZES
        args.repeats = args.repeats or 3
        args.steps = args.steps or 20
    sizes = args.sizes or sorted(KERNEL_REPEATS)
    if args.repeats is not None and args.repeats < 1:
        parser.error("--repeats must be at least 1")
    if args.steps is not None and not 2 <= args.steps <= STEPS:
        parser.error(f"--steps must be in 2..{STEPS}")

    # Import the optional libraries now, then move every object alive into the permanent
    # generation: the gc.collect() before each sample then costs microseconds, not 0.1 s.
    for name in ("particles.resampling", "particles.state_space_models", "particles.collectors",
                 "filterpy.monte_carlo"):
        optional(name)
    gc.collect()
    gc.freeze()
    # Parallel loops on threads that sleep when idle: OpenMP's spin-waiting workers would take the
    # second core from everything timed after a parallel call.
    numba.config.THREADING_LAYER = "workqueue"
    order = random.Random(args.seed)
    threads = tuple(sorted({1, numba.config.NUMBA_NUM_THREADS}))  # 1 core, and all of them
    load_before = os.getloadavg()
    start = time.perf_counter()
    kernels = {}
    for n in sizes:
        kernels[n] = bench_kernels(n, repeats_for(n, KERNEL_REPEATS, args.repeats), args.seed, order, threads)
    truth, observations = simulate(RunConfig(steps=STEPS, seed=args.seed))
    filters = {}
    for n in ([] if args.kernels else sizes):
        filters[n] = bench_filter(n, repeats_for(n, FILTER_REPEATS, args.repeats), filter_steps(n, args.steps),
                                  args.seed, order, truth, observations)
    total = time.perf_counter() - start

    command = "python -m dtpf.scripts.bench.resampling" + (" " + " ".join(sys.argv[1:]) if sys.argv[1:] else "")
    malloc = " ".join(f"{k}={v}" for k, v in os.environ.items() if k.startswith("MALLOC_")) or "default malloc"
    print(f"`{command}`\n\n{os.cpu_count()} CPUs ({cpu_name()}), Python {platform.python_version()}, "
          f"numpy {np.__version__}, numba {numba.__version__}, particles {version('particles')}, "
          f"filterpy {version('filterpy')}, {malloc}; {total:.0f} s in all; load average (1 min) "
          f"{load_before[0]:.2f} at the start, {os.getloadavg()[0]:.2f} at the end.\n")

    # Part 1 table.
    head = " | ".join(f"N={fmt_n(n)}" for n in sizes)
    print("## 1. Resampling kernels: weights -> N ancestors, beside their floors\n")
    print(f"| kernel | implementation | {head} |\n|---|---|{'---|' * len(sizes)}")
    labels = {"floor": "floor", "particles": "particles (numba)", "dtpf": "dtpf (numba, out=, checked=True)",
              "dtpf, checking": "dtpf (numba, checks W, allocates)", "filterpy": "filterpy (Python loop)"}
    floor_labels = {"weight pass": "`np.cumsum(W, out=)`", "gather": "`np.take(X, A, axis=0, out=)`",
                    "uniforms": "`rng.random(N, out=)`",
                    "select": "W of Eq. 28, the (k+1)-th largest weight, k = round(ESS), selected as `preprocess` does",
                    "partners": "N - k random rows of the k large (compiled loop)"}
    rows = [(f, "floor") for f in FLOORS]
    rows += [(s, impl) for s in SCHEMES for impl in ("particles", "dtpf", "dtpf, checking", "filterpy")
             if impl != "filterpy" or s in FILTERPY_SCHEMES]
    rows += [("systematic + gather", "particles")] + [("systematic + gather", threads_label(t)) for t in threads]
    rows += [("preprocess", "dtpf")]
    for key in rows:
        row, impl = key
        if row == "preprocess":
            label = f"dtpf: `rules.preprocess`, PS={PS}, X (N, 1), checked=True"
        elif row == "systematic + gather" and impl != "particles":
            label = f"{impl}: systematic (out=, checked=True), `resampling.gather(..., threads={impl[6]})`"
        elif impl == "floor":
            label = floor_labels[row]
        else:
            label = labels[impl]
        module = {"particles": "particles", "filterpy": "filterpy"}.get(impl)
        cells = []
        for n in sizes:
            times, ratios, _ = kernels[n]
            usual = repeats_for(n, KERNEL_REPEATS, args.repeats)
            if module and optional(module) is None:
                cells.append("not installed")
            else:
                cells.append(kernel_cell(times.get(key, []), ratios, key, usual))
        name = "DT preprocessing" if row == "preprocess" else row
        note = " †" if key == ("residual", "filterpy") else ""
        print(f"| {name} | {label}{note} | {' | '.join(cells)} |")
    print("\nCells: median ms per call over repetitions (n = "
          + ", ".join(f"{repeats_for(n, KERNEL_REPEATS, args.repeats)} at {fmt_n(n)}" for n in sizes)
          + "; other n shown). Ratios are medians of per-repetition ratios: ×floor against the floor that "
          "bounds the kernel (" + "; ".join(f"{row}: {' + '.join(fl)}" for row, fl in BOUNDS.items())
          + "), ×W against the weight pass alone, ×p against particles' same kernel; DT preprocessing "
          f"against dtpf's systematic. Calls repeated to at least {MIN_SAMPLE * 1e3:.0f} ms per sample. "
          f"filterpy at N >= {fmt_n(FILTERPY_ONCE)}: one repetition, one call.\n† filterpy's residual_resample "
          "is biased (`weights - num_copies` where `N*weights - num_copies` is meant; rlabbe/filterpy#290): "
          "timing only.")
    big = max(sizes)
    _, _, kfaults = kernels[big]
    print(f"Minor page faults per call at N={fmt_n(big)} (median): "
          + ", ".join(f"{s} {impl} {statistics.median(f):.0f}"
                      for (s, impl), f in kfaults.items() if f and statistics.median(f)) + ".")

    print("\nTargets:")
    failed = False
    for row, measure, _, limit, target_n in TARGETS:
        impls = [threads_label(t) for t in threads] if row == "systematic + gather" else ["dtpf"]
        for impl in impls:
            what = f"{row} ({impl}) / {measure}"
            ratios = kernels[target_n][1].get(((row, impl), "target")) if target_n in kernels else None
            if not ratios:
                print(f"- N = {fmt_n(target_n)}: {what} <= {limit:g}: not measured (N={fmt_n(target_n)} not run)")
                continue
            ratio = statistics.median(ratios)
            ok = ratio <= limit
            failed |= not ok and impl in ("dtpf", threads_label(1))  # what the filter runs
            print(f"- N = {fmt_n(target_n)}: {what} <= {limit:g}: ×{ratio:.2f} "
                  f"(per-repetition {min(ratios):.2f}-{max(ratios):.2f}), {'PASS' if ok else 'FAIL'}")
            floor = kernels[target_n][1].get((("preprocess", "floor"), "dtpf systematic"))
            if row == "preprocess" and floor:
                print(f"  - its floor, select + partners (no draws, no split, no output set) / dtpf systematic: "
                      f"×{statistics.median(floor):.2f} (per-repetition {min(floor):.2f}-{max(floor):.2f})")
    for n in ([] if args.kernels else sizes):
        ratios = filters[n][1].get("a/c")
        if not ratios:
            print(f"- N = {fmt_n(n)}: filter step dtpf (a) / particles.SMC (c) <= {TARGET_FILTER:g}: not measured")
            continue
        ratio = statistics.median(ratios)
        failed |= ratio > TARGET_FILTER
        print(f"- N = {fmt_n(n)}: filter step dtpf (a) / particles.SMC (c) <= {TARGET_FILTER:g}: ×{ratio:.2f} "
              f"(per-repetition {min(ratios):.2f}-{max(ratios):.2f}), "
              f"{'PASS' if ratio <= TARGET_FILTER else 'FAIL'}")

    if args.kernels:
        return 1 if failed else 0

    # Part 2 tables.
    print("\n## 2. One filter step, growth model `ungm`, systematic resampling every step\n")
    print(f"| implementation | {head} |\n|---|{'---|' * len(sizes)}")
    for mode, label in FILTERS.items():
        cells = []
        for n in sizes:
            per_step, ratios, _, _, steps_of = filters[n]
            if mode not in per_step:
                cells.append("not installed")
                continue
            text = cell(per_step[mode], ratios[mode], mode == "a", repeats_for(n, FILTER_REPEATS, args.repeats))
            if steps_of[mode] != STEPS:
                text += f", {steps_of[mode]} steps"
            cells.append(text)
        print(f"| {label} | {' | '.join(cells)} |")
    print("\nCells: median ms per step = (construction + run) / steps over repetitions (n = "
          + ", ".join(f"{repeats_for(n, FILTER_REPEATS, args.repeats)} at {fmt_n(n)}" for n in sizes)
          + f"), {STEPS} steps unless shown; (×R) the median of per-repetition ratios against (a). Each "
          "repetition runs every implementation with its own seed on the same observations.")
    print("\nSame model? RMSE of the posterior mean against the true path (median over repetitions, "
          "min-max):\n")
    print(f"| implementation | {head} |\n|---|{'---|' * len(sizes)}")
    for mode, label in FILTERS.items():
        cells = []
        for n in sizes:
            _, _, rmse, _, steps_of = filters[n]
            if mode not in rmse:
                cells.append("not installed")
                continue
            text = f"{statistics.median(rmse[mode]):.2f} ({min(rmse[mode]):.2f}-{max(rmse[mode]):.2f})"
            if steps_of[mode] != STEPS:
                text += f", {steps_of[mode]} steps"
            cells.append(text)
        print(f"| {label[:3]} | {' | '.join(cells)} |")
    _, _, _, ffaults, _ = filters[big]
    print(f"\nMinor page faults per step at N={fmt_n(big)} (median): "
          + ", ".join(f"{mode} {statistics.median(f):.0f}" for mode, f in ffaults.items()) + ".")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
