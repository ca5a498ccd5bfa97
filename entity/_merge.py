"""Compiled kernels of :mod:`dtpf.entity.resampling`: one pass over the weights each.

Every scheme merges sorted points with the running weight sum C_j and hands
particle j the points below C_j. Written as "while the next point is below
C_j, take it", the merge's loop exit depends on the data at every particle,
and at N = 1e6 the mispredicted branches cost three times the pass itself.
Here particle j first writes its index, unconditionally, at the next
UNCONDITIONAL output positions and then moves k to the end of its points; a
loop runs only past them. Stores past a particle's points are overwritten by
the particles that follow (or by the tail guard), so every position ends with
the value the plain merge gives it: the same numbers, from the same
floating-point operations in the same order. Multinomial and residual, whose
points are random, compare several points with the running sum at once
(COMPARED) and keep the points in the output itself (see the notes before
_count_below).

For numpy's PCG64 the random numbers are drawn here, from an inline copy of
the generator's state (pcg_state, set_pcg_state), number for number those of
the Generator's methods; any other bit generator goes through numba's
Generator methods (the kernels taking ``rng``).

Outputs are written into a caller's (N,) int64 array, once per position
(plus the overwritten stores, in cache). Nothing here checks the weights;
:mod:`dtpf.entity.resampling` does, once.
"""
from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic
from numba.np.random._constants import fe_double, ke_double, we_double, ziggurat_exp_r

#: N w_i this close below an integer counts as that integer in residual
#: resampling: 49 * (1/49) is 0.9999999999999999 in float64, and equal
#: weights must give one copy each, not a multinomial draw.
ROUNDING = 1e-9


# --- numpy's PCG64, inline ------------------------------------------------------
# numba's Generator methods call numpy's bit generator through a function pointer per number
# (slower than numpy's own rng.random(N)); stepping the same 128-bit LCG in registers is faster
# and lets the merge run beside it. The state comes from the Generator's
# public ``bit_generator.state`` and goes back there, so the stream is numpy's, number for number
# (tests/test_resampling.py checks uniforms and exponentials against the Generator's own).

_U = np.uint64
#: PCG64's 128-bit multiplier (numpy's PCG_DEFAULT_MULTIPLIER_128), high and low words.
_MULTIPLIER_HIGH = _U(2549297995355413924)
_MULTIPLIER_LOW = _U(4865540595714422341)
_MASK64 = (1 << 64) - 1


@intrinsic
def _mul_high(typingctx, a, b):
    # The high 64 bits of the 128-bit product of two uint64 (one mulx; numba has no 128-bit type).
    def codegen(context, builder, signature, args):
        wide = ir.IntType(128)
        product = builder.mul(builder.zext(args[0], wide), builder.zext(args[1], wide))
        return builder.trunc(builder.lshr(product, ir.Constant(wide, 64)), ir.IntType(64))
    return types.uint64(types.uint64, types.uint64), codegen


@numba.njit(inline="always")
def _pcg_next(high, low, inc_high, inc_low):  # pragma: no cover - compiled
    # One PCG64 step, as numpy's pcg64_next64: state = state * multiplier + increment (mod 2**128),
    # then the XSL-RR output of the new state. Returns (64 random bits, high, low).
    product_low = low * _MULTIPLIER_LOW
    new_low = product_low + inc_low
    new_high = (_mul_high(low, _MULTIPLIER_LOW) + low * _MULTIPLIER_HIGH + high * _MULTIPLIER_LOW
                + inc_high + _U(new_low < product_low))
    folded = new_high ^ new_low
    rotation = new_high >> _U(58)
    return (folded >> rotation) | (folded << ((_U(64) - rotation) & _U(63))), new_high, new_low


