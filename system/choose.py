"""Evidence per arm from the real observations: which move's filter predicts them best?

The choosing policy (``--policy choose``, :class:`dtpf.system.policy.ChoosePS`)
puts one of several moves in force (the arms, :data:`dtpf.information.layer.ARMS`):
plain resampling, DT preprocessing with the relative or the paper's rule,
roughening, the regularised filter's kernel. :class:`ArmEvidence` scores them
on the real observations, without truth and without ``sample_observation``:

1. At the first step k0 it copies the entity's weighted set as the system
   layer received it: one copy per arm, M = min(N, ``particles``) particles.
2. Every step k, each copy makes its arm's move on its weighted set of k and
   is resampled and propagated to k + 1: the DT arms preprocess (Eq. 28-30)
   before resampling, the jitters move after it (with the entity's N in
   their bandwidth). Common random numbers: the same uniform points resample
   every copy; the two DT arms draw their partners, r and u from the same
   generator state; the two jitters the same standard normals; every copy
   is propagated with the same numbers.
3. At k + 1 the real z_(k+1) weights each copy; its predictive
   log-likelihood log mean_j p(z_(k+1) | x_j) scores the arm, and the
   difference to the plain copy, clipped to +-50 nats, is arm a's d_a(k).
   A second score looks at the copy's point estimate alone: the
   log-likelihood log p(z_(k+1) | mean_j x_j) of its predicted mean; its
   difference to the plain copy's, clipped at +50 nats only (it can only
   keep an arm out, so a mean far off counts in full), is e_a(k).

The first score is a proper score of the copy's whole predictive
distribution; it favours a cloud spread wide enough to hold the truth over
one collapsed beside it, even when the wide cloud's mean is far worse than
the collapsed one's (the paper's rule on a drifting constant far from the
origin: its copy predicts every observation better than plain, its mean
errs a hundred times more). The second sees the estimate the user reads;
the choosing policy enters an arm only when both favour it.

Each copy is thus a filter of M particles running its arm at every step, a
counterfactual of the entity's: a move whose benefit builds up over many
steps (diversity kept through a collapse) shows in its copy's scores, which a
one-step comparison from the entity's own set cannot see. The sum of the last
W of an arm's differences is a windowed prequential log Bayes factor of that
arm's filter against the plain one (Dawid 1984); two arms' sums compare them
with each other (up to the clipping). A copy whose particles all lose the
observation (log-likelihood -inf everywhere) is copied again from the
entity's set of that step. Every random number comes from the generator
passed (the system layer's stream of step k).

Cost: the copies are held as one (A, M, d) array. Each step scores all of them with one
``log_likelihood`` call over the A x M particles and one over the A means, and propagates
them with one ``propagate`` call, every copy with the same noise (a model's
``propagation_noise``, which ``propagate`` takes instead of drawing; a model without it
gets one call per copy from the same generator state). The model is vectorised over
particles, so each copy's numbers are those one call per copy gave (tests/test_choose_cost.py
holds them to the per-arm calls): the decisions, and any log a chooser recorded, do not
change. The arms' moves stay one call each (the information layer's rules, the
entity's jitters), the same code the layers run when the arm is in force.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from operator import itemgetter

import numpy as np

from dtpf.entity import jitter as jitters
from dtpf.entity import resampling
from dtpf.entity.models import StateSpaceModel
from dtpf.information import rules
from dtpf.information.layer import ARMS, Arm, arms_for
from dtpf.messages.names import OWN_ARM

__all__ = ["ArmEvidence", "CLIP", "point_log_likelihood"]

#: Largest |difference| of one step (nats): one wild observation cannot decide a window.
CLIP = 50.0
#: Lowest point difference of one step (nats): the point evidence is clipped at +CLIP only, so that a copy
#: whose mean is sometimes far off cannot hide it behind steps where it was close (it only ever vetoes).
POINT_FLOOR = 1e9


def point_log_likelihood(model: StateSpaceModel, particles: np.ndarray, observation: np.ndarray, k: int) -> float:
    """log p(z_k | mean_j x_j): the observation's log-likelihood at the particles' mean (-inf when not finite)."""
    mean = np.mean(particles, axis=0, keepdims=True)
    if not np.isfinite(mean).all():
        return -np.inf
    value = float(np.asarray(model.log_likelihood(mean, observation, k), dtype=np.float64).reshape(-1)[0])
    return value if np.isfinite(value) else -np.inf


def _difference(arm: float, plain: float, lowest: float = -CLIP) -> float:
    """arm - plain in nats, clipped to [``lowest``, CLIP]; -inf against -inf is 0."""
    if not math.isfinite(arm) and not math.isfinite(plain):
        return 0.0
    if not math.isfinite(plain):
        return CLIP
    if not math.isfinite(arm):
        return lowest
    return float(min(max(arm - plain, lowest), CLIP))


class ArmEvidence:
    """The running evidence of each arm against plain resampling for one twin (see the module docstring).

    Parameters
    ----------
    model : StateSpaceModel
    arms : sequence of str
        The arms scored (names of :data:`dtpf.information.layer.ARMS`); "plain" is always one.
    n : int
        The entity's N (the jitters' bandwidth).
    threshold_rule :
        W of Eq. 28 for the DT arms (the run's).
    particles : int
        M, at most this many particles per arm.
    window : int
        W, the differences kept and summed per arm.
    move : str
        The run's own move after resampling: a user's makes the arm "own" (:func:`~dtpf.information.layer.arms_for`).
    """

    def __init__(self, model: StateSpaceModel, arms=tuple(ARMS), *, n: int, threshold_rule="neff",
                 particles: int = 1000, window: int = 20, move: str = "none"):
        if int(window) < 1:
            raise ValueError(f"window must be at least 1, got {window!r}")
        table = arms_for(move)
        unknown = [a for a in arms if a not in table]
        if unknown:
            raise ValueError(f"unknown arm {unknown[0]!r}; expected some of {', '.join(table)}")
        self.model = model
        #: The run's own move after resampling, which the arm "own" makes.
        self.move = move
        self.arms: tuple[Arm, ...] = tuple(table[a] for a in dict.fromkeys(("plain", *arms)))
        self._names = tuple(arm.name for arm in self.arms)
        self.n = int(n)
        self.threshold_rule = threshold_rule
        self.particles = int(particles)
        self.differences: deque[dict[str, float]] = deque(maxlen=int(window))
        #: e_a(k): the copies' predicted means scored against plain's (see the module docstring).
        self.point_differences: deque[dict[str, float]] = deque(maxlen=int(window))
        #: Propagate all copies in one call when the model draws its noise on its own (False: one call per copy,
        #: the same numbers; the reference the batched call is tested against).
        self.batched = True
        #: Each arm's estimate of the last step it moved, the weighted mean of the set its filter reports (a
        #: DT arm's after its move), when set to a dict (:mod:`dtpf.system.rehearse` sets it); None: not kept.
        self.estimates: dict[str, np.ndarray] | None = None
        #: (k + 1, the (A, M, d) copies propagated to k + 1, in the order of :attr:`arms`)
        self._copies: tuple[int, np.ndarray] | None = None
        self._z = np.empty(0)

    @property
    def names(self) -> tuple[str, ...]:
        return self._names

    @property
    def window(self) -> int:
        return self.differences.maxlen

    @property
    def copies(self) -> dict[str, np.ndarray]:
        """Each arm's copy, (M, d) particles propagated to the next step (views of one array; empty before
        the first step)."""
        if self._copies is None:
            return {}
        return dict(zip(self.names, self._copies[1]))

    @property
    def steps(self) -> int:
        """How many differences each arm's sum holds (at most W)."""
        return len(self.differences)

    def totals(self) -> dict[str, float]:
        """Each arm's summed differences against plain (nats; plain's is 0)."""
        return {name: float(sum(map(itemgetter(name), self.differences))) for name in self.names}

    def point_totals(self) -> dict[str, float]:
        """Each arm's summed differences of its predicted mean's log-likelihood against plain's (nats)."""
        return {name: float(sum(map(itemgetter(name), self.point_differences))) for name in self.names}

    def observe(self, step: int, particles: np.ndarray, weights: np.ndarray, observation: np.ndarray,
                 rng: np.random.Generator) -> dict[str, float] | None:
        """Take the set of ``step`` as the system layer received it and its observation z_step.

        Returns the new differences d_a(step - 1) (scored with z_step), or None when the copies had
        not reached ``step`` (the first step, or after a gap). Call once per step, in order.
        """
        k = int(step)
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
        self._z = z
        scored = None
        copies, self._copies = self._copies, None
        weighted: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        if copies is not None and copies[0] == k:
            scored = self._score(k, copies[1], z, weighted)
        for name in self.names:  # a copy that lost the observation (or the first step): the entity's set
            if name not in weighted:
                weighted[name] = (particles, weights)
        self._copies = (k + 1, self._advance(k, weighted, rng))
        return scored

    def _score(self, k: int, copies: np.ndarray, z: np.ndarray,
               weighted: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
        """Score the (A, M, d) copies of step k with z_k: append d_a(k - 1) and e_a(k - 1), put each copy that
        kept the observation into ``weighted`` as (particles, normalised weights), and return d_a(k - 1).

        One likelihood call over all A x M particles and one over the A means (the model is vectorised over
        particles, so each copy's numbers are those of a call on its own); the sums run per copy, as
        :func:`~dtpf.system.evidence.predictive_log_likelihood` and :func:`point_log_likelihood` do.
        """
        model, names = self.model, self.names
        a, m, d = copies.shape
        log_w = np.asarray(model.log_likelihood(copies.reshape(a * m, d), z, k), dtype=np.float64).reshape(a, m)
        top = log_w.max(axis=1)
        kept = np.isfinite(top)
        every = bool(kept.all())
        w = np.exp(log_w - top[:, None]) if every else np.exp(log_w[kept] - top[kept, None])
        total = w.sum(axis=1)
        values = top + np.log(total / m) if every else np.full(a, -np.inf)
        if not every:
            values[kept] = top[kept] + np.log(total / m)
        w /= total[:, None]
        for row, i in enumerate(range(a) if every else np.flatnonzero(kept)):
            weighted[names[i]] = (copies[i], w[row])
        means = np.add.reduce(copies, axis=1) / m        # np.mean's numbers, without its wrapper
        finite = np.isfinite(means).all(axis=1)
        if finite.all():
            points = np.asarray(model.log_likelihood(means, z, k), dtype=np.float64).reshape(-1)
        else:
            points = np.full(a, -np.inf)
            if finite.any():
                points[finite] = np.asarray(model.log_likelihood(means[finite], z, k), dtype=np.float64).reshape(-1)
        values, points = values.tolist(), points.tolist()
        plain, plain_point = values[0], points[0]              # plain is the first arm
        scored = {name: _difference(values[i], plain) for i, name in enumerate(names)}
        self.differences.append(scored)
        self.point_differences.append({name: _difference(points[i], plain_point, lowest=-POINT_FLOOR)
                                       for i, name in enumerate(names)})
        return scored

    def _advance(self, k: int, weighted: dict[str, tuple[np.ndarray, np.ndarray]],
                 rng: np.random.Generator) -> np.ndarray:
        """Each arm's move on its weighted copy of step k, resampled to M and propagated to k + 1: (A, M, d)."""
        model = self.model
        m = min(self.particles, min(w.size for _, w in weighted.values()))
        points = (rng.random() + np.arange(m)) / m          # the same points resample every copy
        resampled: dict[str, np.ndarray] = {}
        estimates = None if self.estimates is None else {}
        state = rng.bit_generator.state
        for arm in self.arms:                                 # the DT arms: the same partners, r and u
            x, w = weighted[arm.name]
            if not arm.preprocess:
                if estimates is not None:
                    estimates[arm.name] = w @ x
                resampled[arm.name] = x[resampling.inverse_cdf(points, w)]
                continue
            rng.bit_generator.state = state
            log_likelihood = None
            if arm.weight_rule == "likelihood":
                z = self._z
                log_likelihood = (lambda y: model.log_likelihood(y, z, k))
            moved = rules.preprocess(x, w, arm.ps, rng, threshold_rule=self.threshold_rule,  # sets checked on receipt
                                     weight_rule=arm.weight_rule, log_likelihood=log_likelihood,  # or made here
                                     move_rule=arm.move_rule, checked=True)
            if estimates is not None:
                estimates[arm.name] = moved.weights @ moved.particles
            resampled[arm.name] = moved.particles[resampling.inverse_cdf(points, moved.weights)]
        if estimates is not None:
            self.estimates = estimates
        state = rng.bit_generator.state
        for arm in self.arms:                                 # the jitters: the same standard normals
            if arm.jitter == "none":
                continue
            rng.bit_generator.state = state
            x, w = weighted[arm.name]
            move = self.move if arm.jitter == OWN_ARM else arm.jitter
            resampled[arm.name] = jitters.apply(move, resampled[arm.name], x, w, rng, n=self.n)
        stacked = np.stack([np.asarray(resampled[arm.name], dtype=np.float64).reshape(m, -1) for arm in self.arms])
        return self._propagate(k + 1, stacked, rng)

    def _propagate(self, k: int, stacked: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The (A, M, d) copies propagated to k, every copy with the same numbers (common random numbers).

        A model that draws its noise on its own (``propagation_noise``, which ``propagate`` then uses instead
        of drawing) propagates all copies in one call, each with the same noise, when that call draws nothing
        more; any other in one call per copy, each from the same generator state. Both give the numbers of
        one call per copy.
        """
        model = self.model
        a, m, d = stacked.shape
        state = rng.bit_generator.state
        noise = model.propagation_noise(m, k, rng) if self.batched else None
        if noise is not None and np.ndim(noise) >= 1 and np.shape(noise)[0] == m:
            drawn = rng.bit_generator.state
            out = model.propagate(stacked.reshape(a * m, d), k, rng,
                                  noise=np.concatenate([np.asarray(noise)] * a, axis=0))
            if rng.bit_generator.state == drawn:
                return np.asarray(out, dtype=np.float64).reshape(a, m, -1)
            # It drew more than its noise (a driven step over several pieces of control, a model that draws
            # after the noise): those numbers would differ from copy to copy, so one call per copy after all.
        out = []
        for row in stacked:
            rng.bit_generator.state = state
            out.append(np.asarray(model.propagate(row, k, rng), dtype=np.float64).reshape(m, -1))
        return np.stack(out)
