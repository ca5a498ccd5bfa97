"""Rehearsal: before the run, the twin filters simulated runs of its own model with every arm, and the arm
that estimated best becomes the choosing policy's base (``--choose-base rehearse``).

The choosing policy (:class:`dtpf.system.policy.ChoosePS`) decides from one run's observations. Two kinds of
gain escape that evidence: a gain made in the first steps, before there are observations to score (the
relative rule on a constant far from the prior's centre), and a gain too small against one run's luck to show
in its likelihood (the regularised kernel on ungm). The model itself can show both, when it can draw
observations: with the truth of a simulation the error of each arm's estimate is measured, not inferred.

1. R runs of T steps, (x_1:T, z_1:T) from ``model.simulate``, each from its own stream of one fixed seed
   (:data:`SEED`): the rehearsal depends on the model, N, T and the arms only, so the services, the in-process
   pipeline and ``dtpf verify`` reach the same base.
2. Each run is filtered by every arm at once: the copies of :class:`~dtpf.system.choose.ArmEvidence`
   (M = min(N, ``particles``) particles, common random numbers), started from a plain filter of M particles,
   which also stands in for the entity's set wherever a copy loses an observation.
3. Each arm's estimate at step k is the weighted mean of the set its filter reports (a DT arm's after its
   move, as the entity reports it); its error in a run is the squared error against the simulated truth,
   averaged over steps and state dimensions.
4. The runs come in looks: after 200 runs, 400, 800, ... up to as many as 16e6 particle-steps allow (at
   least 200, at most 1,600: 1,600 at M = 100 and T = 100, 200 at M = 1000). At each look every arm's paired
   difference to the default base (roughening) is a mean with its standard error. When some arm's difference
   lies below 0 by more than ``z`` standard errors (default 2.9 at every look: over four looks about what one
   look at 2.5, one-sided 0.6%, gives; at most 2.5% over four arms), the rehearsal stops, and of those arms
   the one with the lowest mean error becomes the base. An arm whose difference lies above 0 by
   more than one standard error is dropped (it would hardly ever pass); when none is left, or after the last
   look, roughening stays. The chooser then neither copies nor enters the dropped arms (plain excepted: its
   copy is the reference every score is against), which is what a rehearsal saves per step.

Cost, measured by ``python -m dtpf.scripts.bench.chooser_cost --where inprocess --rehearsal ungm drift+100
range-bearing``: 3.7 to 20 s at N = 100 and T = 100 (200 to 1,600 runs) and 5.4 to 13 s at N = 1000 (200 runs) on
2 cores, a look's runs shared among the process's cores by helper processes (:func:`_shared_runs`; 6 to 35 s and
9 to 25 s on one). Once per (model, N, T, arms) and dtpf's code on a machine: a rehearsal of a model that is a
dataclass (every built-in one) is kept in a file of :func:`cache_folder`, named by a digest of those inputs, of the
model's pickled fields and its module's source, of a rule's or move's file, and of the source of dtpf's layers, so
that a second launch of the same twin starts at once. A file that does not hold what its name promises (cut short,
edited, another format) is ignored and written again. Any other model is rehearsed once per process.

A model that cannot draw observations (``samples_observations`` False: the video, a twin of a real system
without a sensor model), or that is driven or fused from several sensors, cannot be rehearsed: :func:`why_not`
says why.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import inspect
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dtpf.entity import resampling
from dtpf.messages.names import ARMS as ARM_NAMES
from dtpf.messages.names import DEFAULT_CHOOSE_BASE
from dtpf.system.choose import ArmEvidence

__all__ = ["Rehearsal", "rehearse", "simulated_runs", "why_not", "most_runs", "looks", "cache_folder", "kept_on_disk",
           "SEED", "BUDGET", "FEWEST", "MOST", "STEPS", "Z"]

#: The root seed of every rehearsal's runs (independent of the run's seed: see the module docstring).
SEED = 20261205
#: A rehearsal runs at most this many particle-steps (M x T x runs) ...
BUDGET = 16_000_000
#: ... and at least FEWEST, at most MOST simulated runs.
FEWEST, MOST = 200, 1600
#: Steps per simulated run: the run's, at most this many.
STEPS = 100
#: Standard errors an arm's mean difference to the base must fall below 0 by, at every look (a constant boundary:
#: with four looks about the one-sided 0.6% per arm a single look at 2.5 has).
Z = 2.9
#: At a look, an arm whose mean difference to the base is above this many standard errors is dropped.
DROP = 1.0
#: An error above this (or not finite) counts as this: one lost run cannot make a mean infinite.
_LARGEST = 1e12
#: Rehearsals kept per process, by their inputs.
_KEPT = 16
_CACHE: dict[tuple, tuple[object, "Rehearsal"]] = {}
#: Whether the last :func:`rehearse` of this process found its rehearsal kept (in the process or on disk) rather
#: than making it.
last_kept = False
#: The format of a rehearsal's file; a file of another is written again.
FILE_FORMAT = 1
#: A rehearsal's file larger than this is not read (it holds a few hundred bytes).
_LARGEST_FILE = 65536


@dataclass(frozen=True)
class Rehearsal:
    """What a rehearsal measured and chose."""

    #: The arm that becomes the base.
    arm: str
    #: The base it was measured against (roughening).
    against: str
    runs: int
    steps: int
    #: M, the particles of each arm's filter.
    particles: int
    #: Each arm's mean error over the runs.
    errors: dict[str, float]
    #: Each arm's paired difference to ``against``: (mean, standard error), over the runs it took part in.
    differences: dict[str, tuple[float, float]]
    #: The arms dropped at a look, their difference clearly above 0.
    dropped: tuple[str, ...] = ()
    #: The most runs the rehearsal would have made.
    most: int = 0

    def summary(self) -> str:
        """One line: the chosen arm and each arm's difference to the base, with 95% intervals."""
        parts = ", ".join(f"{a} {m:+.3g} ± {1.96 * se:.2g}" for a, (m, se) in self.differences.items()
                          if a != self.against)
        return (f"rehearsal over {self.runs} simulated runs of {self.steps} steps at M = {self.particles}: "
                f"error against {self.against} {parts}; base {self.arm}")