@numba.njit(inline="always")
def _pcg_uniform(high, low, inc_high, inc_low):  # pragma: no cover - compiled
    # numpy's next_double: the top 53 bits as a double in [0, 1). Returns (u, high, low).
    bits, high, low = _pcg_next(high, low, inc_high, inc_low)
    return (bits >> _U(11)) * (1.0 / 9007199254740992.0), high, low


@numba.njit(inline="always")
def _pcg_exponential(high, low, inc_high, inc_low):  # pragma: no cover - compiled
    # numpy's random_standard_exponential (the ziggurat, numba's port of it with numba's tables):
    # one 64-bit draw almost always, more on the rare rejections. Returns (x, high, low).
    while True:
        bits, high, low = _pcg_next(high, low, inc_high, inc_low)
        ri = bits >> _U(3)
        idx = ri & _U(0xFF)
        ri >>= _U(8)
        x = ri * we_double[idx]
        if ri < ke_double[idx]:
            return x, high, low
        u, high, low = _pcg_uniform(high, low, inc_high, inc_low)
        if idx == 0:
            return ziggurat_exp_r - np.log1p(-u), high, low
        if (fe_double[idx - _U(1)] - fe_double[idx]) * u + fe_double[idx] < np.exp(-x):
            return x, high, low


def pcg_state(rng) -> np.ndarray | None:
    """(high, low, increment high, increment low) of ``rng``'s PCG64 as uint64, or None for another
    bit generator (the kernels then take numba's Generator methods)."""
    if type(rng.bit_generator) is not np.random.PCG64:
        return None
    state = rng.bit_generator.state["state"]
    value, inc = state["state"], state["inc"]
    return np.array([value >> 64, value & _MASK64, inc >> 64, inc & _MASK64], dtype=np.uint64)


def set_pcg_state(rng, words: np.ndarray) -> None:
    """Put the PCG64 state ``words`` (as :func:`pcg_state` gives them) back into ``rng``."""
    state = rng.bit_generator.state
    state["state"]["state"] = (int(words[0]) << 64) | int(words[1])
    rng.bit_generator.state = state


@numba.njit(cache=True, nogil=True)
def pcg_uniforms(words, out):  # pragma: no cover - compiled
    # len(out) uniforms of the PCG64 state ``words`` (advanced in place): rng.random(len(out))'s.
    high, low, inc_high, inc_low = words[0], words[1], words[2], words[3]
    for i in range(out.shape[0]):
        out[i], high, low = _pcg_uniform(high, low, inc_high, inc_low)
    words[0], words[1] = high, low
    return out


@numba.njit(cache=True, nogil=True)
def pcg_exponentials(words, out):  # pragma: no cover - compiled
    # len(out) standard exponentials of the PCG64 state ``words`` (advanced in place).
    high, low, inc_high, inc_low = words[0], words[1], words[2], words[3]
    for i in range(out.shape[0]):
        out[i], high, low = _pcg_exponential(high, low, inc_high, inc_low)
    words[0], words[1] = high, low
    return out


#: Copies each particle writes without a branch (one 64-byte store): at most N w_j + 1 copies go to
#: particle j, so with the weights of dtpf.scripts.bench.resampling (N w lognormal, median 0.6) 99.5% of
#: particles need no loop. With two stores the loop's exit was mispredicted for the 12% with
#: three copies or more, which made systematic resampling markedly slower than with eight.
UNCONDITIONAL = 8


@numba.njit(inline="always")
def _put(out, k, end, j):  # pragma: no cover - compiled
    # j at out[k:end] (k < N), as UNCONDITIONAL unconditional stores (the stores past ``end`` are
    # overwritten by the particles that follow or by the tail guard) and a loop past them; the new k.
    i = k
    if k + UNCONDITIONAL <= out.shape[0]:
        for q in range(UNCONDITIONAL):
            out[_U(k + q)] = j  # an unsigned index: no check for a negative one
        i = k + UNCONDITIONAL
    while i < end:
        out[i] = j
        i += 1
    return max(k, end)


