"""Traditional resampling schemes (paper section 2.3).

The recommended import is::

    from dtpf.entity import resampling as rs
    ancestors = rs.systematic(weights, rng)
    particles = particles[ancestors]

Every scheme has the same contract, ``ancestors = scheme(weights, rng)``, stated once in
:mod:`dtpf.entity.resamplers.base`: normalised weights (N,) and a numpy Generator in, N int64 ancestor
indices in non-decreasing order out (keyword-only ``out=`` and ``checked=`` for the filter's hot path).

Every built-in is unbiased: the expected number of copies of particle i is
N w_i. They differ in the variance of that number: multinomial (largest),
residual, stratified, systematic (smallest in practice). :data:`RESAMPLERS`
holds them by name; each is a module of :mod:`dtpf.entity.resamplers`, and
:func:`get` also takes a user's resampler by reference
(``path/to/file.py:NAME``, ``package.module:NAME``) or by the name an
installed package registers in the entry-point group ``dtpf.resamplers``.

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

from dtpf.entity import _merge, cores
from dtpf.entity.resamplers.multinomial import multinomial
from dtpf.entity.resamplers.residual import residual
from dtpf.entity.resamplers.stratified import stratified
from dtpf.entity.resamplers.systematic import systematic
from dtpf.messages.family import RESAMPLERS as FAMILY

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
    "systematic_blocks",
]

Resampler = Callable[..., np.ndarray]

#: Below this many particles :func:`gather` stays on one thread: waking others costs more.
PARALLEL_GATHER = cores.PARALLEL_MIN


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


def gather(particles: np.ndarray, ancestors: np.ndarray, out: np.ndarray | None = None, *,
           threads: int | None = None) -> np.ndarray:
    """The resampled set ``particles[ancestors]`` of an (N, d) float64 set, into ``out`` if given.

    ``threads``: from PARALLEL_GATHER particles on, the rows are copied on that many of numba's threads
    (None: the process's, :mod:`dtpf.entity.cores`), the same array whatever their number.
    """
    x = np.ascontiguousarray(particles, dtype=np.float64)
    a = np.ascontiguousarray(ancestors, dtype=np.int64)
    if out is None:
        out = np.empty((a.size,) + x.shape[1:])
    count = cores.threads() if threads is None else int(threads)
    if count <= 1 or a.size < PARALLEL_GATHER:
        return np.take(x, a, axis=0, out=out)
    previous = numba.get_num_threads()
    numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))
    numba.set_parallel_chunksize(1)  # threads take chunks one at a time
    try:
        return _merge.gather_parallel(x, a, out)
    finally:
        numba.set_num_threads(previous)


def systematic_blocks(weights: np.ndarray, rng: np.random.Generator, block: int, *,
                      out: np.ndarray | None = None) -> np.ndarray:
    """Systematic resampling of normalised, checked ``weights`` in blocks of ``block`` particles on the
    process's threads (:mod:`dtpf.entity.cores`): the running sum of a particle is its block's offset (the
    blocks' sums before it, in block order) plus its sum inside the block, so the ancestors are the same for
    any thread count; for N <= ``block``, :func:`systematic`'s. Draws ``rng.random()``, as systematic."""
    w = np.ascontiguousarray(weights, dtype=np.float64)
    out = np.empty(w.size, dtype=np.int64) if out is None else out
    u = rng.random()
    if cores.blocks(w.size, block) == 1:
        return _merge.systematic(w, u, out)
    cores.use(w.size)
    return _merge.systematic_blocks(w, u, int(block), out)


def distinct(ancestors: np.ndarray) -> int:
    """Number of distinct values in sorted ``ancestors`` (the parents of the resampled set); on the process's
    threads from PARALLEL_MIN on (an integer count: the same)."""
    if cores.parallel(ancestors.shape[0]):
        return int(_merge.distinct_parallel(ancestors, cores.CHUNK))
    return int(_merge.distinct(ancestors))


#: The built-in schemes by name (every module of :mod:`dtpf.entity.resamplers`).
RESAMPLERS: dict[str, Resampler] = FAMILY.builtins()


def get(name: str) -> Resampler:
    """The resampler ``name`` names: a built-in, an installed package's, or a user's reference; a
    ValueError (:class:`~dtpf.messages.references.ReferenceLoadError`) listing the valid names."""
    return FAMILY.get(name)
