"""The filter's passes over a set in blocks (:mod:`dtpf.entity.cores`): one job each, the same numbers for
any thread count.

A set of N > B particles (B the run's ``block_particles``) is cut into blocks of B; every sum adds the
blocks' partial sums in block order (a block's sum: four running sums over its elements i = 0, 1, 2, 3
mod 4 from its start, then (s0 + s1) + (s2 + s3): four chains the processor runs side by side), and block b >= 1 draws its propagation noise from its own stream
(:func:`dtpf.messages.streams.block_stream`), block 0 from the step's. The filter calls these only for
more than one block; one block is the filter's own code, so the numbers of N <= B do not change::

    weights, log_total, top, ess = blocks.normalise(log_weights, 65_536, float(np.max(log_weights)))
    mean, var = blocks.moments(particles, weights, 65_536)
"""
from __future__ import annotations

import numba
import numpy as np

from dtpf.entity import cores
from dtpf.messages.streams import block_stream

__all__ = ["normalise", "moments", "noise", "copy", "fill", "largest"]


def copy(out: np.ndarray, values: np.ndarray) -> None:
    """out[:] = values (1-D), in parts on the process's threads (a copy: the same for any cut)."""
    cores.in_parts(out.shape[0], lambda start, end: np.copyto(out[start:end], values[start:end]))