@numba.njit(cache=True, nogil=True)
def fill_tail(ancestors, k, weights):  # pragma: no cover - compiled
    # Points past the running sum (it can end a few ulps below 1) go to the
    # last particle with positive weight: the tail guard.
    if k >= ancestors.shape[0]:
        return
    last = weights.shape[0] - 1
    for j in range(weights.shape[0] - 1, -1, -1):
        if weights[j] > 0.0:
            last = j
            break
    while k < ancestors.shape[0]:
        ancestors[k] = last
        k += 1


@numba.njit(cache=True, nogil=True)
def inverse_cdf(points, weights, out):  # pragma: no cover - compiled
    # One pass over the particles; each takes the given sorted points below its running sum.
    n = points.shape[0]
    cumulative = 0.0
    k = 0
    for j in range(weights.shape[0]):
        cumulative += weights[j]
        while k < n and points[k] < cumulative:
            out[k] = j
            k += 1
    fill_tail(out, k, weights)
    return out


@numba.njit(cache=True, nogil=True)
def _by_ends(weights, u, v, out):  # pragma: no cover - compiled
    # The merges whose points need no search: particle j's last point follows from the running sum
    # C_j. Systematic (v empty): points (k + u) / N, and point k < C_j <=> k < N C_j - u, so particle
    # j ends at ceil(N C_j - u). Stratified: point k is k + v_k on the scale N C_j (v_k in [0, 1), one
    # per stratum). With s = N C_j and m = floor(s), every point below m - 1 lies below s and every
    # point from m + 1 on above it, so particle j ends at m, less one if point m - 1 rounds up to s
    # (only when s is the integer m), plus one if point m is below s; the points are computed as the
    # plain merge computes them, float(k) + v_k.
    n = weights.shape[0]
    stratified = v.shape[0] == n
    cumulative = 0.0
    k = 0
    for j in range(n):
        if k >= n:
            break
        cumulative += weights[j]
        if stratified:
            scaled = cumulative * n
            m = min(max(int(scaled), 0), n)  # floor: scaled >= 0
            at = min(m, n - 1)
            end = m + int((m < n) & (at + v[at] < scaled))
            if scaled == m and m >= 1 and (m - 1) + v[m - 1] >= scaled:  # N C_j an integer: rare
                end -= 1
        else:
            end = min(n, int(np.ceil(cumulative * n - u)))
        k = _put(out, k, end, j)
    fill_tail(out, k, weights)
    return out


@numba.njit(inline="always")
def _put_below(out, k, end, j, limit):  # pragma: no cover - compiled
    # _put with the unconditional stores kept below ``limit``, where the next block's output begins
    # (another thread writes there).
    i = k
    if k + UNCONDITIONAL <= limit:
        for q in range(UNCONDITIONAL):
            out[_U(k + q)] = j
        i = k + UNCONDITIONAL
    while i < end:
        out[i] = j
        i += 1
    return max(k, end)


@numba.njit(cache=True, nogil=True)
def _block_sum(weights):  # pragma: no cover - compiled
    total = 0.0
    for j in range(weights.shape[0]):
        total += weights[j]
    return total


@numba.njit(cache=True, nogil=True)
def _merge_block(weights, first, offset, u, n, base, out):  # pragma: no cover - compiled
    # One block's systematic merge (as _by_ends) into its own output positions: ``weights`` the block's,
    # ``first`` its first particle's index, ``offset`` the blocks' sums before it, ``out`` the output
    # positions [base, base + len(out)).
    limit = out.shape[0]
    k = 0
    running = 0.0
    for j in range(weights.shape[0]):
        if k >= limit:
            break
        running += weights[j]
        end = min(limit, int(np.ceil((offset + running) * n - u)) - base)
        k = _put_below(out, k, end, first + j, limit)


