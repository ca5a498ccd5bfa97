"""The contract of a resampler, and the checks a user's resampler passes before a run.

Every resampler has the form ``ancestors = resample(weights, rng)``:

Parameters
----------
weights : (N,) array_like
    Normalised weights: finite, non-negative, summing to 1 (checked; a
    ValueError names what is wrong).
rng : numpy.random.Generator
    The only source of randomness; a resampler never touches global state.

out : (N,) ndarray of int64, optional, keyword only
    Where to write the ancestors (C-contiguous, writeable); a new array if None.
checked : bool, keyword only
    The weights passed :func:`~dtpf.messages.arrays.check_weights` already (the
    filter normalised them, or a decoded message was checked): if they are
    a float64 vector they are not scanned again.

Returns
-------
ancestors : (N,) ndarray of int64
    Index of the parent of each new particle, in non-decreasing order
    (``out`` if given). Must not change ``weights``.

A resampler is *unbiased* when the expected number of copies of particle i
is N w_i; every built-in is. A user's resampler may be a plain function of
two arguments, ``f(weights, rng) -> ancestors`` (the form textbooks and the
``particles`` library use): :func:`adapt` wraps it into the form above,
checks its output at every call (length, integers in range: one line naming
what is wrong) and sorts it. Before a run it is tried on a small case
(:func:`check_unbiased`): a resampler that draws a particle of weight 0, or
whose mean offspring counts over :data:`BIAS_DRAWS` draws differ from N w_i
by more than :data:`BIAS_Z` standard errors, is refused with the measured bias.

A built-in is a module of this package that registers its function with
``@RESAMPLERS.builtin("name")`` (:mod:`dtpf.messages.family`).
"""
from __future__ import annotations

import math

import numpy as np

from dtpf.entity import _merge
from dtpf.messages import references
from dtpf.messages.arrays import check_weights, is_plain_float64
from dtpf.messages.family import RESAMPLERS
from dtpf.messages.references import ReferenceLoadError, a

__all__ = ["RESAMPLERS", "checked_weights", "output_buffer", "exponential_merge", "adapt", "check_unbiased", "BIAS_DRAWS", "BIAS_Z", "BiasedResamplerError"]

#: Draws of the bias check, and the largest |z| of a particle's mean offspring count it accepts: with 8
#: particles a correct resampler is refused with probability below 8 x 6e-7 (the normal tail beyond 5).
BIAS_DRAWS = 4000
BIAS_Z = 5.0
#: The weights of the bias check: unequal, one of them 0, so that a resampler ignoring them shows.
BIAS_WEIGHTS = np.array([0.30, 0.02, 0.17, 0.0, 0.11, 0.25, 0.05, 0.10])


class BiasedResamplerError(ReferenceLoadError):
    """A user's resampler draws particles in proportions other than their weights (measured, one line)."""


def checked_weights(weights, checked: bool) -> np.ndarray:
    """The weights as a float64 vector: checked in full unless ``checked`` and already one."""
    if checked and is_plain_float64(weights, 1):
        return weights
    return check_weights(weights)


def output_buffer(out, n: int) -> np.ndarray:
    """``out`` if it can hold N ancestors (C-contiguous, writeable int64 of shape (N,)), else a ValueError."""
    if out is None:
        return np.empty(n, dtype=np.int64)
    if not (isinstance(out, np.ndarray) and out.dtype == np.int64 and out.shape == (n,)
            and out.flags.c_contiguous and out.flags.writeable):
        raise ValueError(f"out must be a writeable C-contiguous int64 array of shape ({n},), got "
                         f"{getattr(out, 'dtype', type(out).__name__)} {getattr(out, 'shape', '')}")
    return out


def exponential_merge(w: np.ndarray, rng: np.random.Generator, out: np.ndarray, plain, inline) -> np.ndarray:
    """``inline(w, words, out)`` on numpy's PCG64 stepped in the compiled pass, its state written back where
    ``rng.standard_exponential`` would leave it; ``plain(w, rng, out)`` for any other generator."""
    words = _merge.pcg_state(rng)
    if words is None:
        return plain(w, rng, out)
    inline(w, words, out)
    _merge.set_pcg_state(rng, words)
    return out


