"""Digital-twin preprocessing rules (paper section 3, Eq. 28-30).

Before the traditional resampling runs, the particles with small weights are
moved towards particles with large weights::

    from dtpf.information import rules
    result = rules.preprocess(particles, weights, ps=0.81, rng=rng)
    result.particles, result.weights, result.report

1. Split (Eq. 28): a particle is *large* if its weight exceeds the
   threshold W, *small* otherwise. Large particles are never changed.
2. Move (Eq. 29): each small particle x_l is paired with x_m, drawn
   uniformly from the large set, and r ~ U(0, 1)::

       x_hat = x_m + (2 r - 1) x_l

3. Update (Eq. 30): with u ~ U(0, 1) and the degree factor PS::

       x_tilde = (1 - r) x_m + r x_hat    if u <= PS   ("mixed" branch)
       x_tilde = x_hat                    if u >  PS   ("plain" branch)

   The same r serves Eq. 29 and Eq. 30, as the theorem of section 3
   requires; then |x_tilde - x_m| <= |x_l| component-wise. A
   d-dimensional state applies the rule to the whole particle vector with
   one (x_m, r, u) per particle.

The move of step 2-3 is the paper's (``move_rule="paper"``, the default of
the paper's experiments). It moves a particle by up to its own coordinates,
so its result depends on where the origin of the state space is. dtpf also
offers a rule that is not the paper's, named so nobody confuses the two:

- ``move_rule="relative"``: the same partner, r, u and factor
  f = (2 r - 1) (r if u <= PS else 1) of Eq. 33-34, applied to the
  *difference* to the partner, capped per component at the weighted spread
  sigma of the set (the weighted standard deviation of each component)::

      x_tilde = x_m + f c (x_l - x_m),   c = min(1, sigma / |x_l - x_m|)

  so |x_tilde - x_m| <= min(|x_l - x_m|, sigma) component-wise: a small
  particle lands near its partner, at most one spread away, whatever the
  origin. Translating every particle translates the result; scaling a
  component scales it.

Interpretations the paper leaves open, each an option:

- ``threshold``: ``"neff"`` (default; the paper: "W is usually selected as
  the N_eff value"): W is the (k+1)-th largest weight with k = round(ESS),
  so k particles are large; ``"inverse-n"``: W = 1/N; a user's rule
  ``W = rule(weights)`` named by ``path/to/file.py:NAME``; or a float W.
  The rules are a family (:mod:`dtpf.information.thresholds`).
- ``weight_rule``: ``"inherit"`` (default): processed particles keep their
  old weights, the paper moves positions only; ``"likelihood"``: the weight
  is re-evaluated at the new position,
  w_l <- w_l p(z | x_tilde_l) / p(z | x_l), then all weights renormalised.
  A particle whose weight underflowed to exactly 0 stays at 0.

The weight rules and the move rules are registries of built-ins
(:mod:`dtpf.information.weight_rules`, :mod:`dtpf.information.move_rules`):
their names are read from there. The move rules' code is here, beside the
compiled split and random stream they share.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numba
import numpy as np

from dtpf.entity import cores
from dtpf.information.report import PreprocessReport
from dtpf.information import select
from dtpf.information.select import RADIX_MIN, kth_largest
from dtpf.messages.arrays import check_probability, check_set
from dtpf.messages.family import THRESHOLDS
from dtpf.messages.names import MOVE_RULE_REGISTRY, WEIGHT_RULE_REGISTRY

__all__ = [
    "apply_relative",
    "move_paper",
    "move_relative",
    "spread",
    "PreprocessReport",
    "PreprocessResult",
    "threshold",
    "apply_rules",
    "kth_largest",
    "draws",
    "preprocess",
    "unprocessed",
]



def __getattr__(name: str):
    # WEIGHT_RULES and MOVE_RULES: the names of the two registries (dtpf.messages.names) as tuples, read when
    # asked for, so that importing this module does not import the rules' packages (whose modules import it).
    if name == "WEIGHT_RULES":
        return tuple(WEIGHT_RULE_REGISTRY.names())
    if name == "MOVE_RULES":
        return tuple(MOVE_RULE_REGISTRY.names())
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


LogLikelihood = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class PreprocessResult:
    """Preprocessed particle set: particles (N, d), weights (N,), and the report."""

    particles: np.ndarray
    weights: np.ndarray
    report: PreprocessReport


def threshold(weights: np.ndarray, rule: str | float = "neff") -> float:
    """The threshold W of Eq. 28 for normalised ``weights``.

    ``rule`` names a member of the threshold rules' family
    (:mod:`dtpf.information.thresholds`): ``"neff"``: with k = round(1 / sum w^2)
    (Eq. 25) clipped to [1, N], W is the (k+1)-th largest weight, so the k
    heaviest particles are large (ties at W count as small); with k = N every
    positive weight is large: W = 0. ``"inverse-n"``: W = 1 / N. A reference
    ``path/to/file.py:NAME`` names a user's ``W = rule(weights)``. A number is
    used as W itself. An unknown name, or a user's rule that fails its
    contract, raises :class:`~dtpf.messages.references.ReferenceLoadError` (a
    ValueError) in one line.
    """
    return _threshold(weights, rule)[0]


def _threshold(weights: np.ndarray, rule: str | float) -> tuple[float, int]:
    """(W, the most weights that can exceed it): the family's member's split (k for "neff", N for
    "inverse-n" and a user's rule), or a number and N."""
    if isinstance(rule, str):
        return THRESHOLDS.get(rule)(weights)
    value = float(rule)
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"threshold W must be a finite non-negative number, got {rule!r}")
    return value, weights.size