@numba.njit(cache=True, nogil=True, parallel=True)
def systematic_blocks(weights, u, block, out):  # pragma: no cover - compiled
    # Systematic ancestors of a set in blocks of ``block`` particles, on the threads. The running sum of
    # particle j of block b is offset_b + (the sum of the block's weights up to j, from 0), offset_b the
    # sum of the blocks' sums before b in block order; so block b's points are [ceil(N offset_b - u),
    # ceil(N offset_(b+1) - u)), known before any block is merged, and each block merges its own (as
    # _by_ends) from there. The same ancestors for any thread count; one block would give _by_ends's.
    # (Each block a call on its slices: a loop written inline in a parallel loop ran 2x slower a thread.)
    n = weights.shape[0]
    count = (n + block - 1) // block
    sums = np.empty(count)
    for b in numba.prange(count):
        sums[b] = _block_sum(weights[b * block:min(n, (b + 1) * block)])
    offsets = np.empty(count + 1)
    starts = np.empty(count + 1, dtype=np.int64)
    offsets[0] = 0.0
    starts[0] = 0
    for b in range(count):
        offsets[b + 1] = offsets[b] + sums[b]
        starts[b + 1] = max(starts[b], min(n, int(np.ceil(offsets[b + 1] * n - u))))
    for b in numba.prange(count):
        _merge_block(weights[b * block:min(n, (b + 1) * block)], b * block, offsets[b], u, n, starts[b],
                     out[starts[b]:starts[b + 1]])
    fill_tail(out, starts[count], weights)
    return out


#: Stratified keeps the uniforms it may still read in a ring of this many (32 KB: in L1).
STRATA_RING = 1 << 12
#: ... drawn this far ahead of the merge before it starts (then one per particle).
STRATA_AHEAD = STRATA_RING // 2


@numba.njit(cache=True, nogil=True)
def stratified_pcg(weights, words, out):  # pragma: no cover - compiled
    # _by_ends' stratified merge with its uniforms v_k drawn here from the PCG64 state ``words``
    # (rng.random(N)'s numbers, in order; ``words`` is not advanced: the caller advances the
    # Generator by N). The merge reads v at the stratum m = floor(N C_j), which only grows, and
    # rarely at m - 1, so a ring holds the values from m - 1 on. One uniform is drawn per particle,
    # beside the merge (the two dependency chains overlap: faster than drawing all N first);
    # the merge catches up when m passes the drawn ones (a particle with many points), and the
    # drawing pauses when it is a ring ahead of m (a run of particles with none).
    n = weights.shape[0]
    mask = STRATA_RING - 1
    high, low, inc_high, inc_low = words[0], words[1], words[2], words[3]
    ring = np.empty(STRATA_RING)
    drawn = 0
    for i in range(min(n, STRATA_AHEAD)):
        ring[i], high, low = _pcg_uniform(high, low, inc_high, inc_low)
        drawn += 1
    m = 0
    cumulative = 0.0
    k = 0
    for j in range(n):
        if k >= n:
            break
        if drawn < n and drawn - m < STRATA_RING - 2:  # keeps v[m - 1] in the ring
            ring[drawn & mask], high, low = _pcg_uniform(high, low, inc_high, inc_low)
            drawn += 1
        cumulative += weights[j]
        scaled = cumulative * n
        m = min(max(int(scaled), 0), n)  # floor: scaled >= 0
        at = min(m, n - 1)
        while at >= drawn:
            ring[drawn & mask], high, low = _pcg_uniform(high, low, inc_high, inc_low)
            drawn += 1
        end = m + int((m < n) & (at + ring[at & mask] < scaled))
        if scaled == m and m >= 1 and (m - 1) + ring[(m - 1) & mask] >= scaled:  # N C_j an integer: rare
            end -= 1
        k = _put(out, k, end, j)
    fill_tail(out, k, weights)
    return out


_NO_STRATA = np.empty(0)


