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

Cost, measured by ``python -m dtpf.scripts.bench.chooser_cost --rehearsal ungm drift+100 range-bearing``:
20-44 ms a simulated run of 100 steps at N = 100 and 46-123 ms at N = 1000 (one core), so 6 to 35 s at N = 100
and T = 100 (200 to 1,600 runs) and 9 to 25 s at N = 1000 (200 runs); once per (model, N, T, arms) in a process.
A model that cannot draw observations (``samples_observations`` False: the video, a twin of a real system
without a sensor model), or that is driven or fused from several sensors, cannot be rehearsed: :func:`why_not`
says why.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from dtpf.entity import resampling
from dtpf.messages.names import DEFAULT_CHOOSE_BASE
from dtpf.system.choose import ArmEvidence

__all__ = ["Rehearsal", "rehearse", "why_not", "most_runs", "looks", "SEED", "BUDGET", "FEWEST", "MOST", "STEPS", "Z"]

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
    key = (_identity(model), tuple(arms), int(n), length, runs, threshold_rule, move, m, z, int(seed))
    kept = _CACHE.get(key)
    if kept is not None and _same(kept[0], model):
        return kept[1]
    streams = np.random.SeedSequence(int(seed)).spawn(runs)
    active = tuple(dict.fromkeys(arms))
    errors: dict[str, list[float]] = {}
    differences: dict[str, tuple[float, float]] = {}
    against, chosen, done, dropped = None, None, 0, []
    for look in looks(runs):
        for i in range(done, look):
            run = _one_run(model, active, n=int(n), m=m, steps=length, threshold_rule=threshold_rule, move=move,
                           rng=np.random.Generator(np.random.PCG64(streams[i])))
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
    if len(_CACHE) >= _KEPT:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = (model, result)
    return result


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
