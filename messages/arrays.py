"""Validation of the arrays every layer exchanges: weights and particles.

The algorithms (resampling, preprocessing rules, mirror) and the message
decoders share these checks, so a bad weight vector is rejected with the same
words wherever it appears::

    from dtpf.messages.arrays import check_weights, check_particles
    weights = check_weights(weights)            # (N,) float64, sums to 1
    particles = check_particles(particles, n=len(weights))   # (N, d) float64
    particles, weights = check_set(particles, weights)       # both at once

Every failure raises :class:`ValueError` naming the problem and the value.
"""
from __future__ import annotations

import re
import warnings

import numpy as np

# A NaN or an infinity in hostile input makes the fast paths' sums below warn ("invalid value" or "overflow
# encountered in reduce"); the full passes then name the value in the error, or find every value finite
# (a sum that overflowed), so the warning says nothing and a service would print it to its log: not shown.
warnings.filterwarnings("ignore", r"(invalid value|overflow) encountered in reduce", RuntimeWarning,
                        re.escape(__name__))

#: From this many values on, the checks' two reductions run in parts on :func:`set_check_threads` threads
#: (numpy releases the GIL in them); below it, or on one thread, in one call. A pool of their own, not
#: dtpf.entity.cores.in_parts: the messages import nothing of the layers.
PARALLEL_CHECK = 1 << 18
_CHECK_THREADS = [1]
_POOLS: dict = {}


def set_check_threads(count: int) -> None:
    """Threads the checks of large arrays run on (:func:`dtpf.entity.cores.set_threads` sets the process's
    count here too); 1, the default, checks in one call on the calling thread."""
    _CHECK_THREADS[0] = max(1, int(count))