def systematic(weights, u, out):
    """Systematic ancestors of ``weights`` with the uniform ``u``, into ``out``."""
    return _by_ends(weights, u, _NO_STRATA, out)


def stratified(weights, v, out):
    """Stratified ancestors of ``weights`` with the uniforms ``v`` (one per stratum), into ``out``."""
    return _by_ends(weights, 0.0, v, out)


@numba.njit(cache=True, nogil=True)
def multinomial(weights, rng, out):  # pragma: no cover - compiled
    # Sorted uniforms as normalised partial sums of M + 1 standard exponentials (Eq. 26, "uniform
    # spacings"), merged with the running sum scaled by the same total. The exponentials are drawn
    # here, as numpy's Generator draws standard_exponential(M + 1) (numba's port, the same numbers),
    # into ``out`` itself: position k is written only after point k has been added up.
    m = out.shape[0]
    spacings = out.view(np.float64)
    total = 0.0
    for i in range(m):
        e = rng.standard_exponential()
        spacings[i] = e
        total += e
    total += rng.standard_exponential()  # the (M + 1)-th, past the last point
    cumulative = 0.0
    point = spacings[0]
    k = 0
    for j in range(weights.shape[0]):
        cumulative += weights[j] * total
        while k < m and point < cumulative:
            following = spacings[k + 1] if k + 1 < m else 0.0
            out[k] = j
            k += 1
            point += following
    fill_tail(out, k, weights)
    return out


#: Points each particle compares with its running sum at once (one 64-byte load of sorted points).
COMPARED = 8
#: How far to the right of its ancestor's position a sorted point is kept in the output
#: (see the notes before _count_below).
SHIFT = 2 * COMPARED


@numba.njit(inline="always")
def _point(points, tail, base, stored, d):  # pragma: no cover - compiled
    # Sorted point d: at points[base + d] for d < stored, the last ones in ``tail``.
    return points[base + d] if d < stored else tail[d - stored]


# How multinomial and residual hand particle j the sorted points d, d + 1, ... below its running
# sum, at output positions k, k + 1, ...: the plain merge "while the next point is below the running
# sum, take it" has a loop exit that depends on the data at every particle, and its mispredictions
# cost about half of multinomial's time at large N. Instead the next COMPARED points are compared at
# once (_count_below: sorted, the c below the sum are the first c), j goes to the next COMPARED
# positions unconditionally (as in _put), k and d move on by c, and the plain merge runs only when
# all were below (or near the end). The points live in ``out`` itself (as float64), SHIFT positions
# to the right of where their ancestors go: the positions written hold points already taken, and
# the loads never share a cache line with what the previous particles have just stored (with the
# points in place, or closer behind, the loads waited for the stores). The merge loops are written
# out in each kernel: the same steps in an inlined function that returned early were several times
# slower.


#: Residual's points compared at once: its particles take R / N (0.43 here) of them on average,
#: and 4 beat 8 at large N; multinomial's take one, and 8 beat 4.
RESIDUAL_COMPARED = 4


@numba.njit(inline="always")
def _count_below(points, at, limit, width):  # pragma: no cover - compiled
    # How many of the sorted points[at:at + width] lie below ``limit``: the first that many.
    below = 0
    for q in range(width):
        below += points[_U(at + q)] < limit  # an unsigned index: no check for a negative one
    return below


@numba.njit(inline="always")
def _take_rest(out, points, tail, base, stored, count, k, d, limit, j):  # pragma: no cover - compiled
    # The plain merge from point d (output position k): j takes the points below ``limit``. Returns (k, d).
    while d < count and k < out.shape[0] and _point(points, tail, base, stored, d) < limit:
        out[k] = j
        k += 1
        d += 1
    return k, d



