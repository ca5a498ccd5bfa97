"""Check a model on a small probe at startup, so that a broken model fails now, not at step 500.

::

    from dtpf.entity.model_check import check_model, load_checked
    check_model(model)                                  # raises ModelError, or returns None
    model = load_checked("my_model.py:MyModel", needs_sampling="policy 'predictive'")

The probe draws ``n`` (5) particles from the prior and calls every method of
the model once, the way the filter does:

1. ``dim`` and ``obs_dim`` are ints >= 1;
2. ``initial_particles(n, rng)`` is an (n, dim) array of finite numbers;
3. ``propagation_noise(n, 2, rng)`` is None or an array; if an array,
   ``propagate(x, 2, rng, noise=...)`` must give what ``propagate(x, 2, rng)``
   gives from the same random stream (the entity draws it ahead);
4. ``propagate(x, 2, rng)`` is an (n, dim) array of finite numbers;
5. ``sample_observation`` (where the model gives it) is (n, obs_dim), finite;
6. ``log_likelihood`` is (n,), without NaN or +inf, and not -inf for every
   probe particle. It is evaluated on the given ``observation`` (the first
   observation of the run) at the prior particles, k = 1, as the filter's
   first step does; without one, on the observation sampled from the first
   propagated particle, k = 2. A model that samples no observations, checked
   without an observation, has its likelihood left unchecked;
7. ``observation_moments`` is None or ((n, obs_dim) finite means,
   (obs_dim,) finite non-negative variances).

A driven model (:mod:`dtpf.entity.base`: ``controls``, ``sensors``, ``propagate`` taking ``dt`` or
``control``) is checked the same way through :class:`~dtpf.entity.calls.ModelCalls`, and more:

8. ``controls`` is a tuple of distinct names, ``sensors`` a mapping of names (a letter, then letters,
   digits, ``_`` or ``-``) to positive ints, and ``obs_dim`` is at least the widest sensor's;
9. ``propagate`` is called with ``dt=0.1`` and ``dt=0.0`` and a zero control of ``len(controls)`` values
   (the pieces of :mod:`dtpf.entity.timeline`) and must give (n, dim) finite particles;
10. for every sensor: ``sample_observation`` (where given) is (n, m_sensor), ``log_likelihood`` of the
    run's first observation of that sensor (or a sampled one) is (n,) as in 6, ``observation_moments``
    as in 7 with the sensor's m.

Each failure is a :class:`~dtpf.entity.model_ref.ModelError` with a one-line
message naming the model, the method, what it returned and what was
expected; an exception raised by a model method is reported as
``<method> raised <Type>: <first line of its message>``.
"""
from __future__ import annotations

import threading

import numpy as np

from dtpf.entity.model_ref import ModelError, dimension, resolve
from dtpf.entity.models import StateSpaceModel

__all__ = ["check_model", "load_checked"]

_CHECKED: dict[tuple[str, bool | str], StateSpaceModel] = {}
_LOCK = threading.RLock()


