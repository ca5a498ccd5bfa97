"""Traditional resampling schemes (paper section 2.3).

The recommended import is::

    from dtpf.entity import resampling as rs
    ancestors = rs.systematic(weights, rng)
    particles = particles[ancestors]

Every scheme has the same contract, ``ancestors = scheme(weights, rng)``:

Parameters
----------
weights : (N,) array_like
    Normalised weights: finite, non-negative, summing to 1 (checked; a
    ValueError names what is wrong).
rng : numpy.random.Generator
    The only source of randomness; schemes never touch global state.

out : (N,) ndarray of int64, optional, keyword only
    Where to write the ancestors (C-contiguous, writeable); a new array if None.
checked : bool, keyword only
    The weights passed :func:`~dtpf.messages.arrays.check_weights` already (the
    filter normalised them, or a decoded message was checked): if they are
    a float64 vector they are not scanned again. Validation belongs where
    the weights are made, once per step, not in every kernel the step calls.

Returns
-------
ancestors : (N,) ndarray of int64
    Index of the parent of each new particle, in non-decreasing order
    (``out`` if given).

All four are unbiased: the expected number of copies of particle i is N w_i.
They differ in the variance of that number: multinomial (largest),
residual, stratified, systematic (smallest in practice).

Each scheme is one compiled pass (numba, :mod:`dtpf.entity._merge`) over the
particles that hands each particle the sorted points falling below its
running weight sum; the points are never searched for (``np.searchsorted``
costs a binary search per point and is 2-3x slower at N = 1e6), and the
merge writes each particle's first eight copies without a branch. With a
PCG64 generator (``np.random.default_rng``'s) the uniforms and exponentials
are drawn inside the pass from a copy of its state, which goes back into the
generator after. At N = 1e6 systematic takes 0.6 of one ``np.cumsum`` of the
weights, stratified 1.7, residual 2.6, multinomial 3.2;
``python -m dtpf.scripts.bench.resampling`` measures every scheme against that
floor. The numbers are those of the plain merge for the same seed, bit for
bit, and the generator ends where the plain merge leaves it
(``tests/test_resampling.py`` keeps the plain merge as the reference).
"""
from __future__ import annotations

from typing import Callable

import numba
import numpy as np

from dtpf.entity import _merge
from dtpf.messages.arrays import check_weights, is_plain_float64

__all__ = [
    "multinomial",
    "stratified",
    "systematic",
    "residual",
    "RESAMPLERS",
    "get",
    "inverse_cdf",
    "distinct",
    "gather",
]

Resampler = Callable[..., np.ndarray]

#: Below this many particles :func:`gather` stays on one thread: waking others costs more.
PARALLEL_GATHER = 1 << 17


def _weights(weights, checked: bool) -> np.ndarray:
    """The weights as a float64 vector: checked in full unless ``checked`` and already one."""
    if checked and is_plain_float64(weights, 1):
        return weights
    return check_weights(weights)


def _output(out, n: int) -> np.ndarray:
    """``out`` if it can hold N ancestors (C-contiguous, writeable int64 of shape (N,)), else a ValueError."""
    if out is None:
        return np.empty(n, dtype=np.int64)
    if not (isinstance(out, np.ndarray) and out.dtype == np.int64 and out.shape == (n,)
            and out.flags.c_contiguous and out.flags.writeable):
        raise ValueError(f"out must be a writeable C-contiguous int64 array of shape ({n},), got "
                         f"{getattr(out, 'dtype', type(out).__name__)} {getattr(out, 'shape', '')}")
    return out


def inverse_cdf(points, weights) -> np.ndarray:
    """Ancestors of sorted ``points`` in [0, 1): for each, the first i with cumsum(W)[i] > point.

    Parameters
    ----------
    points : (M,) array_like, non-decreasing, in [0, 1)
    weights : (N,) ndarray, normalised

    Notes
    -----
    The running sum can end a few ulps below 1; points in that gap go to
    the last particle with positive weight (the tail guard). Zero-weight
    particles are never chosen: the running sum does not grow across them.
    """
    p = np.ascontiguousarray(points, dtype=np.float64)
    return _merge.inverse_cdf(p, np.ascontiguousarray(weights, dtype=np.float64),
                              np.empty(p.size, dtype=np.int64))


