"""The mirror: a summary of the entity's particle-weight state.

The information layer keeps this summary of every particle set it receives
and sends it to the system layer, which predicts degradation from it::

    from dtpf.information.mirror import summarise
    state = summarise(particles, weights)
    state.ess_ratio, state.distinct
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from dtpf.entity import cores
from dtpf.information.rules import threshold as threshold_of
from dtpf.information.select import quantiles
from dtpf.messages.arrays import check_set

__all__ = ["WeightSummary", "summarise", "ess", "weight_state"]

#: Weight quantiles reported, by field name.
QUANTILES = {"q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}


def ess(weights: np.ndarray) -> float:
    """Effective sample size 1 / sum(w^2) of normalised weights (Eq. 25)."""
    return 1.0 / float(np.dot(weights, weights))


@dataclass(frozen=True)
class WeightSummary:
    """Weight state of one particle set.

    Attributes
    ----------
    n : int
        Number of particles N.
    ess, ess_ratio : float
        Effective sample size (Eq. 25) and ESS / N.
    entropy, entropy_ratio : float
        Shannon entropy of the weights in nats, and entropy / log N (1 for
        uniform weights, 0 when one particle holds all the weight).
    max_weight : float
        The largest normalised weight.
    threshold : float
        W of Eq. 28 under the threshold rule in force.
    n_above_threshold : int
        Particles with weight > W (the large set of Eq. 28).
    distinct : int
        Number of distinct particles the set descends from (impoverishment
        after resampling); see :func:`summarise`.
    q10, q50, q90, q99 : float
        Quantiles of the normalised weights.
    """

    n: int
    ess: float
    ess_ratio: float
    entropy: float
    entropy_ratio: float
    max_weight: float
    threshold: float
    n_above_threshold: int
    distinct: int
    q10: float
    q50: float
    q90: float
    q99: float

    def as_dict(self) -> dict:
        """The fields by name (a shallow copy: every field is a number; ``dataclasses.asdict`` deep-copies,
        18% of the information layer's work per step at N = 1e3)."""
        return dict(self.__dict__)


@numba.njit(cache=True, nogil=True)
def _entropy(weights):  # pragma: no cover - compiled
    total = 0.0
    for w in weights:
        if w > 0.0:
            total -= w * np.log(w)
    return total


@numba.njit(cache=True, nogil=True)
def _sums(weights, logs, limit):  # pragma: no cover - compiled
    # One block's (sum w^2, -sum w log w, max w, #{w > limit}): four running sums of each (elements
    # i = 0, 1, 2, 3 mod 4 from the block's start), then (s0 + s1) + (s2 + s3), as dtpf.entity.blocks sums.
    q0 = q1 = q2 = q3 = 0.0
    e0 = e1 = e2 = e3 = 0.0
    top = 0.0
    over = 0
    i, end = 0, weights.shape[0]
    while i + 4 <= end:
        w0, w1, w2, w3 = weights[i], weights[i + 1], weights[i + 2], weights[i + 3]
        q0 += w0 * w0
        q1 += w1 * w1
        q2 += w2 * w2
        q3 += w3 * w3
        e0 -= w0 * logs[i] if w0 > 0.0 else 0.0
        e1 -= w1 * logs[i + 1] if w1 > 0.0 else 0.0
        e2 -= w2 * logs[i + 2] if w2 > 0.0 else 0.0
        e3 -= w3 * logs[i + 3] if w3 > 0.0 else 0.0
        top = max(top, max(max(w0, w1), max(w2, w3)))
        over += (w0 > limit) + (w1 > limit) + (w2 > limit) + (w3 > limit)
        i += 4
    while i < end:
        w0 = weights[i]
        q0 += w0 * w0
        e0 -= w0 * logs[i] if w0 > 0.0 else 0.0
        top = max(top, w0)
        over += w0 > limit
        i += 1
    return (q0 + q1) + (q2 + q3), (e0 + e1) + (e2 + e3), top, over


@numba.njit(cache=True, nogil=True, parallel=True)
def _block_sums(weights, logs, block, limit):  # pragma: no cover - compiled
    # (sum w^2, -sum w log w, max w, #{w > limit}) of a set in blocks of ``block``, ``logs`` = log(weights):
    # each block's on a thread (a call on its slices: a loop written inline in a parallel loop ran 2x slower a
    # thread), the sums added in block order (the same numbers for any thread count).
    n = weights.shape[0]
    count = (n + block - 1) // block
    squares = np.empty(count)
    entropies = np.empty(count)
    largest = np.empty(count)
    above = np.empty(count, dtype=np.int64)
    for b in numba.prange(count):
        start, end = b * block, min(n, (b + 1) * block)
        squares[b], entropies[b], largest[b], above[b] = _sums(weights[start:end], logs[start:end], limit)
    square = 0.0
    entropy = 0.0
    top = 0.0
    over = 0
    for b in range(count):
        square += squares[b]
        entropy += entropies[b]
        top = max(top, largest[b])
        over += above[b]
    return square, entropy, top, over


def weight_state(weights: np.ndarray, limit: float, block: int | None = None) -> tuple[float, float, float, int]:
    """(ESS of Eq. 25, Shannon entropy, largest weight, number of weights > ``limit``) of normalised weights;
    for more than ``block`` weights (:mod:`dtpf.entity.cores`) in one pass of blocks on the process's threads,
    the sums per block, else as :func:`ess` and one pass each."""
    if cores.blocks(weights.size, block) == 1:
        return ess(weights), float(_entropy(weights)), float(weights.max()), int(np.count_nonzero(weights > limit))
    logs = np.empty(weights.size)

    def logarithms(start: int, end: int) -> None:  # numpy's log, element by element: any cut
        with np.errstate(divide="ignore"):  # log 0 = -inf, never read
            np.log(weights[start:end], out=logs[start:end])

    cores.in_parts(weights.size, logarithms)
    cores.use(weights.size)
    square, entropy, largest, above = _block_sums(weights, logs, int(block), float(limit))
    return 1.0 / square, float(entropy), float(largest), int(above)


def summarise(particles, weights, threshold_rule: str | float = "neff", parents: int | None = None, *,
              checked: bool = False, block: int | None = None) -> WeightSummary:
    """The :class:`WeightSummary` of a particle set (N, d) with normalised weights (N,).

    ``parents``: the number of distinct particles the set descends from (the
    distinct ancestors of the resampling before the last propagation), which
    the entity knows in O(N). Without it, distinct states are counted by
    sorting, O(N log N); after a propagation with noise that is N.
    ``checked``: as in :func:`dtpf.information.rules.preprocess`. ``block``: B of the run
    (:mod:`dtpf.entity.cores`); more weights than B are summed per block (:func:`weight_state`).
    """
    x, w = check_set(particles, weights, checked=checked)
    n = w.size
    limit = threshold_of(w, threshold_rule)
    effective, entropy, largest, above = weight_state(w, limit, block)
    if parents is not None:
        if not 1 <= int(parents) <= n:
            raise ValueError(f"parents must be in [1, {n}], got {parents!r}")
        distinct = int(parents)
    else:
        distinct = np.unique(x[:, 0]).size if x.shape[1] == 1 else np.unique(x, axis=0).shape[0]
    weight_quantiles = quantiles(w, list(QUANTILES.values()))
    return WeightSummary(
        n=n,
        ess=effective,
        ess_ratio=effective / n,
        entropy=entropy,
        entropy_ratio=entropy / np.log(n) if n > 1 else 1.0,
        max_weight=largest,
        threshold=limit,
        n_above_threshold=above,
        distinct=int(distinct),
        **{name: float(q) for name, q in zip(QUANTILES, weight_quantiles)},
    )