def check_model(model, *, observation=None, needs_sampling: bool | str = False, n: int = 5, seed: int = 0,
                ref: str | None = None) -> None:
    """Call every method of ``model`` on ``n`` probe particles; raise ModelError on the first fault.

    Parameters
    ----------
    model : StateSpaceModel
    observation : (obs_dim,) array_like or dict, optional
        The first observation of the run; the likelihood is evaluated on it. A driven model's: a dict of
        sensor name (None for a model of one unnamed sensor) to its first observation.
    needs_sampling : bool or str
        The run draws observations (a simulating policy, ``dtpf sensor``):
        the model must implement ``sample_observation``. A string names what
        needs it, a noun phrase: the message reads "sample_observation is not
        implemented, but <needs_sampling> needs it" ("policy 'predictive'",
        "dtpf sensor").
    n : int
        Probe particles.
    seed : int
        Seed of the probe's ``np.random.default_rng``.
    ref : str, optional
        The reference the model was loaded from, quoted in messages.

    Raises
    ------
    ModelError
    """
    where = _where(model, ref)
    if not isinstance(model, StateSpaceModel):
        raise ModelError(f"{where}: {type(model).__name__} is not a StateSpaceModel")
    n = int(n)
    if n < 1:
        raise ValueError(f"n must be at least 1, got {n}")
    dim = dimension(model, "dim", where)
    obs_dim = dimension(model, "obs_dim", where)
    samples = bool(_call(where, "samples_observations", lambda: model.samples_observations))
    if needs_sampling and not samples:
        reason = needs_sampling if isinstance(needs_sampling, str) else "this run (it draws observations)"
        raise ModelError(f"{where}: sample_observation is not implemented, but {reason} needs it")
    from dtpf.entity.calls import ModelCalls

    calls = _call(where, "reading its signatures", lambda: ModelCalls(model))
    if calls.driven:
        _check_driven(model, calls, where, dim, obs_dim, observation, samples, n, seed)
        return
    z = None
    if observation is not None:
        z = _observation(observation, obs_dim, where)

    rng = np.random.default_rng(seed)
    shape, what = (n, dim), f"(N particles by dim {dim})"
    prior = _array(where, "initial_particles", _call(where, "initial_particles",
                                                     lambda: model.initial_particles(n, rng)), shape, what)

    # The entity draws propagation noise ahead; it must give the numbers propagate draws itself.
    step_seed = [seed, 2]
    plain_rng = np.random.default_rng(step_seed)
    ahead_rng = np.random.default_rng(step_seed)
    noise = _call(where, "propagation_noise", lambda: model.propagation_noise(n, 2, ahead_rng))
    if noise is not None and not isinstance(noise, np.ndarray):
        raise ModelError(f"{where}: propagation_noise returned {_a(noise)}, expected None or an array")
    moved = _array(where, "propagate", _call(where, "propagate", lambda: model.propagate(prior.copy(), 2, plain_rng)),
                   shape, what)
    if noise is not None:
        with_noise = _array(where, "propagate(noise=...)", _call(
            where, "propagate(noise=...)", lambda: model.propagate(prior.copy(), 2, ahead_rng, noise=noise)),
            shape, what)
        if not np.allclose(with_noise, moved, rtol=1e-9, atol=1e-12):
            raise ModelError(f"{where}: propagate(noise=propagation_noise(...)) gives other particles than "
                             f"propagate(...) from the same random stream; propagation_noise must draw exactly "
                             f"what propagate draws first")

    sampled = None
    if samples:
        sampled = _array(where, "sample_observation", _call(
            where, "sample_observation", lambda: model.sample_observation(moved.copy(), 2, rng)),
            (n, obs_dim), f"(N states by obs_dim {obs_dim})")

    if z is not None:
        _likelihood(model, where, prior, z, 1, n, "no particle explains the first observation")
    elif sampled is not None:
        ll = _likelihood(model, where, moved, sampled[0], 2, n,
                         "no particle explains the observation sampled from the first of them")
        if np.isneginf(ll[0]):
            raise ModelError(f"{where}: log_likelihood is -inf for the probe particle its observation was "
                             f"sampled from: sample_observation and log_likelihood disagree")

    moments = _call(where, "observation_moments", lambda: model.observation_moments(moved.copy(), 2))
    if moments is not None:
        if not isinstance(moments, (tuple, list)) or len(moments) != 2:
            raise ModelError(f"{where}: observation_moments returned {_a(moments)}, expected None or "
                             f"a pair (means (N, obs_dim), noise variances (obs_dim,))")
        _array(where, "observation_moments means", moments[0], (n, obs_dim), f"(N particles by obs_dim {obs_dim})")
        var = _array(where, "observation_moments variances", moments[1], (obs_dim,), f"(obs_dim {obs_dim})")
        if (var < 0).any():
            i = int(np.flatnonzero(var < 0)[0])
            raise ModelError(f"{where}: observation_moments variances are negative at index {i} ({var[i]!r}), "
                             f"expected variances >= 0")