def _exponential_merge(w: np.ndarray, rng: np.random.Generator, out: np.ndarray, plain, inline) -> np.ndarray:
    """``inline(w, words, out)`` on numpy's PCG64 stepped in the compiled pass, its state written back where
    ``rng.standard_exponential`` would leave it; ``plain(w, rng, out)`` for any other generator."""
    words = _merge.pcg_state(rng)
    if words is None:
        return plain(w, rng, out)
    inline(w, words, out)
    _merge.set_pcg_state(rng, words)
    return out


def multinomial(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Multinomial resampling: N i.i.d. draws from W, via ordered uniforms (Eq. 26).

    Eq. 26 builds the order statistics of M uniforms by the recursion
    u_M = v^(1/M), u_j = u_(j+1) v_j^(1/j). The same joint law comes from
    normalised partial sums of M + 1 standard exponentials ("uniform
    spacings"), which costs one exponential draw and one add per point
    instead of a log, a division and an exp; both are O(M). The draws are
    ``rng.standard_exponential(N + 1)``'s, made in the compiled pass.
    """
    w = _weights(weights, checked)
    return _exponential_merge(w, rng, _output(out, w.size), _merge.multinomial, _merge.multinomial_pcg)


def stratified(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Stratified resampling: one uniform in each stratum [(j-1)/N, j/N) (Eq. 27); draws ``rng.random(N)``."""
    w = _weights(weights, checked)
    out = _output(out, w.size)
    words = _merge.pcg_state(rng)
    if words is None:
        return _merge.stratified(w, rng.random(w.size), out)
    _merge.stratified_pcg(w, words, out)  # draws the uniforms as it merges, from a copy of the state
    rng.bit_generator.advance(w.size)  # where rng.random(N) leaves the PCG64
    return out


def systematic(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Systematic resampling (Kitagawa 1996): Eq. 27 with one uniform shared by all strata; draws ``rng.random()``."""
    w = _weights(weights, checked)
    return _merge.systematic(w, rng.random(), _output(out, w.size))


def residual(weights, rng: np.random.Generator, *, out=None, checked: bool = False) -> np.ndarray:
    """Residual resampling (Liu and Chen 1998).

    Particle i first gets floor(N w_i) copies; the R remaining offspring are
    drawn multinomially (Eq. 26) from the residual weights
    N w_i - floor(N w_i), normalised; draws ``rng.standard_exponential(R + 1)``.
    """
    w = _weights(weights, checked)
    return _exponential_merge(w, rng, _output(out, w.size), _merge.residual, _merge.residual_pcg)


def gather(particles: np.ndarray, ancestors: np.ndarray, out: np.ndarray | None = None, *,
           threads: int = 1) -> np.ndarray:
    """The resampled set ``particles[ancestors]`` of an (N, d) float64 set, into ``out`` if given.

    ``threads`` > 1: from PARALLEL_GATHER particles on, the rows are copied on that many of
    numba's threads, the same array whatever their number. It does not pay on the 2-core machine of ``dtpf.scripts.bench.resampling`` while
    anything else runs there (2 threads were slower than one at large N), so the filter gathers on one.
    """
    x = np.ascontiguousarray(particles, dtype=np.float64)
    a = np.ascontiguousarray(ancestors, dtype=np.int64)
    if out is None:
        out = np.empty((a.size,) + x.shape[1:])
    if threads <= 1 or a.size < PARALLEL_GATHER:
        return np.take(x, a, axis=0, out=out)
    previous = numba.get_num_threads()
    numba.set_num_threads(min(int(threads), numba.config.NUMBA_NUM_THREADS))
    try:
        return _merge.gather_parallel(x, a, out)
    finally:
        numba.set_num_threads(previous)


def distinct(ancestors: np.ndarray) -> int:
    """Number of distinct values in sorted ``ancestors`` (the parents of the resampled set)."""
    return int(_merge.distinct(ancestors))


#: Registry of the traditional schemes by name.
RESAMPLERS: dict[str, Resampler] = {
    "multinomial": multinomial,
    "stratified": stratified,
    "systematic": systematic,
    "residual": residual,
}


def get(name: str) -> Resampler:
    """The resampling scheme called ``name``, or a ValueError listing the valid names."""
    try:
        return RESAMPLERS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown resampler {name!r}; expected one of {', '.join(RESAMPLERS)}"
        ) from None