def _reduced(values: np.ndarray, ufuncs) -> list[float]:
    """Each of ``ufuncs``' reductions of all of ``values`` (cut along its first axis into parts on the check
    threads for a large array; the parts' results reduced again: for the checks' decisions, not numbers)."""
    count = min(_CHECK_THREADS[0], values.shape[0])
    if count <= 1 or values.size < PARALLEL_CHECK:
        with np.errstate(invalid="ignore", over="ignore"):
            return [float(ufunc.reduce(values, axis=None)) for ufunc in ufuncs]
    pool = _POOLS.get(count)
    if pool is None:
        from concurrent.futures import ThreadPoolExecutor
        pool = _POOLS[count] = ThreadPoolExecutor(max_workers=count - 1, thread_name_prefix="dtpf-checks")
    bounds = [values.shape[0] * p // count for p in range(count + 1)]

    def part(p: int) -> list:
        chunk = values[bounds[p]:bounds[p + 1]]
        with np.errstate(invalid="ignore", over="ignore"):
            return [ufunc.reduce(chunk, axis=None) for ufunc in ufuncs]

    futures = [pool.submit(part, p) for p in range(1, count)]
    results = [part(0)] + [future.result() for future in futures]
    with np.errstate(invalid="ignore", over="ignore"):
        return [float(ufunc.reduce(np.array([result[i] for result in results]))) for i, ufunc in enumerate(ufuncs)]


#: Relative tolerance on ``sum(weights) == 1`` for normalised weights.
#: Summing N float64 values loses at most about N * 2**-53 relative, so 1e-6
#: leaves room for N up to 1e9 while still catching unnormalised input.
SUM_TOLERANCE = 1e-6


def _describe(values: np.ndarray, mask: np.ndarray) -> str:
    """Say where the first bad entries are: 'at index 3 (value nan)'."""
    bad = np.flatnonzero(mask)
    first = int(bad[0])
    more = f" and {bad.size - 1} more" if bad.size > 1 else ""
    return f"at index {first} (value {float(values.flat[first])!r}){more}"


def check_weights(weights, *, normalised: bool = True, name: str = "weights") -> np.ndarray:
    """Return ``weights`` as a 1-D float64 array, or raise ValueError.

    Parameters
    ----------
    weights : array_like, (N,)
        Non-negative, finite, not all zero.
    normalised : bool
        Also require ``sum(weights) == 1`` within :data:`SUM_TOLERANCE`.
    name : str
        What to call the array in error messages.
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {w.shape}")
    if w.size == 0:
        raise ValueError(f"{name} is empty")
    # Two reductions decide the usual case: a NaN makes the minimum NaN, a negative value makes it
    # negative, an infinite value makes the sum infinite. Anything else takes the passes below.
    smallest, total = _reduced(w, (np.minimum, np.add))  # w.min(), w.sum(), called here
    if smallest >= 0.0 and np.isfinite(total):
        if total <= 0.0:
            raise ValueError(f"{name} are all zero (N={w.size})")
        if normalised and abs(total - 1.0) > SUM_TOLERANCE:
            raise ValueError(f"{name} must sum to 1 (within {SUM_TOLERANCE:g}), got sum {total!r}")
        return w
    finite = np.isfinite(w)
    if not finite.all():
        kind = "NaN" if np.isnan(w).any() else "infinite"
        raise ValueError(f"{name} contain {kind} values {_describe(w, ~finite)}")
    negative = w < 0
    if negative.any():
        raise ValueError(f"{name} contain negative values {_describe(w, negative)}")
    total = float(w.sum())
    if total <= 0.0:
        raise ValueError(f"{name} are all zero (N={w.size})")
    if normalised and abs(total - 1.0) > SUM_TOLERANCE:
        raise ValueError(f"{name} must sum to 1 (within {SUM_TOLERANCE:g}), got sum {total!r}")
    return w


def check_particles(particles, *, n: int | None = None, name: str = "particles") -> np.ndarray:
    """Return ``particles`` as an (N, d) float64 array, or raise ValueError.

    A 1-D array of length N is read as N particles of dimension 1.

    Parameters
    ----------
    particles : array_like, (N,) or (N, d)
        Finite states.
    n : int, optional
        Required number of particles (the length of the weights).
    """
    x = np.asarray(particles, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2:
        raise ValueError(f"{name} must have shape (N,) or (N, d), got shape {x.shape}")
    if x.shape[0] == 0 or x.shape[1] == 0:
        raise ValueError(f"{name} is empty (shape {x.shape})")
    if n is not None and x.shape[0] != n:
        raise ValueError(f"{name} and weights differ in length: {x.shape[0]} particles, {n} weights")
    if np.isfinite(_reduced(x, (np.add,))[0]):  # a NaN or an infinity makes the sum non-finite
        return x
    finite = np.isfinite(x)
    if not finite.all():
        raise ValueError(f"{name} contain non-finite values {_describe(x, ~finite)}")
    return x


def is_plain_float64(value, ndim: int) -> bool:
    """Whether ``value`` is a non-empty float64 ndarray of rank ``ndim``: what an already checked
    array must still be for :func:`check_set` (and a message built from checked arrays) to pass it unscanned."""
    return isinstance(value, np.ndarray) and value.dtype == np.float64 and value.ndim == ndim and value.size > 0


def check_set(particles, weights, *, checked: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(particles, weights)`` of one particle set, checked: (N, d) and (N,) float64.

    ``checked=True``: the arrays passed these checks already (the arrays of a
    decoded message, or a layer's own output); if they are float64 arrays of
    the right ranks and lengths they are returned as they are, without a
    second scan of every value. Anything else is checked in full.
    """
    if (checked and is_plain_float64(particles, 2) and is_plain_float64(weights, 1)
            and particles.shape[0] == weights.shape[0]):
        return particles, weights
    w = check_weights(weights)
    return check_particles(particles, n=w.size), w


def check_probability(value, name: str) -> float:
    """Return ``value`` as a float in [0, 1], or raise ValueError (used for PS)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number in [0, 1], got {value!r}") from None
    if not (0.0 <= v <= 1.0):  # also rejects NaN
        raise ValueError(f"{name} must be in [0, 1], got {value!r}")
    return v