@numba.njit(cache=True, nogil=True)
def _split(weights, limit, particles, capacity):  # pragma: no cover - compiled
    # Eq. 28 in one branch-free pass: the indices of the small particles (weight <= W), the rows of
    # the large ones (weight > W) copied in index order, so that the moves read their partners from
    # a compact array of M rows instead of from all N (random reads in 3 MB, not 8 MB, at N = 1e6
    # and M = 0.37 N: 10x faster), and the copy of every particle the moves then write into (made
    # here, from the values the split reads anyway: one pass over the particles, not two).
    # At most ``capacity`` weights exceed W (k for the "neff" rule): the rows array is no larger.
    n, d = particles.shape
    small = np.empty(n, dtype=np.int32)  # int32: half the memory traffic of int64; N < 2**31
    rows = np.empty((capacity + 1, d))
    out = np.empty((n, d))
    n_large = 0
    if d == 1:  # a loop over one component would serialise the stores
        for i in range(n):  # unsigned indices: numba checks every signed one for a negative value
            value = particles[i, 0]
            out[i, 0] = value
            rows[_U(n_large), 0] = value
            small[_U(i - n_large)] = i
            n_large += weights[i] > limit
    else:
        for i in range(n):
            for c in range(d):
                out[i, c] = particles[i, c]
                rows[n_large, c] = particles[i, c]
            small[i - n_large] = i
            n_large += weights[i] > limit
    return small[: n - n_large], rows[:n_large], out


@numba.njit(cache=True, nogil=True)
def _count_large(weights, limit):  # pragma: no cover - compiled
    count = 0
    for i in range(weights.shape[0]):
        count += weights[i] > limit
    return count


@numba.njit(cache=True, nogil=True)
def _split_part(weights, limit, particles, small, rows, out):  # pragma: no cover - compiled
    # _split's branch-free stores for one part's particles (slices: ``small`` and ``rows`` its own slots). A
    # store for the wrong kind is overwritten by the next particle of the right kind; past the part's last
    # large (last small) particle it would land past its slots, so from there on the stores are checked.
    n, d = particles.shape
    rows_end = rows.shape[0]
    small_end = small.shape[0]
    last_large = n - 1
    while last_large >= 0 and not weights[last_large] > limit:
        last_large -= 1
    last_small = n - 1
    while last_small >= 0 and weights[last_small] > limit:
        last_small -= 1
    safe = max(0, min(last_large, last_small) + 1)
    k = 0
    if d == 1:
        for i in range(safe):
            value = particles[i, 0]
            out[_U(i), 0] = value
            rows[_U(k), 0] = value
            small[_U(i - k)] = i
            k += weights[i] > limit
    else:
        for i in range(safe):
            for c in range(d):
                out[i, c] = particles[i, c]
                rows[k, c] = particles[i, c]
            small[i - k] = i
            k += weights[i] > limit
    for i in range(safe, n):
        for c in range(d):
            out[i, c] = particles[i, c]
            if k < rows_end:
                rows[k, c] = particles[i, c]
        if i - k < small_end:
            small[i - k] = i
        k += weights[i] > limit