def why_not(model) -> str | None:
    """Why ``model`` cannot be rehearsed, or None when it can."""
    name = getattr(model, "name", type(model).__name__)
    if not getattr(model, "samples_observations", False):
        return f"model {name!r} cannot draw observations (no sample_observation)"
    if getattr(model, "controls", ()) or getattr(model, "sensors", None):
        return f"model {name!r} is driven or has several sensors; a rehearsal simulates neither"
    return None


def most_runs(particles: int, steps: int) -> int:
    """The most simulated runs of a rehearsal at M particles and T steps: :data:`BUDGET` particle-steps, at least
    :data:`FEWEST` and at most :data:`MOST` runs."""
    return int(min(MOST, max(FEWEST, BUDGET // max(1, int(particles) * int(steps)))))


def looks(runs: int) -> list[int]:
    """The numbers of runs after which a rehearsal of at most ``runs`` looks: FEWEST, twice that, ..., ``runs``."""
    out, n = [], min(FEWEST, int(runs))
    while n < runs:
        out.append(n)
        n *= 2
    return [*out, int(runs)]


def rehearse(model, arms, *, n: int, steps: int | None, runs: int | None = None, threshold_rule="neff",
             move: str = "none", particles: int = 1000, z: float | None = None, seed: int = SEED) -> Rehearsal:
    """Rehearse ``arms`` on simulated runs of ``model`` and choose the base (the module docstring).

    ``steps``: the run's (None: a run without end); each simulated run has min(steps, :data:`STEPS`).
    ``runs``: the most runs (default :func:`most_runs`); ``z``: default :data:`Z`. The same inputs in one process
    give the same object, computed once (equal built-in models count as the same: a fleet's twins of one
    scenario, N and T share one rehearsal).
    """
    reason = why_not(model)
    if reason is not None:
        raise ValueError(f"choose_base rehearse: {reason}; name a base arm instead")
    length = STEPS if steps is None else max(1, min(int(steps), STEPS))
    m = max(1, min(int(n), int(particles)))
    runs = most_runs(m, length) if runs is None else int(runs)
    z = Z if z is None else float(z)
    if runs < 2:
        raise ValueError(f"a rehearsal needs at least 2 runs, got {runs!r}")
    key = (_identity(model), tuple(arms), int(n), length, runs, tuple(looks(runs)), DROP, threshold_rule, move, m, z,
           int(seed))
    global last_kept
    last_kept = True
    kept = _CACHE.get(key)
    if kept is not None and _same(kept[0], model):
        return kept[1]
    file = _file_of(model, key)
    result = _read(file) if file is not None else None
    if result is not None:
        _keep(key, model, result)
        return result
    last_kept = False
    settings = dict(n=int(n), m=m, steps=length, threshold_rule=threshold_rule, move=move, seed=int(seed))
    active = tuple(dict.fromkeys(arms))
    errors: dict[str, list[float]] = {}
    differences: dict[str, tuple[float, float]] = {}
    against, chosen, done, dropped = None, None, 0, []
    for look in looks(runs):
        for run in _shared_runs(model, active, range(done, look), settings):
            for name, error in run.items():
                errors.setdefault(name, []).append(error)
        done = look
        if against is None:
            against = DEFAULT_CHOOSE_BASE if DEFAULT_CHOOSE_BASE in errors else "plain"
        base = np.array(errors[against])
        candidates = [a for a in active if a != against]
        for name in (*candidates, against):
            d = np.array(errors[name]) - base
            differences[name] = (float(d.mean()), float(d.std(ddof=1) / math.sqrt(d.size)))
        passed = [a for a in candidates if differences[a][0] < -z * differences[a][1]]
        if passed:
            chosen = min(passed, key=lambda a: np.mean(errors[a]))
            break
        clear = [a for a in candidates if differences[a][0] > DROP * differences[a][1]]
        dropped += clear
        active = tuple(a for a in active if a not in clear)
        if not [a for a in active if a != against]:
            break
    result = Rehearsal(chosen or against, against, done, length, m,
                       {a: float(np.mean(e)) for a, e in errors.items() if a in differences},
                       {a: differences[a] for a in errors if a in differences}, tuple(dropped), runs)
    _keep(key, model, result)
    if file is not None:
        _write(file, result)
    return result


def _keep(key: tuple, model, result: Rehearsal) -> None:
    if len(_CACHE) >= _KEPT:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = (model, result)


def cache_folder() -> Path:
    """Where rehearsals are kept between processes: ``$XDG_CACHE_HOME/dtpf/rehearsals`` (default
    ``~/.cache/dtpf/rehearsals``)."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "dtpf" / "rehearsals"


@functools.lru_cache(maxsize=1)
def _code_digest() -> str:
    """A digest of the source a rehearsal runs (every .py file of dtpf's entity, information, system and messages):
    a rehearsal kept by other code is not used."""
    root = Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    paths = [path for folder in ("entity", "information", "system", "messages") for path in (root / folder).rglob("*.py")]
    for path in sorted(paths):
        if "__pycache__" in path.parts:
            continue
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def kept_on_disk(model) -> bool:
    """Whether a rehearsal of ``model`` is kept in :func:`cache_folder` (a dataclass that pickles), so that another
    process of the twin reads it rather than making it again."""
    import pickle

    if not dataclasses.is_dataclass(model):
        return False
    try:
        pickle.dumps(model, protocol=4)
    except Exception:  # noqa: BLE001 - any object a model holds may refuse pickling, in any way
        return False
    return True


def _file_of(model, key: tuple) -> Path | None:
    """The file of a rehearsal of ``model`` with the inputs ``key``, or None when it is not kept on disk (a model
    that is not a dataclass or does not pickle, a rule or move given as an object, a model whose module's source
    cannot be read). The model counts by its pickled fields (every element of an array, where its repr would
    summarise) and its module's source; a rule or move named by a file, by that file's bytes too."""
    import pickle

    if not dataclasses.is_dataclass(model) or not all(isinstance(part, (str, int, float, tuple)) for part in key[1:]):
        return None
    try:
        parts = [FILE_FORMAT, _code_digest(), hashlib.sha256(pickle.dumps(model, protocol=4)).hexdigest(),
                 hashlib.sha256(Path(inspect.getsourcefile(type(model)) or "").read_bytes()).hexdigest(),
                 *(_file_digest(part) for part in key[1:] if isinstance(part, str)), list(key)]
        text = json.dumps(parts, default=str)
    except Exception:  # noqa: BLE001 - whatever does not pickle or read is not kept on disk
        return None
    return cache_folder() / (hashlib.sha256(text.encode()).hexdigest()[:32] + ".json")


def _file_digest(reference: str) -> str:
    """The digest of the file a rule or move reference names (``path/to/file.py:NAME``), or "" for a name."""
    from dtpf.messages.references import is_path, resolved_path

    source = reference.rsplit(":", 1)[0]
    if ":" not in reference or not is_path(source):
        return ""
    return hashlib.sha256(resolved_path(source).read_bytes()).hexdigest()


def _read(file: Path) -> Rehearsal | None:
    """The rehearsal kept in ``file``, or None when there is none or the file does not hold one (then it is
    written again)."""
    try:
        if not file.is_file() or file.stat().st_size > _LARGEST_FILE:
            return None
        data = json.loads(file.read_bytes())
        if not isinstance(data, dict) or data.get("format") != FILE_FORMAT:
            raise ValueError("another format")
        return _rehearsal_of(data["rehearsal"])
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as error:
        logging.getLogger(__name__).warning("rehearsal file %s not used (%s); rehearsing again", file.name, error)
        return None


def _rehearsal_of(value) -> Rehearsal:
    """A Rehearsal from its JSON form; ValueError or TypeError when any field is missing or of the wrong kind."""
    if not isinstance(value, dict):
        raise TypeError("not an object")
    ints = {name: value[name] for name in ("runs", "steps", "particles", "most")}
    if not all(type(v) is int and v >= 0 for v in ints.values()):
        raise ValueError("runs, steps, particles and most must be whole numbers")
    arm, against = value["arm"], value["against"]
    errors, differences, dropped = value["errors"], value["differences"], value["dropped"]
    if not (isinstance(arm, str) and isinstance(against, str) and isinstance(errors, dict)
            and isinstance(differences, dict) and isinstance(dropped, list)):
        raise TypeError("arm, against, errors, differences or dropped of the wrong kind")
    errors = {str(a): float(e) for a, e in errors.items()}
    pairs = {}
    for a, pair in differences.items():
        if not (isinstance(pair, list) and len(pair) == 2):
            raise ValueError(f"difference of {a!r} is not a pair")
        pairs[str(a)] = (float(pair[0]), float(pair[1]))
    names = {arm, against, *map(str, dropped)}
    if not names <= set(errors) | set(dropped) or arm not in errors:
        raise ValueError("arms that were not rehearsed")
    unknown = sorted((names | set(errors) | set(pairs)) - set(ARM_NAMES))
    if unknown:
        raise ValueError(f"unknown arm {unknown[0]!r}")
    return Rehearsal(arm, against, errors=errors, differences=pairs, dropped=tuple(map(str, dropped)), **ints)


def _write(file: Path, result: Rehearsal) -> None:
    """Keep ``result`` in ``file`` (written whole or not at all); a folder that cannot be written is logged."""
    data = {"format": FILE_FORMAT, "rehearsal": {**dataclasses.asdict(result), "dropped": list(result.dropped),
                                                 "differences": {a: list(p) for a, p in result.differences.items()}}}
    part = file.with_name(f"{file.stem}.{os.getpid()}.part")
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        part.write_text(json.dumps(data, allow_nan=True))
        os.replace(part, file)
    except OSError as error:
        logging.getLogger(__name__).warning("rehearsal not kept in %s: %s", file.parent, error)
        if part.parent.is_dir():
            part.unlink(missing_ok=True)


def _identity(model) -> tuple:
    """What tells one model from another for the cache: a dataclass (every built-in model) by its class and
    fields, so that equal models (a fleet's twins of one scenario) share a rehearsal; any other by the object."""
    if dataclasses.is_dataclass(model):
        return (type(model).__module__, type(model).__qualname__, repr(model))
    return ("object", id(model))


def _same(kept, model) -> bool:
    """Whether ``model`` is the model a kept rehearsal was made for: the same object, or an equal dataclass."""
    if kept is model:
        return True
    try:
        return type(kept) is type(model) and dataclasses.is_dataclass(model) and bool(kept == model)
    except (TypeError, ValueError):  # fields whose comparison has no single truth value (arrays)
        return False


def simulated_runs(model, arms, runs, *, n: int, m: int, steps: int, threshold_rule, move: str,
                   seed: int) -> list[dict[str, float]]:
    """Each arm's error on each of the simulated runs numbered ``runs``, run i from the i-th stream spawned
    from ``seed`` (the same numbers in any process, in any order)."""
    return [_one_run(model, arms, n=n, m=m, steps=steps, threshold_rule=threshold_rule, move=move,
                     rng=np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=(int(i),)))))
            for i in runs]


#: Particle-steps of one look (runs x M x T x arms) from which a rehearsal shares the runs among the cores of its
#: process (helper processes start in about a second; below this the look takes about as long on one).
SHARED_WORK = 5_000_000


def _shared_runs(model, arms, runs: range, settings: dict) -> list[dict[str, float]]:
    """:func:`simulated_runs` of ``runs``, shared among the process's cores (:func:`dtpf.entity.cores.threads`)
    when the look is large (:data:`SHARED_WORK`): helper processes take the later runs, this one the first; a
    helper that fails (a model that does not pickle, or cannot be imported in another process) has its runs
    made here. The numbers are those of one process."""
    from dtpf.entity import cores

    work = len(runs) * settings["m"] * settings["steps"] * len(arms)
    helpers = min(cores.threads(), len(runs)) - 1 if work >= SHARED_WORK else 0
    if helpers < 1:
        return simulated_runs(model, arms, runs, **settings)
    parts = np.array_split(np.arange(runs.start, runs.stop), helpers + 1)
    started = [_start_helper(model, arms, part, settings) for part in parts[1:]]
    out = simulated_runs(model, arms, parts[0].tolist(), **settings)
    for part, helper in zip(parts[1:], started):
        result = _finish_helper(helper, len(part))
        out += result if result is not None else simulated_runs(model, arms, part.tolist(), **settings)
    return out


def _start_helper(model, arms, part, settings: dict):
    """A helper process given its task, or None when the task does not pickle."""
    import pickle
    import subprocess
    import sys
    import tempfile

    # A user's files (a model, move or rule given as path/to/file.py:NAME) are imported by the helper first, under
    # the module names they have here, so that their objects unpickle there.
    files = [module.__file__ for name, module in list(sys.modules.items())
             if name.startswith("_dtpf_model_") and getattr(module, "__file__", None)]
    try:
        payload = pickle.dumps({"model": model, "arms": tuple(arms), "runs": part.tolist(), "settings": settings})
        task = pickle.dumps({"files": files, "payload": payload})
    except Exception as error:  # noqa: BLE001 - any object a model holds may refuse pickling, in any way
        _say_once(f"the model does not pickle ({type(error).__name__}); the rehearsal runs on one core")
        return None
    files = [tempfile.TemporaryFile() for _ in range(3)]
    files[0].write(task)
    files[0].seek(0)
    try:
        process = subprocess.Popen([sys.executable, "-P", "-m", "dtpf.system._rehearse_worker"],
                                   stdin=files[0], stdout=files[1], stderr=files[2])
    except OSError as error:
        _say_once(f"no helper process ({error}); the rehearsal runs on one core")
        return None
    return process, files


def _finish_helper(helper, count: int) -> list[dict[str, float]] | None:
    """The errors a helper wrote, or None (said once) when it failed or wrote something else."""
    import pickle

    if helper is None:
        return None
    process, (task, out, err) = helper
    try:
        code = process.wait()
        out.seek(0)
        err.seek(0)
        if code == 0:
            result = pickle.load(out)
            if isinstance(result, list) and len(result) == count and all(isinstance(r, dict) for r in result):
                return result
        why = err.read()[-300:].decode(errors="replace").strip().splitlines()
        _say_once(f"a helper process failed ({why[-1] if why else f'exit code {code}'}); its runs are made here")
        return None
    except Exception as error:  # noqa: BLE001 - whatever the helper wrote, the runs are made here
        _say_once(f"a helper process's answer was unreadable ({type(error).__name__}); its runs are made here")
        return None
    finally:
        for file in (task, out, err):
            file.close()


_HELPER_SAID: set[str] = set()


def _say_once(text: str) -> None:
    if text not in _HELPER_SAID:
        _HELPER_SAID.add(text)
        logging.getLogger(__name__).warning("rehearsal: %s", text)


def _one_run(model, arms, *, n: int, m: int, steps: int, threshold_rule, move: str,
             rng: np.random.Generator) -> dict[str, float]:
    """Each arm's error on one simulated run: mean over steps and dimensions of (estimate - truth)^2."""
    truth, observations = model.simulate(steps, rng)
    truth = np.asarray(truth, dtype=np.float64).reshape(steps, -1)
    copies = ArmEvidence(model, arms, n=n, threshold_rule=threshold_rule, particles=m, window=1, move=move)
    copies.estimates = {}
    estimates = {name: np.empty_like(truth) for name in copies.names}
    particles = np.asarray(model.initial_particles(m, rng), dtype=np.float64).reshape(m, -1)
    weights = np.full(m, 1.0 / m)
    for k in range(1, steps + 1):
        z = np.asarray(observations[k - 1], dtype=np.float64).reshape(-1)
        if k > 1:   # the plain filter the copies start from: systematic resampling, then the state equation
            ancestors = resampling.systematic(weights, rng)
            particles = np.asarray(model.propagate(particles[ancestors], k, rng), dtype=np.float64).reshape(m, -1)
        log_w = np.asarray(model.log_likelihood(particles, z, k), dtype=np.float64).reshape(-1)
        top = np.max(log_w)
        if np.isfinite(top):
            weights = np.exp(log_w - top)
            weights /= weights.sum()
        else:       # every particle lost the observation: the set keeps equal weights
            weights = np.full(m, 1.0 / m)
        copies.observe(k, particles, weights, z, rng)
        for name in copies.names:
            estimates[name][k - 1] = copies.estimates[name]
    out = {}
    for name, estimate in estimates.items():
        error = float(np.mean((estimate - truth) ** 2))
        out[name] = error if math.isfinite(error) and error < _LARGEST else _LARGEST
    return out