def largest(values: np.ndarray) -> float:
    """max(values) (1-D; NaN if any is NaN), each part's on a thread (a maximum: the same for any cut)."""
    n = values.size
    count = max(1, min(cores.threads(), n)) if n >= cores.PARALLEL_MIN else 1
    tops = np.empty(count)

    def top(p: int) -> None:
        tops[p] = np.max(values[n * p // count:n * (p + 1) // count])

    cores.in_parts(count, lambda first, last: [top(p) for p in range(first, last)], count)
    return float(np.max(tops))


def fill(out: np.ndarray, value: float) -> None:
    """out[:] = value (1-D), in parts on the process's threads."""
    cores.in_parts(out.shape[0], lambda start, end: out[start:end].fill(value))


@numba.njit(inline="always")
def _bounds(n, block, b):  # pragma: no cover - compiled
    return b * block, min(n, (b + 1) * block)


# Each parallel loop calls a compiled function on its block's slices: a loop written inline in a parallel
# loop ran 1.6-2x slower a thread.

@numba.njit(cache=True, nogil=True)
def _sum(values):  # pragma: no cover - compiled
    # sum(values) in the module's order: four running sums, (s0 + s1) + (s2 + s3).
    s0 = s1 = s2 = s3 = 0.0
    i, end = 0, values.shape[0]
    while i + 4 <= end:
        s0 += values[i]
        s1 += values[i + 1]
        s2 += values[i + 2]
        s3 += values[i + 3]
        i += 4
    while i < end:
        s0 += values[i]
        i += 1
    return (s0 + s1) + (s2 + s3)


@numba.njit(cache=True, nogil=True)
def _divide_squares(weights, total):  # pragma: no cover - compiled
    # weights /= total in place; sum w^2 of the result in the module's order.
    s0 = s1 = s2 = s3 = 0.0
    i, end = 0, weights.shape[0]
    while i + 4 <= end:
        w0, w1, w2, w3 = weights[i] / total, weights[i + 1] / total, weights[i + 2] / total, weights[i + 3] / total
        weights[i], weights[i + 1], weights[i + 2], weights[i + 3] = w0, w1, w2, w3
        s0 += w0 * w0
        s1 += w1 * w1
        s2 += w2 * w2
        s3 += w3 * w3
        i += 4
    while i < end:
        w0 = weights[i] / total
        weights[i] = w0
        s0 += w0 * w0
        i += 1
    return (s0 + s1) + (s2 + s3)


@numba.njit(cache=True, nogil=True, parallel=True)
def _total(values, block):  # pragma: no cover - compiled
    # sum(values): each block's sum on a thread, added in block order.
    n = values.shape[0]
    count = (n + block - 1) // block
    sums = np.empty(count)
    for b in numba.prange(count):
        start, end = _bounds(n, block, b)
        sums[b] = _sum(values[start:end])
    total = 0.0
    for b in range(count):
        total += sums[b]
    return total


@numba.njit(cache=True, nogil=True, parallel=True)
def _divide(weights, total, block):  # pragma: no cover - compiled
    # weights /= total in place, and sum w^2 of the result (Eq. 25), per block, added in block order.
    n = weights.shape[0]
    count = (n + block - 1) // block
    sums = np.empty(count)
    for b in numba.prange(count):
        start, end = _bounds(n, block, b)
        sums[b] = _divide_squares(weights[start:end], total)
    square = 0.0
    for b in range(count):
        square += sums[b]
    return square


def normalise(log_weights: np.ndarray, block: int, top: float) -> tuple[np.ndarray, float, float, float]:
    """(normalised weights, log sum_i exp(log w_i), ``top``, ESS) of (N,) log-weights whose largest is
    ``top``, finite (Eq. 23 normalised, shifted by the maximum; ESS of Eq. 25), the sums per block of
    ``block``."""
    weights = np.empty_like(log_weights)

    def exponentials(start: int, end: int) -> None:  # numpy's exp, element by element: any cut
        part = weights[start:end]
        np.subtract(log_weights[start:end], top, out=part)
        np.exp(part, out=part)

    cores.in_parts(weights.size, exponentials)
    cores.use(weights.size)
    total = _total(weights, int(block))
    square = _divide(weights, total, int(block))
    return weights, top + float(np.log(total)), top, 1.0 / square


@numba.njit(cache=True, nogil=True)
def _weighted(particles, weights, c):  # pragma: no cover - compiled
    # sum_i w_i x_ic, in the module's order.
    s0 = s1 = s2 = s3 = 0.0
    i, end = 0, weights.shape[0]
    while i + 4 <= end:
        s0 += weights[i] * particles[i, c]
        s1 += weights[i + 1] * particles[i + 1, c]
        s2 += weights[i + 2] * particles[i + 2, c]
        s3 += weights[i + 3] * particles[i + 3, c]
        i += 4
    while i < end:
        s0 += weights[i] * particles[i, c]
        i += 1
    return (s0 + s1) + (s2 + s3)


@numba.njit(cache=True, nogil=True)
def _weighted_squares(particles, weights, c, mean):  # pragma: no cover - compiled
    # sum_i w_i (x_ic - mean)^2, in the module's order.
    s0 = s1 = s2 = s3 = 0.0
    i, end = 0, weights.shape[0]
    while i + 4 <= end:
        e0, e1 = particles[i, c] - mean, particles[i + 1, c] - mean
        e2, e3 = particles[i + 2, c] - mean, particles[i + 3, c] - mean
        s0 += weights[i] * (e0 * e0)
        s1 += weights[i + 1] * (e1 * e1)
        s2 += weights[i + 2] * (e2 * e2)
        s3 += weights[i + 3] * (e3 * e3)
        i += 4
    while i < end:
        e0 = particles[i, c] - mean
        s0 += weights[i] * (e0 * e0)
        i += 1
    return (s0 + s1) + (s2 + s3)


@numba.njit(cache=True, nogil=True, parallel=True)
def _moments(particles, weights, block):  # pragma: no cover - compiled
    # The weighted mean, then the weighted variance about it, per component: per block, added in block order.
    # No np.zeros here: in a parallel function it is a parallel loop, which threads taking one iteration at
    # a time (dtpf.entity.cores) would run element by element.
    n, d = particles.shape
    count = (n + block - 1) // block
    sums = np.empty((count, d))
    for b in numba.prange(count):
        start, end = _bounds(n, block, b)
        for c in range(d):
            sums[b, c] = _weighted(particles[start:end], weights[start:end], c)
    mean = _sum_rows(sums)
    squares = np.empty((count, d))
    for b in numba.prange(count):
        start, end = _bounds(n, block, b)
        for c in range(d):
            squares[b, c] = _weighted_squares(particles[start:end], weights[start:end], c, mean[c])
    return mean, _sum_rows(squares)


@numba.njit(cache=True, nogil=True)
def _sum_rows(partial):  # pragma: no cover - compiled
    # The rows of (blocks, d) partial sums added in block order.
    total = np.zeros(partial.shape[1])
    for b in range(partial.shape[0]):
        for c in range(partial.shape[1]):
            total[c] += partial[b, c]
    return total


def moments(particles: np.ndarray, weights: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean and variance per component, (d,), (d,), the sums per block of ``block``."""
    cores.use(particles.shape[0])
    return _moments(np.ascontiguousarray(particles, dtype=np.float64), weights, int(block))


def noise(model, n: int, k: int, rng: np.random.Generator, block: int, key: tuple[int, str]) -> np.ndarray | None:
    """The propagation noise of step k, (N, d), block by block: block 0's ``model.propagation_noise(B, k,
    rng)`` from the step's stream, block b's from ``block_stream(seed, twin, k, "entity", b)`` (``key`` is
    (seed, twin)); the blocks drawn on the process's threads (a compiled model's draws release the GIL).
    None when the model draws no noise apart (``propagation_noise`` gives None): it then propagates on the
    step's stream alone."""
    count = cores.blocks(n, block)
    dim = getattr(model, "dim", None)
    out = np.empty((n, dim)) if isinstance(dim, int) else None
    #: Per block: True (written into out), False (the model draws no noise apart), or its array (another shape).
    results: list = [None] * count
    seed, twin = key

    def draw(b: int) -> None:
        start, end = b * block, min(n, (b + 1) * block)
        values = model.propagation_noise(end - start, k, rng if b == 0 else block_stream(seed, twin, k, "entity", b))
        if values is None:
            results[b] = False
            return
        values = np.asarray(values, dtype=np.float64)
        if out is not None and values.shape == (end - start, dim):
            out[start:end] = values
            results[b] = True
        else:
            results[b] = values

    # Block 0 on the calling thread with the first blocks: the step's stream is drawn from nowhere else.
    cores.in_parts(count, lambda first, last: [draw(b) for b in range(first, last)],
                   cores.threads() if n >= cores.PARALLEL_MIN else 1)
    if any(result is False for result in results):
        return None
    if all(result is True for result in results):
        return out
    return np.concatenate([out[b * block:min(n, (b + 1) * block)] if result is True else result
                           for b, result in enumerate(results)])
