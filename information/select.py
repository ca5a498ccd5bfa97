"""Order statistics of non-negative float64 arrays in O(N) (the weights).

The threshold W of Eq. 28 and the mirror's weight quantiles are order
statistics of the weights. One pass builds a histogram of the top 16 bits of
the values' bit patterns, which order like the values for non-negative
floats; a second collects the members of the buckets that hold a requested
rank, and each order statistic is selected among those only (np.partition).
Below 2**16 values ``np.partition`` on the whole array is faster and is used
instead. On more than one thread (:mod:`dtpf.entity.cores`) each thread counts
and collects a contiguous part: the counts are integers and the members keep
index order, so the values are those of one thread.
"""
from __future__ import annotations

import numba
import numpy as np

from dtpf.entity import cores

__all__ = ["order_statistics", "kth_largest", "quantiles"]

#: Below this size np.partition beats the radix select (its histogram has 2**15 bins).
RADIX_MIN = 1 << 16


@numba.njit(inline="always")
def _part(n, parts, p):  # pragma: no cover - compiled
    # [start, end) of part p of ``parts`` contiguous parts of n values.
    return n * p // parts, n * (p + 1) // parts


# The parallel passes call a compiled function on each part's slices: a loop written inline in a parallel
# loop ran 1.6-2x slower a thread.

@numba.njit(cache=True, nogil=True)
def _histogram_into(bits, counts):  # pragma: no cover - compiled
    for b in range(counts.shape[0]):
        counts[b] = 0
    for i in range(bits.shape[0]):
        counts[bits[i] >> 48] += 1


@numba.njit(cache=True, nogil=True, parallel=True)
def _counts_parallel(bits, parts):  # pragma: no cover - compiled
    # The histograms of the top 16 bits, one a part, each on a thread: (parts, 2**15).
    partial = np.empty((parts, 1 << 15), dtype=np.int64)
    for p in numba.prange(parts):
        start, end = _part(bits.shape[0], parts, p)
        _histogram_into(bits[start:end], partial[p])
    return partial


@numba.njit(cache=True, nogil=True)
def _sum_rows(partial):  # pragma: no cover - compiled
    counts = np.zeros(partial.shape[1], dtype=np.int64)
    for p in range(partial.shape[0]):
        for b in range(partial.shape[1]):
            counts[b] += partial[p, b]
    return counts


@numba.njit(cache=True, nogil=True)
def _collect_into(values, bits, needed, members):  # pragma: no cover - compiled
    j = 0
    for i in range(bits.shape[0]):
        if needed[bits[i] >> 48]:
            members[j] = values[i]
            j += 1


@numba.njit(cache=True, nogil=True, parallel=True)
def _collect_parallel(values, bits, needed, found, parts):  # pragma: no cover - compiled
    # The values whose bucket is needed, in index order: part p's from found[p] (the needed members of the
    # parts before it, from their histograms).
    members = np.empty(found[parts])
    for p in numba.prange(parts):
        start, end = _part(bits.shape[0], parts, p)
        _collect_into(values[start:end], bits[start:end], needed, members[found[p]:found[p + 1]])
    return members


@numba.njit(cache=True, nogil=True)
def _plan(counts, ranks):  # pragma: no cover - compiled
    # From the histogram: the buckets that hold a requested rank (needed), their members' number (size),
    # and each rank's position in sorted(members) (local): the members of needed buckets below its
    # bucket, plus its rank inside the bucket. Ranks ascend, so do their buckets.
    needed = np.zeros(counts.shape[0], dtype=np.bool_)
    bucket_of = np.empty(ranks.shape[0], dtype=np.int64)
    below_of = np.empty(ranks.shape[0], dtype=np.int64)
    below = 0
    bucket = 0
    for q in range(ranks.shape[0]):
        while below + counts[bucket] <= ranks[q]:
            below += counts[bucket]
            bucket += 1
        needed[bucket] = True
        bucket_of[q] = bucket
        below_of[q] = below
    size = 0
    for b in range(counts.shape[0]):
        if needed[b]:
            size += counts[b]
    local = np.empty(ranks.shape[0], dtype=np.int64)
    start = 0
    b = 0
    for q in range(ranks.shape[0]):
        while b < bucket_of[q]:
            if needed[b]:
                start += counts[b]
            b += 1
        local[q] = start + ranks[q] - below_of[q]
    return needed, size, local


@numba.njit(cache=True, nogil=True)
def _pick(members, local):  # pragma: no cover - compiled
    # Select, not sort: near-uniform weights put most of N in one bucket, and
    # sorting it costs O(size log size) (np.partition is O(size) per rank).
    members = np.partition(members, local)
    out = np.empty(local.shape[0])
    for q in range(local.shape[0]):
        out[q] = members[local[q]]
    return out


@numba.njit(cache=True, nogil=True)
def _order_statistics(values, ranks):  # pragma: no cover - compiled
    # ranks: sorted 0-based positions in ascending order. Pass 1: histogram of
    # the top 16 bits. Pass 2: collect the members of the buckets that hold a
    # requested rank; sorted, each bucket is a contiguous run of them.
    bits = values.view(np.int64)
    shift = 48
    counts = np.zeros(1 << 15, dtype=np.int64)
    for i in range(bits.shape[0]):
        counts[bits[i] >> shift] += 1
    needed, size, local = _plan(counts, ranks)
    members = np.empty(size)
    j = 0
    for i in range(bits.shape[0]):
        if needed[bits[i] >> shift]:
            members[j] = values[i]
            j += 1
    return _pick(members, local)


#: The second level of the parallel select: the next 12 bits of the needed buckets' values.
SUB_BITS = 12


