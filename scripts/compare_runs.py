"""The runs of ``dtpf compare``: each (variant, seed) filtered in one process, on worker processes.

A run is :func:`dtpf.scripts.inprocess.run` of its configuration; its figure is its task's metric
(:mod:`~dtpf.scripts.compare_metrics`), beside the figures every row keeps. Each worker
first runs every variant a few steps on a few particles (each model once over all its steps), so
numba's kernels and a model's lazily computed data are loaded before any run is timed, and ignores
Ctrl-C: the parent stops the workers and keeps what has finished::

    run_all(tasks, workers=2, warm=[config, ...], on_row=print)
"""
from __future__ import annotations

import math
import multiprocessing
import signal
from dataclasses import dataclass

from dtpf.entity import sources
from dtpf.messages.config import RunConfig
from dtpf.scripts.compare_csv import RunRow
from dtpf.scripts.compare_metrics import Metric, figures_of

__all__ = ["Task", "RunFailed", "run_task", "run_all", "warm_up"]

#: The warm-up of a worker: this many particles and steps of each variant.
WARM_PARTICLES, WARM_STEPS = 50, 3


@dataclass(frozen=True)
class Task:
    """One run to make: a variant's label, spec and settings, the run's configuration (with its seed), the
    metric it is judged by and the cell of the grid it belongs to ("" without a grid)."""

    label: str
    spec: str
    settings: str
    config: RunConfig
    metric: Metric
    cell: str = ""


class RunFailed(RuntimeError):
    """A run raised: which variant and seed, and what it said (one line)."""


@dataclass(frozen=True)
class _Failure:
    label: str
    seed: int
    message: str
    cell: str = ""


#: The models of this process by (scenario, model): loaded (and checked in the parent) once.
_MODELS: dict[tuple[str, str | None], object] = {}


def _model(config: RunConfig):
    key = (config.scenario, config.model)
    if key not in _MODELS:
        _MODELS[key] = sources.load_model(config, check=False)
    return _MODELS[key]


def run_task(task: Task) -> RunRow | _Failure:
    """The row of one run (a failure, not an exception, when the run raises: the parent names it)."""
    from dtpf.scripts.inprocess import run

    try:
        result = run(task.config, model=_model(task.config))
        value = task.metric.of(result)
    except Exception as error:  # a user's model or file may raise anything; the parent reports it
        message = " ".join(f"{type(error).__name__}: {error}".split())
        return _Failure(task.label, task.config.seed, message, task.cell)
    steps = len(result.steps)
    figures = figures_of(result)
    return RunRow(task.label, task.spec, task.settings, task.config.seed, task.metric.key, value,
                  figures["mean_ess"], steps, 1e3 * result.elapsed / steps if steps else math.nan, cell=task.cell,
                  distinct=figures["distinct"], preprocessed=figures["preprocessed"],
                  log_predictive=figures["log_predictive"])


def warm_up(configs: list[RunConfig]) -> None:
    """Run each configuration on a few particles and steps, the first of each model over all its steps: numba's
    kernels load, and so does what a model computes once per process when a step first needs it (the video's
    frame histograms). A configuration that raises is passed over: its runs will say what is wrong."""
    from dtpf.scripts.inprocess import run

    whole: set[tuple[str, str | None]] = set()
    for config in configs:
        first = (config.scenario, config.model) not in whole
        whole.add((config.scenario, config.model))
        small = dict(particles=min(config.particles, WARM_PARTICLES),
                     steps=config.steps if first else min(config.steps or WARM_STEPS, WARM_STEPS))
        try:
            run(config.model_copy(update=small), model=_model(config))
        except Exception:  # noqa: BLE001 - a worker that died here would be started again and again
            continue


def _start_worker(configs: list[RunConfig]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    warm_up(configs)


def run_all(tasks: list[Task], workers: int, warm: list[RunConfig], on_row) -> None:
    """Run every task, calling ``on_row(row)`` in this process as each ends; raises :class:`RunFailed` for a
    run that raised, after stopping the others. ``workers`` 1 runs them here; more, in worker processes
    (forkserver where there is one, else spawn), each warmed with ``warm`` first. A KeyboardInterrupt stops
    the workers at once; the rows given to ``on_row`` so far are all that finished."""
    if not tasks:
        return
    if workers <= 1:
        warm_up(warm)
        for task in tasks:
            on_row(_checked(run_task(task)))
        return
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    pool = multiprocessing.get_context(method).Pool(min(workers, len(tasks)), initializer=_start_worker,
                                                     initargs=(warm,))
    try:
        for outcome in pool.imap_unordered(run_task, tasks):
            on_row(_checked(outcome))
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()


def _checked(outcome: RunRow | _Failure) -> RunRow:
    if isinstance(outcome, _Failure):
        where = f"cell {outcome.cell!r}, " if outcome.cell else ""
        raise RunFailed(f"{where}variant {outcome.label!r}, seed {outcome.seed}: {outcome.message}")
    return outcome