def _check_driven(model, calls, where: str, dim: int, obs_dim: int, observation, samples: bool, n: int,
                  seed: int) -> None:
    """Items 8-10 of the module docstring, with 2-7 through the driven calls."""
    import re

    controls = getattr(model, "controls", ())
    if not isinstance(controls, (tuple, list)) or not all(isinstance(c, str) and c for c in controls) \
            or len(set(controls)) != len(controls):
        raise ModelError(f"{where}: controls is {controls!r}, expected a tuple of distinct names")
    for name, m in calls.sensors.items():
        if name is not None and not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]{0,63}", name):
            raise ModelError(f"{where}: sensor name {name!r} must be a letter then letters, digits, '_' or '-'")
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise ModelError(f"{where}: sensor {name!r} has dimension {m!r}, expected a positive int")
    if obs_dim < max(calls.sensors.values()):
        raise ModelError(f"{where}: obs_dim is {obs_dim}, less than its widest sensor's {max(calls.sensors.values())}")
    given = {}
    if observation is not None:
        given = dict(observation) if isinstance(observation, dict) else {next(iter(calls.sensors)): observation}
    for name in given:
        if name not in calls.sensors:
            raise ModelError(f"{where}: an observation from sensor {name!r}, which the model does not have")
    rng = np.random.default_rng(seed)
    shape, what = (n, dim), f"(N particles by dim {dim})"
    prior = _array(where, "initial_particles", _call(where, "initial_particles",
                                                     lambda: model.initial_particles(n, rng)), shape, what)
    c = len(calls.controls)
    moved = prior
    for dt in (0.1, 0.0):
        label = f"propagate(dt={dt}, control=zeros({c}))"
        moved = _array(where, label, _call(where, label, lambda dt=dt: calls.propagate(
            prior.copy(), 2, rng, dt=dt, control=np.zeros(c))), shape, what)
    # The entity draws propagation noise ahead; the first piece of a step takes it.
    plain_rng, ahead_rng = np.random.default_rng([seed, 2]), np.random.default_rng([seed, 2])
    noise = _call(where, "propagation_noise", lambda: model.propagation_noise(n, 2, ahead_rng))
    if noise is not None:
        control = np.zeros(c)
        plain = calls.propagate(prior.copy(), 2, plain_rng, dt=0.1, control=control)
        ahead = _call(where, "propagate(noise=...)", lambda: calls.propagate(prior.copy(), 2, ahead_rng, noise,
                                                                              dt=0.1, control=control))
        if not np.allclose(np.asarray(ahead, dtype=np.float64), np.asarray(plain, dtype=np.float64), rtol=1e-9,
                           atol=1e-12):
            raise ModelError(f"{where}: propagate(noise=propagation_noise(...), dt=0.1) gives other particles than "
                             f"propagate(dt=0.1) from the same random stream; propagation_noise must draw exactly "
                             f"what propagate draws first")
    for name, m in calls.sensors.items():
        said = "" if name is None else f"(sensor={name!r})"
        sampled = None
        if samples:
            sampled = _array(where, f"sample_observation{said}", _call(
                where, f"sample_observation{said}", lambda: calls.sample_observation(moved.copy(), 2, rng,
                                                                                     sensor=name)),
                (n, m), f"(N states by the sensor's {m} values)")
        if name in given:
            z = _observation(given[name], m, where)
            _likelihood(calls, where, prior, z, 1, n, f"no particle explains the first observation{said}", name)
        elif sampled is not None:
            _likelihood(calls, where, moved, sampled[0], 2, n,
                        f"no particle explains the observation{said} sampled from the first of them", name)
        moments = _call(where, f"observation_moments{said}",
                        lambda: calls.observation_moments(moved.copy(), 2, sensor=name))
        if moments is not None:
            if not isinstance(moments, (tuple, list)) or len(moments) != 2:
                raise ModelError(f"{where}: observation_moments{said} returned {_a(moments)}, expected None or "
                                 f"a pair (means (N, {m}), noise variances ({m},))")
            _array(where, f"observation_moments{said} means", moments[0], (n, m), f"(N particles by {m})")
            _array(where, f"observation_moments{said} variances", moments[1], (m,), f"({m} values)")


def load_checked(ref: str, *, observation=None, needs_sampling: bool | str = False) -> StateSpaceModel:
    """:func:`~dtpf.entity.model_ref.resolve` ``ref`` and :func:`check_model` it, once per (ref, needs_sampling)."""
    key = (ref, needs_sampling)
    with _LOCK:
        model = _CHECKED.get(key)
        if model is None:
            model = resolve(ref)
            check_model(model, observation=observation, needs_sampling=needs_sampling, ref=ref)
            _CHECKED[key] = model
        return model