@numba.njit(inline="always")
def _sub_key(bit, slot):  # pragma: no cover - compiled
    # (slot of the top 16 bits' bucket, next SUB_BITS bits), or -1 outside the needed buckets.
    u = slot[bit >> 48]
    if u < 0:
        return -1
    return (u << SUB_BITS) + ((bit >> (48 - SUB_BITS)) & ((1 << SUB_BITS) - 1))


@numba.njit(cache=True, nogil=True)
def _sub_histogram_into(bits, slot, counts):  # pragma: no cover - compiled
    for b in range(counts.shape[0]):
        counts[b] = 0
    for i in range(bits.shape[0]):
        key = _sub_key(bits[i], slot)
        if key >= 0:
            counts[key] += 1


@numba.njit(cache=True, nogil=True, parallel=True)
def _sub_counts_parallel(bits, slot, width, parts):  # pragma: no cover - compiled
    # The histograms, one a part, of (slot of the top 16 bits' bucket, next SUB_BITS bits) over the values
    # of the needed buckets (slot >= 0): (parts, width).
    partial = np.empty((parts, width), dtype=np.int64)
    for p in numba.prange(parts):
        start, end = _part(bits.shape[0], parts, p)
        _sub_histogram_into(bits[start:end], slot, partial[p])
    return partial


@numba.njit(cache=True, nogil=True)
def _collect_sub_into(values, bits, slot, needed, members):  # pragma: no cover - compiled
    j = 0
    for i in range(bits.shape[0]):
        key = _sub_key(bits[i], slot)
        if key >= 0 and needed[key]:
            members[j] = values[i]
            j += 1


@numba.njit(cache=True, nogil=True, parallel=True)
def _collect_sub_parallel(values, bits, slot, needed, found, parts):  # pragma: no cover - compiled
    # The values whose (slot, next SUB_BITS bits) is needed, in index order: part p's from found[p].
    members = np.empty(found[parts])
    for p in numba.prange(parts):
        start, end = _part(bits.shape[0], parts, p)
        _collect_sub_into(values[start:end], bits[start:end], slot, needed, members[found[p]:found[p + 1]])
    return members


#: Members of the needed buckets that the parallel select selects among on one thread; more go through a
#: second level of buckets (np.partition of 160,000 members took 2 ms, a pass on 2 threads 0.4 ms).
FEW_MEMBERS = 1 << 14


def _found(partial, needed) -> np.ndarray:
    """Where each part's members begin: the needed buckets' counts of the parts before it, (parts + 1,)."""
    found = np.zeros(partial.shape[0] + 1, dtype=np.int64)
    np.cumsum(partial[:, needed].sum(axis=1), out=found[1:])
    return found


def _order_statistics_parallel(values, ranks, parts, few: int = FEW_MEMBERS):
    """_order_statistics on the threads, each of ``parts`` parts counted and collected on one: the buckets of
    the top 16 bits that hold a rank, and when they hold more than FEW_MEMBERS values, inside them the buckets
    of the next SUB_BITS bits (``few``: FEW_MEMBERS); the few members left are selected among. Order statistics
    are values: the same numbers."""
    bits = values.view(np.int64)
    partial = _counts_parallel(bits, parts)
    needed, size, local = _plan(_sum_rows(partial), ranks)
    if size <= few:
        return _pick(_collect_parallel(values, bits, needed, _found(partial, needed), parts), local)
    slot = np.full(needed.size, -1, dtype=np.int64)
    buckets = np.flatnonzero(needed)
    slot[buckets] = np.arange(buckets.size)  # ascending buckets, ascending slots: the values' order
    partial = _sub_counts_parallel(bits, slot, buckets.size << SUB_BITS, parts)
    sub_needed, _, sub_local = _plan(_sum_rows(partial), local)
    return _pick(_collect_sub_parallel(values, bits, slot, sub_needed, _found(partial, sub_needed), parts),
                 sub_local)


def order_statistics(values: np.ndarray, ranks) -> np.ndarray:
    """The values at 0-based ``ranks`` of ``sorted(values)``; values non-negative float64."""
    ranks = np.asarray(ranks, dtype=np.int64)
    if ranks.size and (ranks.min() < 0 or ranks.max() >= values.size):
        raise ValueError(f"ranks must be in [0, {values.size - 1}], got {ranks.tolist()}")
    if values.size < RADIX_MIN:
        return np.partition(values, ranks)[ranks]
    order = np.argsort(ranks, kind="stable")
    out = np.empty(ranks.size)
    values = np.ascontiguousarray(values, dtype=np.float64)
    if cores.parallel(values.size):
        parts = cores.parts(values.size, 4 * cores.threads())  # a histogram of 256 KB a part
        out[order] = _order_statistics_parallel(values, ranks[order], parts)
    else:
        out[order] = _order_statistics(values, ranks[order])
    return out


def kth_largest(values: np.ndarray, k: int) -> float:
    """The k-th largest value (k = 1 is the maximum)."""
    if not 1 <= k <= values.size:
        raise ValueError(f"k must be in [1, {values.size}], got {k}")
    return float(order_statistics(values, [values.size - k])[0])


def quantiles(values: np.ndarray, probabilities) -> np.ndarray:
    """Quantiles with numpy's default (linear) interpolation, as ``np.quantile``."""
    p = np.asarray(probabilities, dtype=np.float64)
    position = p * (values.size - 1)
    lower = np.floor(position).astype(np.int64)
    upper = np.minimum(lower + 1, values.size - 1)
    stats = order_statistics(values, np.concatenate((lower, upper)))
    low, high = stats[: p.size], stats[p.size:]
    return low + (high - low) * (position - lower)