@numba.njit(cache=True, nogil=True, parallel=True)
def _split_parallel(weights, limit, particles, capacity, parts):  # pragma: no cover - compiled
    # _split's arrays on ``parts`` threads, each a contiguous part of the particles: a part counts its
    # large particles, then writes its rows and small indices after those of the parts before it (each part
    # a call on its slices: a loop written inline in a parallel loop ran 2x slower a thread). The arrays are
    # _split's, element for element (a part's small indices are local, then shifted by its start).
    n, d = particles.shape
    large_before = np.empty(parts + 1, dtype=np.int64)  # not np.zeros: a parallel loop here (dtpf.entity.cores)
    large_before[0] = 0
    for p in numba.prange(parts):
        large_before[p + 1] = _count_large(weights[n * p // parts:n * (p + 1) // parts], limit)
    for p in range(parts):
        large_before[p + 1] += large_before[p]
    n_large = large_before[parts]
    small = np.empty(n - n_large, dtype=np.int32)
    rows = np.empty((n_large, d))
    out = np.empty((n, d))
    for p in numba.prange(parts):
        start, end = n * p // parts, n * (p + 1) // parts
        first, last = start - large_before[p], end - large_before[p + 1]
        _split_part(weights[start:end], limit, particles[start:end], small[first:last],
                    rows[large_before[p]:large_before[p + 1]], out[start:end])
        for j in range(first, last):
            small[j] += start
    return small, rows, out


def split(weights, limit, particles, capacity):
    """Eq. 28: (indices of the small particles, rows of the large ones in index order, a copy of the
    particles); on the process's threads from PARALLEL_MIN particles on (the same arrays)."""
    if cores.parallel(weights.shape[0]):
        return _split_parallel(weights, limit, particles, capacity, cores.parts(weights.shape[0]))
    return _split(weights, limit, particles, capacity)


# --- the random stream of the rules --------------------------------------------
# Each small particle needs three numbers (partner, r, u). Drawing them inside
# the compiled loop from a xoshiro256** generator (Blackman and Vigna 2018),
# seeded by four words from the caller's numpy Generator, saves three arrays
# of N numbers and their memory traffic; it costs about 1 ns per number.

_U = np.uint64


@numba.njit(inline="always")
def _rotl(x, k):  # pragma: no cover - compiled
    return (x << k) | (x >> (_U(64) - k))


@numba.njit(inline="always")
def _next(s0, s1, s2, s3):  # pragma: no cover - compiled
    # One xoshiro256** step on a state held in locals (an array would be
    # reloaded from memory after every store to the output).
    result = _rotl(s1 * _U(5), _U(7)) * _U(9)
    t = s1 << _U(17)
    s2 ^= s0
    s3 ^= s1
    s1 ^= s2
    s0 ^= s3
    s2 ^= t
    s3 = _rotl(s3, _U(45))
    return result, s0, s1, s2, s3


@numba.njit(inline="always")
def _uniform(s0, s1, s2, s3):  # pragma: no cover - compiled
    # 53 random bits -> a double in [0, 1), and the next state.
    bits, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
    return (bits >> _U(11)) * (1.0 / 9007199254740992.0), s0, s1, s2, s3


def _seed(rng: np.random.Generator) -> np.ndarray:
    """The xoshiro256** state of one preprocessing, drawn from ``rng``: four uniform 64-bit words,
    ``rng.integers(0, 2**64, size=4, dtype=np.uint64)`` (for a PCG64, the same words as its next
    four raw outputs, which take a tenth of the time)."""
    if type(rng.bit_generator) is np.random.PCG64:
        return rng.bit_generator.random_raw(4).astype(np.uint64, copy=False)
    return rng.integers(0, 2 ** 64, size=4, dtype=np.uint64, endpoint=False)


@numba.njit(inline="always")
def _factor(r, u, ps):  # pragma: no cover - compiled
    # f with x_tilde = x_m + f x_l: Eq. 29 into Eq. 30 gives r (2r - 1) on the
    # mixed branch u <= PS (Eq. 33) and 2r - 1 on the plain branch (Eq. 34).
    return (2.0 * r - 1.0) * (r if u <= ps else 1.0)


@numba.njit(cache=True, nogil=True)
def _factors(r, u, ps):  # pragma: no cover - compiled
    factors = np.empty(r.shape[0])
    for l in range(r.shape[0]):
        factors[l] = _factor(r[l], u[l], ps)
    return factors


@numba.njit(cache=True, nogil=True)
def _draws(state, n_small, n_large):  # pragma: no cover - compiled
    # The numbers _preprocess draws, in its order: partner position, r, u.
    partners = np.empty(n_small, dtype=np.int64)
    r = np.empty(n_small)
    u = np.empty(n_small)
    s0, s1, s2, s3 = state[0], state[1], state[2], state[3]
    for l in range(n_small):
        v, s0, s1, s2, s3 = _uniform(s0, s1, s2, s3)
        partners[l] = int(v * n_large)
        r[l], s0, s1, s2, s3 = _uniform(s0, s1, s2, s3)
        u[l], s0, s1, s2, s3 = _uniform(s0, s1, s2, s3)
    return partners, r, u


@numba.njit(inline="always")
def _mixed_below(ps):  # pragma: no cover - compiled
    # u <= PS for u = b * 2**-53 (b the top 53 bits of a draw) is b <= floor(PS * 2**53), exactly:
    # the scaling by a power of two is exact, so the branch of Eq. 30 needs no conversion of u.
    return _U(np.floor(ps * 9007199254740992.0))


@numba.njit(inline="always")
def _draw(s0, s1, s2, s3, n_large, mixed_below):  # pragma: no cover - compiled
    # One small particle's three draws, in the stream's order: its partner's position m in the large
    # rows, r, then u (decided as u <= PS on the draw's 53 bits, _mixed_below). Returns (m, f, mixed,
    # the next state) with f = (2 r - 1) (r if u <= PS else 1), the factor of Eq. 33-34 (_factor).
    v, s0, s1, s2, s3 = _uniform(s0, s1, s2, s3)
    r, s0, s1, s2, s3 = _uniform(s0, s1, s2, s3)
    bits, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
    mixed = (bits >> _U(11)) <= mixed_below
    return _U(int(v * n_large)), (2.0 * r - 1.0) * (r if mixed else 1.0), mixed, s0, s1, s2, s3


@numba.njit(inline="always")
def _put_moved(particles, rows, out, i, m, f, d):  # pragma: no cover - compiled
    # out[i] = x_m + f x_l (Eq. 29-30), i and m unsigned (numba checks every signed index for a
    # negative value); for d = 1 without the loop over components, which serialises the random reads.
    if d == 1:
        out[i, 0] = rows[m, 0] + f * particles[i, 0]
    else:
        for c in range(d):
            out[i, c] = rows[m, c] + f * particles[i, c]


@numba.njit(cache=True, nogil=True)
def _move(particles, small, rows, ps, state, out):  # pragma: no cover - compiled
    # For each small particle x_l in index order: its partner x_m drawn uniformly from the large
    # rows, r and u, then out[l] = x_m + f x_l (Eq. 29-30). Returns the number on the mixed branch.
    # Draws and moves alternate particle by particle: for small sets (_rules), where the block
    # arrays of _move_blocked cost more than they save.
    n_large = rows.shape[0]
    d = particles.shape[1]
    mixed_below = _mixed_below(ps)
    n_mixed = 0
    s0, s1, s2, s3 = state[0], state[1], state[2], state[3]
    for l in range(small.shape[0]):
        m, f, mixed, s0, s1, s2, s3 = _draw(s0, s1, s2, s3, n_large, mixed_below)
        n_mixed += mixed
        _put_moved(particles, rows, out, _U(small[l]), m, f, d)
    return n_mixed


#: Small particles whose draws _move_blocked makes before it moves them.
MOVE_BLOCK = 128


@numba.njit(cache=True, nogil=True)
def _move_blocked(particles, small, rows, ps, state, out):  # pragma: no cover - compiled
    # _move's numbers (the same draws in the same order, the same out), in blocks of MOVE_BLOCK
    # particles: first the block's draws (a dependency chain through the generator's state), then
    # its moves, whose random reads of the partners are independent of each other, so the processor
    # overlaps them instead of waiting on the generator between two reads; the gain grows with d
    # (docs/results/kernels.md).
    n_large = rows.shape[0]
    d = particles.shape[1]
    mixed_below = _mixed_below(ps)
    n_mixed = 0
    s0, s1, s2, s3 = state[0], state[1], state[2], state[3]
    partners = np.empty(MOVE_BLOCK, dtype=np.uint64)
    factors = np.empty(MOVE_BLOCK)
    n_small = small.shape[0]
    for start in range(0, n_small, MOVE_BLOCK):
        count = min(MOVE_BLOCK, n_small - start)
        for j in range(count):
            partners[j], factors[j], mixed, s0, s1, s2, s3 = _draw(s0, s1, s2, s3, n_large, mixed_below)
            n_mixed += mixed
        for j in range(count):
            _put_moved(particles, rows, out, _U(small[start + j]), partners[j], factors[j], d)
    return n_mixed


#: xoshiro256**'s jump polynomial: the state 2**128 draws on (Blackman and Vigna 2018).
_JUMP = np.array([0x180EC6D33CFD0ABA, 0xD5A61266F0C9392C, 0xA9582618E03FC9AA, 0x39ABDC4529B1661C],
                 dtype=np.uint64)


@numba.njit(cache=True, nogil=True)
def _jumped(state, count):  # pragma: no cover - compiled
    # (count, 4) states: row b is ``state`` jumped b times (b * 2**128 draws on); row 0 is ``state``.
    states = np.empty((count, 4), dtype=np.uint64)
    s0, s1, s2, s3 = state[0], state[1], state[2], state[3]
    for b in range(count):
        states[b, 0], states[b, 1], states[b, 2], states[b, 3] = s0, s1, s2, s3
        t0, t1, t2, t3 = _U(0), _U(0), _U(0), _U(0)
        for word in range(4):
            for bit in range(64):
                if (_JUMP[word] >> _U(bit)) & _U(1):
                    t0 ^= s0
                    t1 ^= s1
                    t2 ^= s2
                    t3 ^= s3
                _, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
        s0, s1, s2, s3 = t0, t1, t2, t3
    return states


@numba.njit(cache=True, nogil=True)
def _move_block(particles, small, rows, mixed_below, state, out):  # pragma: no cover - compiled
    # _move_blocked's loop for one block's small particles ``small`` with the stream ``state``; the number on
    # the mixed branch.
    n_large = rows.shape[0]
    d = particles.shape[1]
    s0, s1, s2, s3 = state[0], state[1], state[2], state[3]
    partners = np.empty(MOVE_BLOCK, dtype=np.uint64)
    factors = np.empty(MOVE_BLOCK)
    n_mixed = 0
    for start in range(0, small.shape[0], MOVE_BLOCK):
        count = min(MOVE_BLOCK, small.shape[0] - start)
        for j in range(count):
            partners[j], factors[j], mixed, s0, s1, s2, s3 = _draw(s0, s1, s2, s3, n_large, mixed_below)
            n_mixed += mixed
        for j in range(count):
            _put_moved(particles, rows, out, _U(small[start + j]), partners[j], factors[j], d)
    return n_mixed


@numba.njit(cache=True, nogil=True, parallel=True)
def _move_blocks(particles, small, rows, ps, states, starts, out):  # pragma: no cover - compiled
    # _move_blocked for a set in blocks: block b moves the small particles small[starts[b]:starts[b+1]]
    # (those of its particles) with the draws of the stream states[b], in _move_blocked's order; the
    # blocks run on the threads (each a call on its slices: a loop written inline in a parallel loop ran 2x
    # slower a thread). Returns the number on the mixed branch, summed in block order.
    mixed_below = _mixed_below(ps)
    blocks = starts.shape[0] - 1
    mixed_of = np.empty(blocks, dtype=np.int64)  # each block writes its own
    for b in numba.prange(blocks):
        mixed_of[b] = _move_block(particles, small[starts[b]:starts[b + 1]], rows, mixed_below, states[b], out)
    total = 0
    for b in range(blocks):
        total += mixed_of[b]
    return total


def move_blocks(particles, small, rows, ps, state, out, block):
    """Eq. 29-30 for the small particles of a set in blocks of ``block`` particles: block b's small
    particles draw, in index order, from the xoshiro256** stream ``state`` jumped b times (block 0 from
    ``state`` itself, as one block would). Returns the number on the mixed branch."""
    n = particles.shape[0]
    count = cores.blocks(n, block)
    # The first particle of each block in small's own dtype: searchsorted would cast all of small otherwise.
    edges = np.minimum(np.arange(count + 1, dtype=np.int64) * block, n).astype(small.dtype)
    starts = np.searchsorted(small, edges).astype(np.int64)
    starts[-1] = small.shape[0]
    cores.use(n)
    return _move_blocks(particles, small, rows, ps, _jumped(state, count), starts, out)


@numba.njit(cache=True, nogil=True)
def _rules(particles, weights, limit, rank, capacity, ps, state):  # pragma: no cover - compiled
    # Eq. 28-30 in one call, for small sets, where each call into compiled code costs more than
    # the work: W (the value of ascending rank ``rank`` if rank >= 0, else ``limit``), the split,
    # the copy and the moves. Returns (new particles, W, M, N - M, number mixed).
    if rank >= 0:
        limit = np.partition(weights, rank)[rank]
    small, rows, out = _split(weights, limit, particles, capacity)
    if rows.shape[0] == 0 or small.shape[0] == 0:
        return out, limit, rows.shape[0], 0, 0
    return out, limit, rows.shape[0], small.shape[0], _move(particles, small, rows, ps, state, out)


def warm_up_threads(particles: np.ndarray, weights: np.ndarray) -> None:
    """Compile (or load) the kernels a set of PARALLEL_MIN particles or more takes on the threads, on a small
    set of the kinds given (read-only arrays compile apart), so that a layer's first such step does not."""
    ranks = np.array([0, weights.size // 2, weights.size - 1])
    for few in (select.FEW_MEMBERS, -1):  # one level of buckets, and two
        select._order_statistics_parallel(np.ascontiguousarray(weights), ranks, 2, few)
    _split_parallel(weights, float(np.median(weights)), particles, weights.size, 2)


def draws(rng: np.random.Generator, n_small: int, n_large: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The random numbers :func:`preprocess` draws from ``rng`` for ``n_small`` small particles.

    Returns
    -------
    partners : (n_small,) int64
        Position of each small particle's partner in the large set (index order).
    r, u : (n_small,) float64
        r of Eq. 29-30 and u of Eq. 30.
    """
    return _draws(_seed(rng), int(n_small), int(n_large))


def apply_rules(x_m: np.ndarray, x_l: np.ndarray, r: np.ndarray, u: np.ndarray, ps: float) -> np.ndarray:
    """Eq. 29 and Eq. 30 for given random numbers.

    Parameters
    ----------
    x_m : (L, d) ndarray
        The large particle paired with each small one.
    x_l : (L, d) ndarray
        The small particles.
    r, u : (L,) ndarray
        r of Eq. 29-30 and u of Eq. 30, one per small particle.
    ps : float
        Degree factor PS in [0, 1].

    Returns
    -------
    x_tilde : (L, d) ndarray
    """
    # Eq. 29 into Eq. 30 simplifies to x_tilde = x_m + f x_l (Eq. 33, 34).
    factors = _factors(np.asarray(r, dtype=np.float64), np.asarray(u, dtype=np.float64), float(ps))
    return x_m + factors[:, None] * x_l


def spread(particles: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(d,) weighted standard deviation of each component of the set (sigma of the relative rule)."""
    mean = weights @ particles
    centred = particles - mean
    return np.sqrt(np.maximum(weights @ (centred * centred), 0.0))


def apply_relative(x_m: np.ndarray, x_l: np.ndarray, r: np.ndarray, u: np.ndarray, ps: float,
                   sigma: np.ndarray) -> np.ndarray:
    """The relative rule for given random numbers: x_m + f c (x_l - x_m), c = min(1, sigma / |x_l - x_m|).

    f is the factor of Eq. 33-34 (the paper's, from r, u and PS); ``sigma``
    is the (d,) weighted spread of the set (:func:`spread`). Translation
    invariant: it reads positions only through x_l - x_m.
    """
    factors = _factors(np.asarray(r, dtype=np.float64), np.asarray(u, dtype=np.float64), float(ps))
    diff = x_l - x_m
    size = np.abs(diff)
    with np.errstate(divide="ignore", invalid="ignore"):
        cap = np.where(size > sigma, sigma / size, 1.0)
    return x_m + factors[:, None] * cap * diff


def move_relative(x: np.ndarray, w: np.ndarray, threshold_rule: str | float, ps: float,
                  rng: np.random.Generator):
    """(new particles or None, W, M, N - M, mixed) of the relative rule (the move rule "relative",
    :mod:`dtpf.information.move_rules`): the same split and draws as the paper's rule (:func:`draws`,
    after the seed words of :func:`_seed`)."""
    limit, _ = _threshold(w, threshold_rule)
    small = np.flatnonzero(w <= limit)
    large = np.flatnonzero(w > limit)
    if large.size == 0 or small.size == 0:
        return None, float(limit), int(large.size), 0, 0
    partners, r, u = draws(rng, small.size, large.size)
    out = x.copy()
    out[small] = apply_relative(x[large[partners]], x[small], r, u, ps, spread(x, w))
    return out, float(limit), int(large.size), int(small.size), int(np.count_nonzero(u <= ps))


#: Below this many particles :func:`preprocess` makes one compiled call (numba's np.partition selects W);
#: from it on, numpy's partition or the radix select (dtpf.information.select) is faster than that.
SMALL_SET = 1 << 12


def size_class(n: int) -> int:
    """The smallest set that takes the code path :func:`preprocess` and the mirror take for N = ``n``: 8
    (one compiled call, below SMALL_SET), SMALL_SET (three calls) or RADIX_MIN (W and the quantiles from
    the radix select); what a layer warms up on."""
    return 8 if n < SMALL_SET else SMALL_SET if n < RADIX_MIN else RADIX_MIN


def _preprocess_small(x, w, threshold_rule, ps, rng):
    """:func:`preprocess`'s numbers for N < SMALL_SET and a PCG64, in one compiled call: (new particles
    or None, W, M, N - M, mixed). The four seed words are drawn first and given back (the PCG64 steps
    back 4) when nothing is moved, so ``rng`` ends where the general path leaves it."""
    member = THRESHOLDS.get(threshold_rule) if isinstance(threshold_rule, str) else None
    order = getattr(member, "order", None)
    if order is not None:  # W selected in the compiled call (neff: the (k+1)-th largest weight)
        limit = 0.0
        rank, capacity = order(w)
    else:
        (limit, capacity), rank = _threshold(w, threshold_rule), -1
    out, limit, n_large, n_small, n_mixed = _rules(x, w, limit, rank, capacity, ps, _seed(rng))
    if n_large == 0 or n_small == 0:
        rng.bit_generator.advance(-4 % 2 ** 128)
        return None, float(limit), int(n_large), 0, 0
    return out, float(limit), int(n_large), int(n_small), int(n_mixed)


def move_paper(x: np.ndarray, w: np.ndarray, threshold_rule: str | float, ps: float, rng: np.random.Generator,
               *, block: int | None = None):
    """(new particles or None, W, M, N - M, mixed) of Eq. 29-30 as printed (the move rule "paper",
    :mod:`dtpf.information.move_rules`): one compiled call for a small set drawn from a PCG64, else the
    split, then the moves in blocks of MOVE_BLOCK (the same numbers). ``block``: B of a run
    (:mod:`dtpf.entity.cores`); a set of more than B particles moves in blocks of B, each drawing from its
    own stream (:func:`move_blocks`), on the process's threads."""
    if w.size < SMALL_SET and type(rng.bit_generator) is np.random.PCG64:
        return _preprocess_small(x, w, threshold_rule, ps, rng)
    limit, capacity = _threshold(w, threshold_rule)
    small_idx, large_rows, new_particles = split(w, limit, x, capacity)
    n_small, n_large = small_idx.size, large_rows.shape[0]
    if n_large == 0 or n_small == 0:
        return None, limit, n_large, 0, 0
    if cores.blocks(w.size, block) > 1:
        n_mixed = int(move_blocks(x, small_idx, large_rows, ps, _seed(rng), new_particles, block))
    else:
        n_mixed = int(_move_blocked(x, small_idx, large_rows, ps, _seed(rng), new_particles))
    return new_particles, limit, n_large, n_small, n_mixed


def unprocessed(particles, weights, ps: float, *, threshold_rule: str | float = "neff",
                checked: bool = False) -> PreprocessResult:
    """The set as it is, when the system layer has turned preprocessing off for a step.

    The report gives W and M as :func:`preprocess` would (the mirror reads W)
    and no processed particle; particles and weights are read-only views of
    the inputs, so the entity resamples exactly the set it sent.
    """
    x, w = check_set(particles, weights, checked=checked)
    ps = check_probability(ps, "PS")
    limit, _ = _threshold(w, threshold_rule)
    x, w = x.view(), w.view()
    x.flags.writeable = w.flags.writeable = False
    return PreprocessResult(x, w, PreprocessReport(float(limit), int(np.count_nonzero(w > limit)), 0, 0, 0, ps))


def preprocess(
    particles,
    weights,
    ps: float,
    rng: np.random.Generator,
    *,
    threshold_rule: str | float = "neff",
    weight_rule: str = "inherit",
    log_likelihood: LogLikelihood | None = None,
    checked: bool = False,
    move_rule: str = "paper",
    block: int | None = None,
) -> PreprocessResult:
    """Move small-weight particles towards large-weight ones (Eq. 28-30).

    Parameters
    ----------
    particles : (N,) or (N, d) array_like
    weights : (N,) array_like, normalised
    ps : float
        Degree factor PS in [0, 1] (Eq. 30).
    rng : numpy.random.Generator
        Seeds the rules' stream: four 64-bit words start a xoshiro256**
        generator that gives, for each small particle in index order, the
        position of x_m in the large set, then r, then u (see :func:`draws`).
    threshold_rule : "neff", "inverse-n", a reference to a user's rule, or float
        How W of Eq. 28 is chosen; see :func:`threshold`.
    weight_rule : "inherit" or "likelihood"
        Weights of processed particles (:mod:`dtpf.information.weight_rules`); see the module docstring.
    log_likelihood : callable, optional
        ``(M, d) -> (M,)`` log p(z_k | x); required by ``"likelihood"``.
    checked : bool
        The arrays passed :func:`~dtpf.messages.arrays.check_weights` and
        :func:`~dtpf.messages.arrays.check_particles` already (a decoded message):
        only their dtype, rank and lengths are checked again.
    move_rule : "paper" or "relative"
        Eq. 29-30 as printed (default), or the translation-invariant rule
        of the module docstring (:mod:`dtpf.information.move_rules`); both use
        the same split and random numbers.
    block : int, optional
        B of the run (its ``block_particles``, :mod:`dtpf.entity.cores`): the paper's moves of a set of
        more than B particles draw each block's numbers from its own stream; None: one block.

    Returns
    -------
    PreprocessResult
        New particles; weights as a new array (``"likelihood"``) or a
        read-only view of the input (``"inherit"``); the inputs are not modified.
    """
    x, w = check_set(particles, weights, checked=checked)
    ps = check_probability(ps, "PS")
    weigh = WEIGHT_RULE_REGISTRY.get(weight_rule)
    needs_likelihood = getattr(weigh, "needs_likelihood", False)
    if needs_likelihood and log_likelihood is None:
        raise ValueError(f"weight rule {weight_rule!r} needs the observation's log_likelihood")
    move = MOVE_RULE_REGISTRY.get(move_rule)

    if move_rule == "paper" and cores.blocks(w.size, block) > 1:
        new_particles, limit, n_large, n_small, n_mixed = move_paper(x, w, threshold_rule, ps, rng, block=block)
    else:
        new_particles, limit, n_large, n_small, n_mixed = move(x, w, threshold_rule, ps, rng)
    if new_particles is None:
        report = PreprocessReport(limit, n_large, 0, 0, 0, ps)
        return PreprocessResult(x.copy(), w.copy(), report)
    new_weights = weigh(w, limit, x, new_particles, log_likelihood if needs_likelihood else None)
    report = PreprocessReport(limit, n_large, n_small, n_mixed, n_small - n_mixed, ps)
    return PreprocessResult(new_particles, new_weights, report)
