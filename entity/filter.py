"""The particle filter as an iterator: each ``next()`` is one filter step.

::

    from dtpf.entity import models
    from dtpf.entity.filter import ParticleFilter
    model = models.get("ungm")
    truth, observations = model.simulate(100, rng)
    pf = ParticleFilter(model, observations, n_particles=1000, seed=7)
    for step in pf:
        print(step.step, step.mean, step.ess)

One step k:

1. propagate: x_k ~ p(x_k | x_(k-1)) (k = 1: draw from the prior);
2. weight: log w_k = log w_(k-1) + log p(z_k | x_k) (Eq. 23, in logs, so
   nothing underflows at N = 1e6 or on an outlier), normalise, ESS (Eq. 25);
3. if resampling is due (every step, or when ESS < threshold N): hand the
   set to the ``preprocessor`` (the digital twin's Eq. 28-30, in process or
   over Zenoh); if it gives no answer the step is *degraded* and plain
   resampling goes on;
4. estimate from the weighted set about to be resampled: posterior mean,
   variance and a 95% interval (mean +- 1.96 sd, per dimension);
5. resample with the configured traditional scheme; weights become uniform;
6. with a ``jitter`` (not the paper's; :mod:`dtpf.entity.jitter`), move every
   resampled particle by roughening or the regularised filter's kernel, with
   numbers from ``stream(seed, twin, k, "jitter")``; a twin whose answer names
   a move (the choosing system layer's arm in force at k) sets it for step k.

A driven model (:mod:`dtpf.entity.base`) gets each step's time since the last one and the control held
over it (``drives``: :class:`~dtpf.entity.timeline.Drive`, made from the observations' stamps by
:mod:`dtpf.entity.timeline`) and the sensor each observation is from (``sensors``); a model written
without them is called as before (:class:`~dtpf.entity.calls.ModelCalls`).

Random numbers of step k come from ``stream(seed, twin, k, "entity")``:
propagation first, then resampling. A set of more than ``block`` particles (the
run's ``block_particles``, :mod:`dtpf.entity.cores`) is worked on in blocks on
the process's threads: its sums add per-block sums in block order, and block
b >= 1 draws its propagation noise from its own stream (:mod:`dtpf.entity.blocks`),
so the numbers do not depend on the thread count. The propagation noise of step k + 1
depends on nothing of step k, so :meth:`ParticleFilter.prepare_next_step` can
draw it while step k waits for its preprocessor; and when the preprocessor
keeps the weights, :meth:`ParticleFilter.resample_ahead` can resample before
its answer arrives. The entity service does both during the lockstep wait
(:meth:`ParticleFilter.work_ahead`); the numbers are the same either way.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from dtpf.entity import blocks as blocked
from dtpf.entity import cores
from dtpf.entity import jitter as jitters
from dtpf.entity import resampling
from dtpf.entity.calls import ModelCalls
from dtpf.entity.models import StateSpaceModel
from dtpf.messages.arrays import check_particles, check_set
from dtpf.messages.errors import DtpfError
from dtpf.messages.names import OWN_ARM
from dtpf.messages.references import describe
from dtpf.messages.models import MAX_COVARIANCE_DIM
from dtpf.messages.streams import stream

__all__ = ["ParticleFilter", "FilterStep", "PendingStep", "Preprocessor", "Preprocessed", "FilterError"]

#: z value of a two-sided 95% normal interval.
Z95 = 1.959963984540054


class FilterError(DtpfError, ValueError):
    """The filter cannot go on (for example every weight is zero at a step)."""


@dataclass(frozen=True)
class Preprocessed:
    """What a preprocessor hands back: the set to resample, and its report.

    The filter keeps ``report`` in its step without reading it: the information layer's
    ``PreprocessReport`` in process, the preprocessed set's message over Zenoh (both carry W, M, N - M,
    the branches of Eq. 30 and PS).
    """

    particles: np.ndarray
    weights: np.ndarray
    report: object = None
    #: The arrays passed check_particles / check_weights already (a decoded message): not scanned again.
    checked: bool = False
    #: The move after resampling the twin's chosen arm names (:data:`dtpf.entity.jitter.JITTERS`);
    #: None: the filter's own ``jitter``.
    jitter: str | None = None


class Preprocessor(Protocol):
    """Runs before resampling; returns None when it has no answer (degraded step)."""

    def __call__(self, step: int, particles: np.ndarray, weights: np.ndarray,
                 observation: np.ndarray, parents: int | None) -> Preprocessed | None: ...


@dataclass(frozen=True)
class FilterStep:
    """The outcome of one filter step.

    Attributes
    ----------
    step : int
        k, from 1.
    particles, weights : (N, d), (N,) ndarray
        The weighted set before preprocessing and resampling.
    ess : float
        Effective sample size of ``weights`` (Eq. 25).
    mean, var, lower, upper : (d,) ndarray
        Posterior mean, variance and 95% interval of the set that was
        resampled (after preprocessing where it ran).
    resampled : bool
        Whether resampling ran at this step.
    degraded : bool
        Resampling was due but the preprocessor gave no answer.
    report : object or None
        The preprocessor's report, if it ran.
    ancestors : (N,) ndarray or None
        Ancestor indices of the resampling, if it ran.
    parents : int or None
        Number of distinct particles ``particles`` descend from (the distinct
        ancestors of the last resampling); None before the first.
    log_predictive : float
        log p(z_k | z_1:k-1), estimated from the weights before normalisation:
        log sum_i W_(k-1)^i p(z_k | x_k^i). What a filter on real data, without
        truth, is judged by (higher is better).
    innovation : float or None
        The normalised innovation squared of z_k, sum_j (z_j - zhat_j)^2 / S_jj
        with zhat and S the predictive mean and variance of z_k (about m when the
        filter is consistent); None unless the filter was asked for it and the
        model gives ``observation_moments``.
    covariance : (d(d-1)/2,) ndarray or None
        The weighted covariances between the components of the set that was
        resampled, the pairs i < j row by row (:func:`covariances`); None unless
        2 <= d <= 8.
    sensor : str or None
        The sensor z_k is from (None: the model's one sensor).
    drive : Drive or None
        How the step was reached: dt and the control of each piece (None: the first step, or a model
        that is not driven).
    """

    step: int
    particles: np.ndarray
    weights: np.ndarray
    ess: float
    mean: np.ndarray
    var: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    resampled: bool
    degraded: bool
    report: object
    ancestors: np.ndarray | None
    parents: int | None
    log_predictive: float = float("nan")
    innovation: float | None = None
    covariance: np.ndarray | None = None
    sensor: str | None = None
    drive: object = None


def _model_failed(model, k: int, method: str, exc: Exception) -> Exception:
    """What to raise for a model method that failed at step k: a FilterError in one line naming the step, the
    method and the line of the model's file (an IndexError at step 50 is not a traceback); a FilterError
    itself as it is."""
    if isinstance(exc, FilterError):
        return exc
    try:
        path = inspect.getsourcefile(type(model))
    except TypeError:
        path = None
    return FilterError(f"step {k}: the model's {method} raised {describe(exc, path)}")


def normalise(log_weights: np.ndarray) -> np.ndarray:
    """Normalised weights from log-weights, shifted by the maximum (no underflow of the largest)."""
    return _normalise(log_weights)[0]


def _normalise(log_weights: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Normalised weights, log sum_i exp(log_weights_i) and the largest log-weight, from one pass of
    exponentials into the new array (Eq. 23 normalised, shifted by the maximum)."""
    top = _top_of(log_weights)
    weights = np.subtract(log_weights, top)
    np.exp(weights, out=weights)
    total = weights.sum()
    weights /= total
    return weights, top + float(np.log(total)), top


def _top_of(log_weights: np.ndarray, largest=np.max) -> float:
    """The largest log-weight (by ``largest``); FilterError when it is NaN or infinite (no particle explains z_k)."""
    top = float(largest(log_weights))
    if not np.isfinite(top):
        if np.isnan(top):
            raise FilterError("a log-weight is NaN (the model's log_likelihood gave NaN): no particle explains "
                              "the observation")
        raise FilterError(f"every log-weight is {top}: no particle explains the observation")
    return top


def _shown(values: np.ndarray, most: int = 8) -> str:
    """A short text of an observation's values, for a one-line error: the first ``most`` of them."""
    shown = ", ".join(f"{v:.6g}" for v in values[:most])
    return f"[{shown}{', ...' if values.size > most else ''}]"


def normalised_innovation(model, particles: np.ndarray, prior_weights: np.ndarray, observation: np.ndarray,
                          k: int, *, sensor: str | None = None, calls: ModelCalls | None = None) -> float | None:
    """Normalised innovation squared of z_k under the predictive law of the propagated set.

    zhat = sum_i W^i h(x^i), S = sum_i W^i (h(x^i) - zhat)^2 + R per observed
    dimension (diagonal), with h and R from ``model.observation_moments``; the
    result sum_j (z_j - zhat_j)^2 / S_j is about m on average for a consistent
    filter. None where the model gives no moments. ``sensor``: the sensor z_k is from, passed to a model
    whose ``observation_moments`` takes it.
    """
    calls = calls if calls is not None else ModelCalls(model)
    moments_of = calls.observation_moments(particles, k, sensor=sensor)
    if moments_of is None:
        return None
    h, noise_var = moments_of
    h = np.asarray(h, dtype=np.float64).reshape(particles.shape[0], -1)
    zhat = prior_weights @ h
    centred = h - zhat
    spread = prior_weights @ (centred * centred) + np.asarray(noise_var, dtype=np.float64)
    residual = np.asarray(observation, dtype=np.float64).reshape(-1) - zhat
    return float(np.sum(residual * residual / spread))


def covariances(particles: np.ndarray, weights: np.ndarray, mean: np.ndarray) -> np.ndarray | None:
    """The weighted covariances between the components, the pairs i < j row by row: (d(d-1)/2,); None unless
    2 <= d <= MAX_COVARIANCE_DIM (what an :class:`~dtpf.messages.models.Estimate` carries)."""
    d = particles.shape[1]
    if not 2 <= d <= MAX_COVARIANCE_DIM:
        return None
    centred = particles - mean
    full = (centred * weights[:, None]).T @ centred
    return full[np.triu_indices(d, 1)]


def moments_and_covariances(particles: np.ndarray, weights: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`moments` and :func:`covariances` in one pass over the centred particles: the weighted mean and
    variances (d,), and the covariances between components (None unless 2 <= d <= MAX_COVARIANCE_DIM).
    With covariances, sum_n (sqrt(w_n) c_n)(sqrt(w_n) c_n)^T gives them all, the variances on its diagonal:
    one pass instead of two."""
    d = particles.shape[1]
    if not 2 <= d <= MAX_COVARIANCE_DIM:
        mean, var = moments(particles, weights)
        return mean, var, None
    mean = weights @ particles
    scaled = particles - mean
    scaled *= np.sqrt(weights)[:, None]
    full = scaled.T @ scaled
    return mean, np.diagonal(full).copy(), full[np.triu_indices(d, 1)]


def moments(particles: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean and variance per dimension: (d,), (d,)."""
    mean = weights @ particles
    centred = particles - mean
    np.multiply(centred, centred, out=centred)
    return mean, weights @ centred


class ParticleFilter:
    """A bootstrap particle filter over a :class:`~dtpf.entity.models.StateSpaceModel`.

    Parameters
    ----------
    model : StateSpaceModel
    observations : (T, m) array_like
        z_1 .. z_T; the filter runs T steps.
    n_particles : int
        N.
    resampler : str
        A traditional scheme of :data:`dtpf.entity.resampling.RESAMPLERS`, or a reference to a user's
        resampler (:mod:`dtpf.entity.resamplers.base`).
    resample_below : float or None
        None (default, the paper's setting): resample at every step.
        A fraction in (0, 1]: resample when ESS < resample_below * N.
    seed : int
        Root seed of the run's random streams.
    twin : str
        Twin id, part of the random streams' key.
    preprocessor : Preprocessor, optional
        Runs before each resampling (the digital twin); None: plain resampling.
    jitter : str
        A move after each resampling (a built-in of :data:`dtpf.entity.jitter.JITTERS` or a reference to a
        user's move, :mod:`dtpf.entity.moves.base`): "none"
        (default, the paper), "roughening" or "regularised".
    innovation : bool
        Also compute each step's normalised innovation (where the model gives
        ``observation_moments``): one more pass over the particles, so off by
        default; a run without truth turns it on.
    sensors : sequence of str, optional
        The sensor of each observation (a model with ``sensors``); its rows then hold the sensor's values
        first and NaN after them (rows as long as the longest sensor's).
    drives : sequence of Drive or None, optional
        How each step is reached from the one before (:mod:`dtpf.entity.timeline`); None: not driven.
    block : int or None
        B, the run's ``block_particles``: N > B particles are worked on in blocks of B
        (:mod:`dtpf.entity.blocks`); None (default): one block, whatever N.

    ``observations=None`` makes a filter for observations that arrive one at
    a time (a live sensor): call :meth:`update` with each z_k; there is no T
    and iteration stops at once.
    """

    def __init__(self, model: StateSpaceModel, observations, n_particles: int, *,
                 resampler: str = "systematic", resample_below: float | None = None,
                 seed: int = 0, twin: str = "twin", preprocessor: Preprocessor | None = None,
                 innovation: bool = False, jitter: str = "none", sensors=None, drives=None,
                 block: int | None = None):
        self.move = jitters.get(jitter)  # a ValueError naming the move if it is unknown or breaks the contract
        self.calls = ModelCalls(model)
        if observations is None:
            z = np.empty((0, model.obs_dim))
        else:
            z = np.asarray(observations, dtype=np.float64)
            if z.ndim == 1:
                z = z[:, None]
            if z.ndim != 2 or z.shape[0] == 0:
                raise ValueError(f"observations must have shape (T,) or (T, m) with T >= 1, got {z.shape}")
            if sensors is not None:
                sensors = tuple(sensors)
                if len(sensors) != z.shape[0]:
                    raise ValueError(f"{len(sensors)} sensor names for {z.shape[0]} observations")
                for i, name in enumerate(sensors):
                    if not np.isfinite(z[i, :self._width(name)]).all():
                        raise ValueError(f"observation {i + 1} ({name}) contains non-finite values")
            elif not np.isfinite(z).all():
                raise ValueError("observations contain non-finite values")
            if drives is not None and len(drives) != z.shape[0]:
                raise ValueError(f"{len(drives)} drives for {z.shape[0]} observations")
        self.sensors = sensors
        self.drives = drives
        if int(n_particles) < 1:
            raise ValueError(f"n_particles must be at least 1, got {n_particles!r}")
        if resample_below is not None and not 0.0 < float(resample_below) <= 1.0:
            raise ValueError(f"resample_below must be in (0, 1] or None, got {resample_below!r}")
        self.model = model
        self.observations = z
        self.n = int(n_particles)
        if block is not None and int(block) < 1:
            raise ValueError(f"block must be at least 1 or None, got {block!r}")
        self.block = None if block is None else int(block)
        #: The set is worked on in blocks of ``block`` (more than one: dtpf.entity.blocks).
        self.blocked = cores.blocks(self.n, self.block) > 1
        self.resampler_name = resampler
        self.resample = resampling.get(resampler)
        self.resample_below = resample_below
        self.seed = int(seed)
        self.twin = twin
        self.preprocessor = preprocessor
        self.innovation = bool(innovation)
        self.jitter = jitter
        self.live = observations is None
        self.k = 0
        #: log sum_i exp(log_weights_i) of the carried log-weights (log N after a resampling).
        self._log_total = float(np.log(self.n))
        self.particles: np.ndarray | None = None
        self.log_weights = np.zeros(self.n)
        #: log_weights are all 0 (after a resampling): the next step's are its log-likelihoods.
        self._flat = True
        #: Where the resampled particles are gathered: reused while nothing else holds them.
        self._gathered: np.ndarray | None = None
        self.parents: int | None = None
        #: (step, rng, noise) of the next step, drawn ahead by prepare_next_step().
        self._ahead: tuple[int, np.random.Generator, np.ndarray | None] | None = None
        #: (step, weights, rng) of the step whose preprocessor is running.
        self._waiting: tuple[int, np.ndarray, np.random.Generator] | None = None
        #: (step, rng state before, weights, ancestors) from resample_ahead().
        self._resampled: tuple[int, dict, np.ndarray, np.ndarray] | None = None

    @property
    def steps(self) -> int:
        """T, the number of steps the filter runs (0 for a live filter, which has no T)."""
        return self.observations.shape[0]

    def __iter__(self):
        return self

    def warm_up(self) -> None:
        """Resample and gather a small throwaway set, writable and read-only, so that the compiled
        resampler and gather are loaded (or, on a cold cache, compiled) before the first step, and make a
        stream of step 0 (the compiled SeedSequence); the run's random streams are not touched."""
        weights, particles = np.full(8, 1.0 / 8), np.zeros((8, self.model.dim))
        ancestors = self.resample(weights, np.random.default_rng(0))
        resampling.gather(particles, ancestors, np.empty_like(particles))
        # A twin's answer arrives as a decoded message's read-only arrays, which numba compiles apart.
        weights.flags.writeable = particles.flags.writeable = False
        resampling.gather(particles, self.resample(weights, np.random.default_rng(0)), np.empty_like(particles))
        resampling.distinct(np.zeros(2, dtype=np.int64))
        stream(self.seed, self.twin, 0, "entity")
        if self.blocked:  # the kernels of a set in blocks, on 2 blocks of 4, writable and read-only
            weights = blocked.normalise(np.zeros(8), 4, 0.0)[0]
            particles = np.zeros((8, self.model.dim))
            for writeable in (True, False):
                weights.flags.writeable = particles.flags.writeable = writeable
                blocked.moments(particles, weights, 4)
                if self.resampler_name == "systematic":
                    resampling.systematic_blocks(weights, np.random.default_rng(0), 4)

    def prepare_next_step(self) -> None:
        """Draw the random numbers that start the next step now: its stream and propagation noise.

        For a caller with time to spare during a step (the lockstep wait for
        the information layer). The next step uses what was drawn here, so the
        numbers do not change; a model whose ``propagation_noise`` is None
        gets only its stream made ahead. Nothing to do before the first step
        (its particles come from the prior), after the last, or twice.
        """
        k = self.k + 1
        if self.k == 0 or (k > self.steps and not self.live) or self._ahead is not None:
            return
        rng = stream(self.seed, self.twin, k, "entity")
        try:
            self._ahead = (k, rng, self._noise(k, rng))
        except Exception as exc:
            raise _model_failed(self.model, k, "propagation_noise", exc) from exc

    def resample_ahead(self) -> None:
        """Resample the set being preprocessed with its own weights, before the answer comes.

        For a preprocessor to call while it waits for the twin. If the answer
        keeps the weights (the "inherit" weight rule, or a degraded step with
        no answer), the step uses these ancestors; otherwise it puts its stream
        back where it was and resamples the answer. The numbers do not change
        either way. Outside a preprocessor call, or twice, it does nothing.
        """
        if self._waiting is None or self._resampled is not None:
            return
        k, weights, rng = self._waiting
        state = rng.bit_generator.state
        self._resampled = (k, state, weights, self._resample(weights, rng))

    def work_ahead(self) -> None:
        """Everything the answer of the preprocessor does not change: :meth:`resample_ahead`, then
        :meth:`prepare_next_step`. The entity service calls it during the lockstep wait."""
        self.resample_ahead()
        self.prepare_next_step()

    def _gather(self, particles: np.ndarray, ancestors: np.ndarray) -> np.ndarray:
        """particles[ancestors], into the array of the last gather when nothing else holds it.

        The resampled set is only the next propagation's input; a model whose ``propagate`` returned
        its input (an in-place model) makes that array a step's ``particles``, and :meth:`_step`
        then lets it go.
        """
        out = self._gathered
        if out is None or out.shape != particles.shape or np.may_share_memory(out, particles):
            out = np.empty_like(particles)
        self._gathered = resampling.gather(particles, ancestors, out)
        return out

    def _noise(self, k: int, rng: np.random.Generator) -> np.ndarray | None:
        """The model's propagation noise of step k (None: it draws none apart), block by block for a set
        in blocks (:func:`dtpf.entity.blocks.noise`)."""
        if self.blocked:
            return blocked.noise(self.model, self.n, k, rng, self.block, (self.seed, self.twin))
        return self.model.propagation_noise(self.n, k, rng)

    def _resample(self, weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The configured scheme on weights made (normalised) or checked (check_set) this step: not scanned
        again; systematic in blocks for a set in blocks (:func:`dtpf.entity.resampling.systematic_blocks`)."""
        if self.blocked and self.resampler_name == "systematic":
            return resampling.systematic_blocks(weights, rng, self.block)
        return self.resample(weights, rng, checked=True)

    def _ancestors(self, k: int, weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Ancestor indices of step k: those of resample_ahead() if they were drawn from these weights."""
        ahead, self._resampled = self._resampled, None
        if ahead is not None and ahead[0] == k:
            _, state, used, ancestors = ahead
            if used is weights or np.array_equal(used, weights):
                return ancestors
            rng.bit_generator.state = state  # as if nothing had been drawn
        return self._resample(weights, rng)

    def __next__(self) -> FilterStep:
        """One step of the particle filter, on the next of the observations it was given."""
        if self.k >= self.steps:
            raise StopIteration
        k = self.k
        return self._step(self.observations[k], sensor=None if self.sensors is None else self.sensors[k],
                          drive=None if self.drives is None else self.drives[k])

    def _width(self, sensor: str | None) -> int:
        """m of ``sensor``'s observations; ValueError naming an unknown sensor."""
        dims = self.calls.sensors
        if sensor not in dims:
            known = ", ".join(str(name) for name in dims)
            if None in dims:
                raise ValueError(f"observation from sensor {sensor!r}; the model has one sensor, unnamed")
            raise ValueError(f"observation from {'no sensor' if sensor is None else f'sensor {sensor!r}'}; the "
                             f"model's sensors are {known}")
        return dims[sensor]

    def update(self, observation, *, sensor: str | None = None, drive=None) -> FilterStep:
        """One step of the particle filter on ``observation`` (z_k, m values): for a live filter.
        ``sensor``: the sensor it is from; ``drive``: how the step is reached (:mod:`dtpf.entity.timeline`).

        Raises ValueError if z_k does not have its sensor's m finite values.
        """
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
        m = self._width(sensor)
        if z.shape != (m,):
            where = "the model observes" if sensor is None else f"sensor {sensor!r} observes"
            raise ValueError(f"observation has {z.size} values, {where} {m}")
        if not np.isfinite(z).all():
            raise ValueError(f"observation contains non-finite values: {z.tolist()}")
        return self._step(z, sensor=sensor, drive=drive)

    def _step(self, observation: np.ndarray, *, sensor: str | None = None, drive=None) -> FilterStep:
        pending = self.begin_step(observation, ask=self.preprocessor is not None, sensor=sensor, drive=drive)
        answer = None
        if pending.asks:
            try:
                if pending.sensor is None and pending.drive is None:
                    answer = self.preprocessor(pending.step, pending.particles, pending.weights,
                                               pending.observation, pending.parents)
                else:
                    answer = self.preprocessor(pending.step, pending.particles, pending.weights,
                                               pending.observation, pending.parents, sensor=pending.sensor,
                                               drive=pending.drive)
            except BaseException:
                self._waiting = None
                raise
        return self.finish_step(pending, answer)

    def begin_step(self, observation, *, ask: bool = True, sensor: str | None = None,
                   drive=None) -> "PendingStep":
        """Steps 1-2 of step k on z_k (propagate, weight, normalise, ESS), up to the preprocessor's question.

        For a caller that asks its preprocessor itself, without blocking (the
        entity service's event loop): when ``pending.asks`` (resampling is due
        and ``ask``), hand ``pending``'s set to the preprocessor, then call
        :meth:`finish_step` with its answer (None: no answer, a degraded step);
        :meth:`work_ahead` may run in between. Otherwise call
        :meth:`finish_step` at once. The numbers are those of ``next()``. ``sensor`` and ``drive``: as
        :meth:`update` takes them (a row of a multi-sensor table is cut to its sensor's values here).
        """
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
        if sensor is not None or self.calls.named_sensors:
            z = z[:self._width(sensor)]
        self.k += 1
        k = self.k
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead[0] == k:
            _, rng, noise = ahead
        else:
            rng, noise = stream(self.seed, self.twin, k, "entity"), None
        if self.particles is None:
            drive = None  # the first step starts from the prior
        try:
            if self.particles is None:
                self.particles = check_particles(self.model.initial_particles(self.n, rng))
            elif drive is not None:
                self.particles = check_particles(self.calls.advance(self.particles, k, rng, drive, noise))
            elif noise is None and self.blocked and (noise := self._noise(k, rng)) is not None:
                self.particles = check_particles(self.model.propagate(self.particles, k, rng, noise=noise))
            elif noise is None:
                self.particles = check_particles(self.model.propagate(self.particles, k, rng))
            else:
                self.particles = check_particles(self.model.propagate(self.particles, k, rng, noise=noise))
        except Exception as exc:
            raise _model_failed(self.model, k, "propagate" if self.particles is not None else "initial_particles",
                                exc) from exc
        if self._gathered is not None and np.may_share_memory(self.particles, self._gathered):
            self._gathered = None  # propagated in place: this step's particles, not to be gathered over
        prior_log_total = self._log_total
        innovation = None
        if self.innovation:
            prior = np.exp(self.log_weights - prior_log_total)
            innovation = normalised_innovation(self.model, self.particles, prior, z, k, sensor=sensor,
                                               calls=self.calls)
        try:
            log_likelihood = self.calls.log_likelihood(self.particles, z, k, sensor=sensor)
        except Exception as exc:
            raise _model_failed(self.model, k, "log_likelihood", exc) from exc
        if self._flat and self.blocked and np.shape(log_likelihood) == self.log_weights.shape:  # 0 + l is l
            blocked.copy(self.log_weights, np.asarray(log_likelihood))
        elif self._flat:  # 0 + l is l: no pass over zeros
            np.copyto(self.log_weights, log_likelihood)
        else:
            np.add(self.log_weights, log_likelihood, out=self.log_weights)
        try:
            if self.blocked:
                weights, log_total, top, ess = blocked.normalise(self.log_weights, self.block,
                                                                 _top_of(self.log_weights, blocked.largest))
            else:
                weights, log_total, top = _normalise(self.log_weights)
                ess = 1.0 / float(np.dot(weights, weights))
        except FilterError as error:
            raise FilterError(f"step {k}: {error} z = {_shown(z)}") from None
        log_predictive = log_total - prior_log_total  # log sum_i W_(k-1)^i p(z_k | x_k^i)
        self._log_total = log_total - top

        due = self.resample_below is None or ess < self.resample_below * self.n
        self._flat = due
        if not due:
            self.log_weights -= top  # keep log-weights near 0 between resamplings
        pending = PendingStep(k, self.particles, weights, z, self.parents, ess, due, due and ask, rng,
                              log_predictive, innovation, sensor, drive)
        if pending.asks:
            self._waiting = (k, weights, rng)
        return pending

    def finish_step(self, pending: "PendingStep", answer: Preprocessed | None) -> FilterStep:
        """Steps 3-6 of the step :meth:`begin_step` began: take the preprocessor's ``answer`` (None:
        degraded, if it was asked), estimate, resample, jitter."""
        self._waiting = None
        k, particles, weights, rng, due = pending.step, pending.particles, pending.weights, pending.rng, pending.due
        degraded = False
        report = None
        target_particles, target_weights = particles, weights
        move = self.jitter
        if pending.asks:
            if answer is None:
                degraded = True
            else:
                target_particles, target_weights = check_set(answer.particles, answer.weights,
                                                             checked=answer.checked)
                if target_particles.shape != particles.shape:
                    raise ValueError(f"preprocessed particles have shape {target_particles.shape}, "
                                     f"expected {particles.shape}")
                report = answer.report
                if answer.jitter is not None:
                    # Only a built-in or the run's own move: a name on the wire never loads code.
                    if answer.jitter == OWN_ARM and self.jitter not in jitters.JITTERS:
                        move = self.jitter
                    elif answer.jitter not in jitters.JITTERS:
                        raise ValueError(f"unknown jitter {answer.jitter!r} in the twin's answer (this run has "
                                         f"{'no move of its own' if answer.jitter == OWN_ARM else 'no such move'})")
                    else:
                        move = answer.jitter

        if self.blocked and not 2 <= target_particles.shape[1] <= MAX_COVARIANCE_DIM:
            (mean, var), covariance = blocked.moments(target_particles, target_weights, self.block), None
        else:
            mean, var, covariance = moments_and_covariances(target_particles, target_weights)
        half = Z95 * np.sqrt(var)
        ancestors = None
        parents = self.parents
        if due:
            ancestors = self._ancestors(k, target_weights, rng)
            self.particles = self._gather(target_particles, ancestors)
            if move != "none":
                apply = self.move if move == self.jitter else jitters.get(move)
                self.particles = apply(self.particles, target_particles, target_weights,
                                       stream(self.seed, self.twin, k, "jitter"))
            if self.blocked:
                blocked.fill(self.log_weights, 0.0)
            else:
                self.log_weights.fill(0.0)
            self._log_total = float(np.log(self.n))
            self.parents = resampling.distinct(ancestors)
        return FilterStep(k, particles, weights, pending.ess, mean, var, mean - half, mean + half,
                          due, degraded, report, ancestors, parents, pending.log_predictive, pending.innovation,
                          covariance, pending.sensor, pending.drive)


@dataclass(frozen=True)
class PendingStep:
    """A filter step between :meth:`ParticleFilter.begin_step` and :meth:`ParticleFilter.finish_step`.

    ``particles``, ``weights``, ``observation`` and ``parents`` are what the
    preprocessor is asked about (``asks``: resampling is due and a preprocessor
    is to be asked); the rest is the step's own state.
    """

    step: int
    particles: np.ndarray
    weights: np.ndarray
    observation: np.ndarray
    parents: int | None
    ess: float
    due: bool
    asks: bool
    rng: np.random.Generator
    log_predictive: float
    innovation: float | None
    sensor: str | None = None
    #: How the step was reached from the one before (None: the first step, or a model that is not driven).
    drive: object = None