# --- helpers ----------------------------------------------------------------------------------------------

def _where(model, ref: str | None) -> str:
    try:
        name = getattr(model, "name", None)
    except Exception:
        name = None
    if not isinstance(name, str) or not name:
        name = type(model).__name__
    if ref and ref != name:
        return f"model {name!r} (ref {ref})"
    return f"model {name!r}"


def _call(where: str, method: str, call):
    try:
        return call()
    except ModelError:
        raise
    except Exception as exc:
        lines = str(exc).strip().splitlines()
        text = f"{type(exc).__name__}: {lines[0].strip()}" if lines else type(exc).__name__
        raise ModelError(f"{where}: {method} raised {text}") from exc


def _array(where: str, method: str, value, shape: tuple, what: str) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` with finite entries, or a ModelError."""
    if value is None:
        raise ModelError(f"{where}: {method} returned None, expected an array of shape {shape} {what}")
    try:
        raw = np.asarray(value)
    except Exception as exc:
        raise ModelError(f"{where}: {method} returned {_a(value)} that is no array ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else ''}), expected shape {shape} {what}") from exc
    if raw.dtype.kind not in "biuf":
        raise ModelError(f"{where}: {method} returned dtype {raw.dtype}, expected float64-convertible numbers")
    if raw.shape != shape:
        raise ModelError(f"{where}: {method} returned shape {raw.shape}, expected {shape} {what}")
    x = raw.astype(np.float64, copy=False)
    bad = ~np.isfinite(x)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        shown = index[0] if len(index) == 1 else index
        raise ModelError(f"{where}: {method} returned {_kind(x[index])} at index {shown}, expected finite numbers")
    return x


def _likelihood(model, where: str, particles: np.ndarray, z: np.ndarray, k: int, n: int, unexplained: str,
                sensor=None):
    """``model``: the model, or its :class:`~dtpf.entity.calls.ModelCalls` (then with ``sensor``)."""
    if sensor is None:
        value = _call(where, "log_likelihood", lambda: model.log_likelihood(particles.copy(), z.copy(), k))
    else:
        value = _call(where, "log_likelihood", lambda: model.log_likelihood(particles.copy(), z.copy(), k,
                                                                            sensor=sensor))
    if value is None:
        raise ModelError(f"{where}: log_likelihood returned None, expected an array of shape ({n},) (one per particle)")
    raw = np.asarray(value)
    if raw.dtype.kind not in "biuf":
        raise ModelError(f"{where}: log_likelihood returned dtype {raw.dtype}, expected float64-convertible numbers")
    if raw.shape != (n,):
        raise ModelError(f"{where}: log_likelihood returned shape {raw.shape}, expected ({n},) (one per particle)")
    ll = raw.astype(np.float64, copy=False)
    for bad, kind in ((np.isnan(ll), "NaN"), (np.isposinf(ll), "+inf")):
        if bad.any():
            raise ModelError(f"{where}: log_likelihood returned {kind} at index {int(np.flatnonzero(bad)[0])}, "
                             f"expected finite numbers or -inf")
    if np.isneginf(ll).all():
        raise ModelError(f"{where}: log_likelihood is -inf for every probe particle: {unexplained}")
    return ll


def _observation(observation, obs_dim: int, where: str) -> np.ndarray:
    try:
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{where}: observation is not an array of numbers ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else ''})") from exc
    if z.size != obs_dim:
        raise ModelError(f"{where}: observation has {z.size} values, model observes {obs_dim}")
    if not np.isfinite(z).all():
        raise ModelError(f"{where}: observation has a non-finite value ({_kind(z[~np.isfinite(z)][0])}), "
                         f"expected {obs_dim} finite numbers")
    return z


def _kind(value: float) -> str:
    return "NaN" if np.isnan(value) else ("+inf" if value > 0 else "-inf")


def _a(value) -> str:
    if value is None:
        return "None"
    kind = type(value).__name__
    return f"{'an' if kind[0].lower() in 'aeiou' or kind == 'ndarray' else 'a'} {kind}"