@numba.njit(inline="always")
def _draw_points(points, tail, base, stored, count, high, low, inc_high, inc_low):  # pragma: no cover
    # ``count`` + 1 standard exponentials; their running sums, the sorted points e_0 + ... + e_d,
    # stored as _point reads them. Returns (total of all count + 1, high, low): the additions and
    # their order are those of the plain merge.
    total = 0.0
    for d in range(stored):
        e, high, low = _pcg_exponential(high, low, inc_high, inc_low)
        total += e
        points[_U(base + d)] = total
    for d in range(stored, count):
        e, high, low = _pcg_exponential(high, low, inc_high, inc_low)
        total += e
        tail[d - stored] = total
    e, high, low = _pcg_exponential(high, low, inc_high, inc_low)
    return total + e, high, low  # the (count + 1)-th, past the last point


@numba.njit(cache=True, nogil=True)
def multinomial_pcg(weights, words, out):  # pragma: no cover - compiled
    # multinomial's numbers with the exponentials drawn from the PCG64 state ``words`` (advanced
    # in place; the caller puts it back into the Generator). Pass 1 draws the M + 1 exponentials
    # and stores the M points in ``out``, SHIFT positions to the right, the last SHIFT in a small
    # array; pass 2 merges them with the running weight sum scaled by the total.
    m = out.shape[0]
    points = out.view(np.float64)
    stored = max(m - SHIFT, 0)
    tail = np.empty(SHIFT)
    high, low, inc_high, inc_low = words[0], words[1], words[2], words[3]
    total, high, low = _draw_points(points, tail, SHIFT, stored, m, high, low, inc_high, inc_low)
    words[0], words[1] = high, low
    cumulative = 0.0
    k = 0
    for j in range(weights.shape[0]):
        if k >= m:
            break
        cumulative += weights[j] * total
        if k + COMPARED <= stored:  # point k at out[k + SHIFT]
            below = _count_below(points, k + SHIFT, cumulative, COMPARED)
            for q in range(COMPARED):
                out[_U(k + q)] = j
            k += below
            if below < COMPARED:
                continue
        k, _ = _take_rest(out, points, tail, SHIFT, stored, m, k, k, cumulative, j)
    fill_tail(out, k, weights)
    return out


@numba.njit(cache=True, nogil=True)
def residual_pcg(weights, words, out):  # pragma: no cover - compiled
    # residual's numbers with the exponentials drawn from the PCG64 state ``words`` (advanced in
    # place). The R points live in ``out`` from N - R + SHIFT on (the last SHIFT in a small array):
    # when residual point d is read, the floors and points taken fill at most N - R + d positions,
    # and the unconditional stores reach UNCONDITIONAL - 1 further, less than SHIFT, so nothing
    # unread is overwritten (see the notes before _count_below).
    n = weights.shape[0]
    kept = 0
    residual_total = 0.0
    for j in range(n):
        scaled = weights[j] * n
        whole = np.floor(scaled + ROUNDING)
        kept += int(whole)
        residual_total += max(scaled - whole, 0.0)
    remaining = max(n - kept, 0)
    points = out.view(np.float64)
    base = n - remaining + SHIFT
    stored = max(remaining - SHIFT, 0)
    tail = np.empty(SHIFT)
    high, low, inc_high, inc_low = words[0], words[1], words[2], words[3]
    total, high, low = _draw_points(points, tail, base, stored, remaining, high, low, inc_high, inc_low)
    words[0], words[1] = high, low
    scale = total / residual_total if residual_total > 0.0 else 0.0
    k = 0
    drawn = 0
    cumulative = 0.0
    for j in range(n):
        if k >= n:
            break
        scaled = weights[j] * n
        whole = np.floor(scaled + ROUNDING)
        k = _put(out, k, min(k + int(whole), n), j)
        cumulative += max(scaled - whole, 0.0) * scale
        if drawn + RESIDUAL_COMPARED <= stored and k + RESIDUAL_COMPARED <= n:
            below = _count_below(points, base + drawn, cumulative, RESIDUAL_COMPARED)
            for q in range(RESIDUAL_COMPARED):
                out[_U(k + q)] = j
            k += below
            drawn += below
            if below < RESIDUAL_COMPARED:
                continue
        k, drawn = _take_rest(out, points, tail, base, stored, remaining, k, drawn, cumulative, j)
    fill_tail(out, k, weights)
    return out


