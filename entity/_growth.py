"""Compiled laws of the growth model (Eq. 35, 36), one pass each, no temporary arrays.

Each kernel does the floating-point operations of the numpy expressions in
:class:`dtpf.entity.models.GrowthModel` in the same order (numba compiles without
fast-math, so nothing is contracted or reassociated): the same numbers, bit
for bit. The normal draws are numba's port of numpy's
``Generator.standard_normal``, which gives the same sequence as
``rng.standard_normal(N)`` and is about 3x faster at N = 1e6.

:func:`propagate` and :func:`log_likelihood` are element-wise: from
:data:`dtpf.entity.cores.PARALLEL_MIN` particles on they share the set among
the process's threads, with the same numbers.
"""
from __future__ import annotations

import numba
import numpy as np

from dtpf.entity import cores

#: From this many draws on, the kernels draw the normals themselves; below it numpy does, because
#: handing a Generator to a compiled function has a fixed cost (numba builds its ctypes view).
COMPILED_DRAWS = 2048


@numba.njit(cache=True, nogil=True)
def normals(rng, out):  # pragma: no cover - compiled
    # out[:] = rng.standard_normal(out.shape), in C order.
    flat = out.reshape(out.size)
    for i in range(flat.shape[0]):
        flat[i] = rng.standard_normal()
    return out


@numba.njit(inline="always")
def _mean(x, growth, drift):  # pragma: no cover - compiled
    # Eq. 35 without its noise: 0.5 x + c x / (1 + x^2) + 8 cos(1.2 (k - 1)).
    return 0.5 * x + growth * x / (1.0 + x * x) + drift


@numba.njit(cache=True, nogil=True)
def _propagate(particles, noise, scale, growth, drift):  # pragma: no cover - compiled
    # noise <- noise * sqrt(Q) + mean(x), in place (Eq. 35); the propagated particles.
    for i in range(particles.shape[0]):
        for c in range(particles.shape[1]):
            noise[i, c] = noise[i, c] * scale + _mean(particles[i, c], growth, drift)
    return noise


@numba.njit(cache=True, nogil=True, parallel=True)
def _propagate_parallel(particles, noise, scale, growth, drift, chunk):  # pragma: no cover - compiled
    # _propagate on the threads, chunk by chunk: each element's operations are the same, so are the numbers.
    # (Each chunk a call on slices: a loop written inline in a parallel loop ran 2x slower a thread.)
    n = particles.shape[0]
    for b in numba.prange((n + chunk - 1) // chunk):
        start, end = b * chunk, min(n, (b + 1) * chunk)
        _propagate(particles[start:end], noise[start:end], scale, growth, drift)
    return noise


def propagate(particles, noise, scale, growth, drift):
    """noise <- noise * sqrt(Q) + mean(x) in place (Eq. 35), the propagated particles; on the process's
    threads from PARALLEL_MIN particles on (the same numbers)."""
    if cores.parallel(particles.shape[0]):
        return _propagate_parallel(particles, noise, scale, growth, drift, cores.CHUNK)
    return _propagate(particles, noise, scale, growth, drift)


@numba.njit(cache=True, nogil=True)
def propagate_drawing(particles, rng, scale, growth, drift):  # pragma: no cover - compiled
    # propagate(particles, rng.standard_normal(particles.shape), ...) without the noise array.
    out = np.empty_like(particles)
    for i in range(particles.shape[0]):
        for c in range(particles.shape[1]):
            out[i, c] = rng.standard_normal() * scale + _mean(particles[i, c], growth, drift)
    return out


@numba.njit(inline="always")
def _log_density(x, z, variance, constant):  # pragma: no cover - compiled
    # log N(z; x^2 / 20, R) (Eq. 36): -0.5 r r / R - 0.5 log(2 pi R), r = z - x^2 / 20.
    residual = z - x * x / 20.0
    return -0.5 * residual * residual / variance - constant


@numba.njit(cache=True, nogil=True)
def _log_likelihood(particles, z, variance, constant):  # pragma: no cover - compiled
    out = np.empty(particles.shape[0])
    for i in range(particles.shape[0]):
        out[i] = _log_density(particles[i, 0], z, variance, constant)
    return out


@numba.njit(cache=True, nogil=True)
def _log_likelihood_into(particles, z, variance, constant, out):  # pragma: no cover - compiled
    for i in range(particles.shape[0]):
        out[i] = _log_density(particles[i, 0], z, variance, constant)


@numba.njit(cache=True, nogil=True, parallel=True)
def _log_likelihood_parallel(particles, z, variance, constant, chunk):  # pragma: no cover - compiled
    # Each chunk a call on slices (a loop written inline in a parallel loop ran 2x slower a thread).
    n = particles.shape[0]
    out = np.empty(n)
    for b in numba.prange((n + chunk - 1) // chunk):
        start, end = b * chunk, min(n, (b + 1) * chunk)
        _log_likelihood_into(particles[start:end], z, variance, constant, out[start:end])
    return out


def log_likelihood(particles, z, variance, constant):
    """log N(z; x^2 / 20, R) per particle (Eq. 36), (N,); on the process's threads from PARALLEL_MIN
    particles on (the same numbers)."""
    if cores.parallel(particles.shape[0]):
        return _log_likelihood_parallel(particles, z, variance, constant, cores.CHUNK)
    return _log_likelihood(particles, z, variance, constant)