def adapt(obj, where: str):
    """A user's resampler in the contract's form, checked on a small case (see the module docstring)."""
    references.function_of(obj, where, "a resampler", "(weights, rng) -> ancestors", ("weights", "rng"))
    resampler = _Checked(obj, where)
    check_unbiased(resampler, where)
    return resampler


class _Checked:
    """A user's ``f(weights, rng)`` in the contract's form: its output checked, made int64 and sorted."""

    def __init__(self, function, where: str):
        self.function, self.where = function, where
        self.__name__ = getattr(function, "__name__", "resampler")
        self.__doc__ = getattr(function, "__doc__", None)

    def __call__(self, weights, rng, *, out=None, checked: bool = False) -> np.ndarray:
        w = checked_weights(weights, checked)
        n = w.size
        try:
            result = self.function(w.copy() if not w.flags.writeable else w, rng)
        except Exception as exc:
            raise ReferenceLoadError(f"{self.where} raised {type(exc).__name__}: {exc}") from exc
        ancestors = np.asarray(result)
        if ancestors.shape != (n,):
            raise ReferenceLoadError(f"{self.where} returned {a(result)} of shape {ancestors.shape}, expected "
                                     f"({n},) ancestor indices")
        if not np.issubdtype(ancestors.dtype, np.integer):
            raise ReferenceLoadError(f"{self.where} returned {ancestors.dtype} values, expected integer "
                                     f"ancestor indices")
        if n and (ancestors.min() < 0 or ancestors.max() >= n):
            raise ReferenceLoadError(f"{self.where} returned an ancestor out of range: "
                                     f"{int(ancestors.min())} .. {int(ancestors.max())}, expected 0 .. {n - 1}")
        target = output_buffer(out, n)
        target[:] = ancestors
        if n > 1 and not np.all(target[1:] >= target[:-1]):
            target.sort()
        return target


def check_unbiased(resampler, where: str, *, draws: int = BIAS_DRAWS, seed: int = 20261204) -> None:
    """Refuse ``resampler`` if it draws a zero-weight particle or its mean offspring counts over ``draws``
    draws on :data:`BIAS_WEIGHTS` differ from N w_i by more than :data:`BIAS_Z` standard errors (the
    sample standard deviation of the counts over sqrt(draws); a scheme whose counts never vary must hit N w_i
    to 1e-9)."""
    weights = BIAS_WEIGHTS / BIAS_WEIGHTS.sum()
    n = weights.size
    rng = np.random.default_rng(seed)
    counts = np.empty((draws, n))
    try:
        for i in range(draws):
            counts[i] = np.bincount(resampler(weights, rng), minlength=n)
    except ReferenceLoadError as error:
        raise ReferenceLoadError(f"{error} (tried on {n} weights before the run)") from None
    zero = np.flatnonzero((weights == 0) & (counts.sum(axis=0) > 0))
    if zero.size:
        raise BiasedResamplerError(f"{where} is biased: it drew particle {int(zero[0])} of weight 0 "
                                   f"{int(counts[:, zero[0]].sum())} times in {draws} draws")
    mean, expected = counts.mean(axis=0), n * weights
    error = np.sqrt(counts.var(axis=0, ddof=1) / draws)
    gap = np.abs(mean - expected)
    z = np.where(error > 0, gap / np.where(error > 0, error, 1.0), np.where(gap > 1e-9, math.inf, 0.0))
    worst = int(np.argmax(z))
    if z[worst] > BIAS_Z:
        raise BiasedResamplerError(
            f"{where} is biased: particle {worst} of weight {weights[worst]:.4g} got {mean[worst]:.4f} "
            f"offspring on average over {draws} draws, expected N w = {expected[worst]:.4f} "
            f"(z = {z[worst]:.1f}; an unbiased resampler gives mean offspring N w_i)")