@numba.njit(cache=True, nogil=True)
def residual(weights, rng, out):  # pragma: no cover - compiled
    # Pass 1: R = N - sum floor(N w_j) and the total residual mass.
    n = weights.shape[0]
    kept = 0
    residual_total = 0.0
    for j in range(n):
        scaled = weights[j] * n
        whole = np.floor(scaled + ROUNDING)
        kept += int(whole)
        residual_total += max(scaled - whole, 0.0)
    # Weights may sum to 1 +- SUM_TOLERANCE, so the floors may overshoot N
    # by a few; never write past the end.
    remaining = max(n - kept, 0)
    # Pass 2: floor(N w_j) copies of j, then j's share of the R multinomial
    # draws (uniform spacings over the residuals), so the output stays sorted.
    exponentials = rng.standard_exponential(remaining + 1)
    total = 0.0
    for i in range(remaining + 1):
        total += exponentials[i]
    scale = total / residual_total if residual_total > 0.0 else 0.0
    k = 0
    drawn = 0
    point = exponentials[0]
    cumulative = 0.0
    for j in range(n):
        if k >= n:
            break
        scaled = weights[j] * n
        whole = np.floor(scaled + ROUNDING)
        k = _put(out, k, min(k + int(whole), n), j)
        cumulative += max(scaled - whole, 0.0) * scale
        while drawn < remaining and k < n and point < cumulative:
            out[k] = j
            k += 1
            drawn += 1
            point += exponentials[drawn]
    fill_tail(out, k, weights)
    return out


@numba.njit(cache=True, nogil=True)
def distinct(ancestors):  # pragma: no cover - compiled
    # Distinct values of a non-decreasing array: 1 + the number of changes.
    changes = 0
    for i in range(1, ancestors.shape[0]):
        changes += ancestors[i] != ancestors[i - 1]
    return 1 + changes



@numba.njit(cache=True, nogil=True, parallel=True)
def distinct_parallel(ancestors, chunk):  # pragma: no cover - compiled
    # distinct's count, chunk by chunk on the threads: the changes inside each chunk and at its start.
    # (Each chunk a call on its slice: a loop written inline in a parallel loop ran 2x slower a thread.)
    n = ancestors.shape[0]
    count = (n + chunk - 1) // chunk
    changes = np.empty(count, dtype=np.int64)
    for b in numba.prange(count):
        start = max(1, b * chunk)
        changes[b] = distinct(ancestors[start - 1:min(n, (b + 1) * chunk)]) - 1
    total = 1
    for b in range(count):
        total += changes[b]
    return total


#: Rows of one chunk of the parallel gather (threads take chunks one at a time).
GATHER_CHUNK = 1 << 13


@numba.njit(cache=True, nogil=True)
def _gather_into(particles, ancestors, out):  # pragma: no cover - compiled
    for i in range(ancestors.shape[0]):
        for c in range(particles.shape[1]):
            out[i, c] = particles[ancestors[i], c]


@numba.njit(cache=True, nogil=True, parallel=True)
def gather_parallel(particles, ancestors, out):  # pragma: no cover - compiled
    # out[i] = particles[ancestors[i]] on numba's threads, chunk by chunk (each a call on slices: a loop
    # written inline in a parallel loop ran 2x slower a thread): the same array whatever their number.
    n = ancestors.shape[0]
    for b in numba.prange((n + GATHER_CHUNK - 1) // GATHER_CHUNK):
        start, end = b * GATHER_CHUNK, min(n, (b + 1) * GATHER_CHUNK)
        _gather_into(particles, ancestors[start:end], out[start:end])
    return out
