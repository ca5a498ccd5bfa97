"""Resampling schemes: probability-one facts, then seeded statistics.

Statistical tolerances come from the variance of what is estimated: the mean
of R i.i.d. offspring counts has standard error sd / sqrt(R), and every
scheme's per-particle variance is at most the multinomial one,
N w (1 - w). With Z = 5 and the fixed seeds below, a correct scheme fails
with probability below 1e-5 per particle.
"""
import numpy as np
import pytest

from dtpf.entity import resampling as rs

SCHEMES = sorted(rs.RESAMPLERS)
Z = 5.0
REPEATS = 4000


def skewed_weights(n=40, seed=1):
    """Strongly skewed weights: a few particles carry most of the mass."""
    lw = np.random.default_rng(seed).normal(scale=2.0, size=n)
    w = np.exp(lw)
    return w / w.sum()


def offspring(scheme, weights, repeats, seed):
    """(repeats, N) offspring counts of ``scheme`` on ``weights``."""
    rng = np.random.default_rng(seed)
    n = weights.size
    return np.array([np.bincount(rs.RESAMPLERS[scheme](weights, rng), minlength=n) for _ in range(repeats)])


# --- probability-one facts -------------------------------------------------

@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("n", [1, 2, 7, 49, 1000])
def test_output_contract(scheme, n):
    rng = np.random.default_rng(0)
    w = skewed_weights(n) if n > 1 else np.ones(1)
    ancestors = rs.RESAMPLERS[scheme](w, rng)
    assert ancestors.shape == (n,)
    assert ancestors.dtype == np.int64
    assert ancestors.min() >= 0 and ancestors.max() < n
    assert np.all(np.diff(ancestors) >= 0), "ancestors are sorted"


@pytest.mark.parametrize("scheme", ["stratified", "systematic", "residual"])
@pytest.mark.parametrize("n", [3, 49, 1000])
def test_equal_weights_give_identity(scheme, n):
    ancestors = rs.RESAMPLERS[scheme](np.full(n, 1.0 / n), np.random.default_rng(3))
    np.testing.assert_array_equal(ancestors, np.arange(n))


@pytest.mark.parametrize("scheme", SCHEMES)
def test_single_weight_takes_everything(scheme):
    w = np.zeros(10)
    w[6] = 1.0
    np.testing.assert_array_equal(rs.RESAMPLERS[scheme](w, np.random.default_rng(0)), np.full(10, 6))


@pytest.mark.parametrize("scheme", SCHEMES)
def test_zero_weights_are_never_drawn(scheme):
    rng = np.random.default_rng(5)
    w = np.zeros(51)
    w[::2] = skewed_weights(26, seed=2)  # even indices only, including the first and last
    for _ in range(200):
        assert np.all(rs.RESAMPLERS[scheme](w, rng) % 2 == 0)


def test_systematic_counts_stay_within_floor_and_ceil():
    w = skewed_weights(40)
    counts = offspring("systematic", w, 2000, seed=11)
    n = w.size
    assert np.all(counts >= np.floor(n * w))
    assert np.all(counts <= np.ceil(n * w))


def test_residual_keeps_the_integer_part():
    w = skewed_weights(40)
    counts = offspring("residual", w, 2000, seed=12)
    assert np.all(counts >= np.floor(w.size * w))


@pytest.mark.parametrize("scheme", SCHEMES)
def test_same_seed_same_ancestors(scheme):
    w = skewed_weights(500)
    a = rs.RESAMPLERS[scheme](w, np.random.default_rng(42))
    b = rs.RESAMPLERS[scheme](w, np.random.default_rng(42))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_weights_summing_slightly_above_one_stay_in_bounds(scheme):
    n = 1000
    w = np.full(n, (1.0 + 9e-7) / n)  # within the accepted tolerance of 1e-6
    ancestors = rs.RESAMPLERS[scheme](w, np.random.default_rng(0))
    assert ancestors.shape == (n,) and ancestors.max() < n


# --- statistics --------------------------------------------------------------

@pytest.mark.parametrize("scheme", SCHEMES)
def test_offspring_counts_are_unbiased(scheme):
    w = skewed_weights(40)
    n = w.size
    counts = offspring(scheme, w, REPEATS, seed=100 + SCHEMES.index(scheme))
    expected = n * w
    standard_error = np.sqrt(n * w * (1 - w) / REPEATS)
    deviation = np.abs(counts.mean(axis=0) - expected)
    worst = int(np.argmax(deviation / np.maximum(standard_error, 1e-12)))
    assert np.all(deviation <= Z * standard_error + 1e-12), (
        f"particle {worst}: mean {counts.mean(axis=0)[worst]:.4f}, expected {expected[worst]:.4f}"
    )


def test_multinomial_variance_matches_theory_and_is_the_largest():
    w = skewed_weights(40)
    n = w.size
    variance = {s: offspring(s, w, REPEATS, seed=7).var(axis=0, ddof=1).sum() for s in SCHEMES}
    theory = float(np.sum(n * w * (1 - w)))
    # A sample variance over R draws has relative standard error about
    # sqrt(2 / (R - 1)) for near-normal counts; the sum over particles is no worse.
    tolerance = Z * np.sqrt(2.0 / (REPEATS - 1)) * theory
    assert abs(variance["multinomial"] - theory) <= tolerance, (variance, theory)
    for scheme in ("residual", "stratified", "systematic"):
        assert variance[scheme] < variance["multinomial"] - tolerance, (scheme, variance)
    # Systematic counts are floor or ceil of N w_i: the smallest possible variance.
    frac = n * w - np.floor(n * w)
    assert variance["systematic"] <= np.sum(frac * (1 - frac)) + tolerance


def test_multinomial_draws_are_iid_from_the_weights():
    """Eq. 26 ordered uniforms: draws of one call follow W (total-variation check)."""
    w = skewed_weights(20)
    n_draws = 200_000
    ancestors = rs.multinomial(np.repeat(w / 10_000, 10_000), np.random.default_rng(9)) // 10_000
    freq = np.bincount(ancestors, minlength=w.size) / n_draws
    se = np.sqrt(w * (1 - w) / n_draws)
    assert np.all(np.abs(freq - w) <= Z * se)


# --- bad input ---------------------------------------------------------------

@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("weights, message", [
    ([], "weights is empty"),
    ([[0.5, 0.5]], r"weights must be 1-D, got shape \(1, 2\)"),
    ([0.5, np.nan, 0.5], r"weights contain NaN values at index 1 \(value nan\)"),
    ([0.5, np.inf], r"weights contain infinite values at index 1"),
    ([0.7, -0.2, 0.5], r"weights contain negative values at index 1 \(value -0.2\)"),
    ([0.0, 0.0], r"weights are all zero \(N=2\)"),
    ([0.2, 0.2], r"weights must sum to 1 .* got sum 0.4"),
])
def test_bad_weights_are_named(scheme, weights, message):
    with pytest.raises(ValueError, match=message):
        rs.RESAMPLERS[scheme](np.asarray(weights, dtype=float), np.random.default_rng(0))


def test_unknown_scheme_is_named():
    with pytest.raises(ValueError, match="unknown resampler 'sistematic'; expected one of"):
        rs.get("sistematic")


def test_inverse_cdf_picks_the_interval_of_each_point():
    w = np.array([0.1, 0.0, 0.4, 0.5])
    points = np.array([0.0, 0.0999, 0.1, 0.49, 0.5, 0.99999])
    np.testing.assert_array_equal(rs.inverse_cdf(points, w), [0, 0, 2, 2, 3, 3])


# --- the same numbers as the plain merge --------------------------------------
# The compiled kernels write each particle's first copies without a branch. These references are
# the plain merges they replace ("while the next point is below the running sum, take it"), in
# Python, with the same floating-point operations: the ancestors must be the same, bit for bit.

def _plain_merge(weights, points_below, m):
    """Ancestors from ``points_below(k, running sum)``: the plain merge with the tail guard."""
    ancestors = np.empty(m, dtype=np.int64)
    cumulative, k = 0.0, 0
    for j, w in enumerate(weights):
        cumulative += w
        while k < m and points_below(k, cumulative):
            ancestors[k] = j
            k += 1
    positive = np.flatnonzero(weights > 0)
    ancestors[k:] = positive[-1] if positive.size else weights.size - 1
    return ancestors


def reference(scheme, weights, rng):
    n = weights.size
    if scheme == "systematic":
        u = rng.random()
        return _plain_merge(weights, lambda k, c: k < int(np.ceil(c * n - u)), n)
    if scheme == "stratified":
        v = rng.random(n)
        return _plain_merge(weights, lambda k, c: k + v[k] < c * n, n)
    if scheme == "multinomial":
        e = rng.standard_exponential(n + 1)
        total = 0.0
        for x in e:
            total += x
        points = np.empty(n)
        point = e[0]
        for k in range(n):
            points[k] = point
            point += e[k + 1]
        return _plain_merge(weights * total, lambda k, c: points[k] < c, n)
    raise ValueError(scheme)


def merge_cases():
    """Weights the branch-free writes could get wrong: zeros, ties, integer N w, long runs of copies."""
    rng = np.random.default_rng(31)
    for n in (1, 2, 3, 7, 50, 333):
        yield skewed_weights(n, seed=n) if n > 1 else np.ones(1)
        yield np.full(n, 1.0 / n)
        w = rng.integers(0, 4, n).astype(float)  # N C_j lands on integers
        w[0] += 1.0
        yield w / w.sum()
        w = np.exp(3.0 * rng.standard_normal(n))  # a few particles take most points
        w[rng.random(n) < 0.4] = 0.0
        w[-1] = 1.0
        yield w / w.sum()


@pytest.mark.parametrize("scheme", ["systematic", "stratified", "multinomial"])
def test_ancestors_are_those_of_the_plain_merge(scheme):
    for i, w in enumerate(merge_cases()):
        for seed in range(5):
            expected = reference(scheme, w, np.random.default_rng(seed))
            rng = np.random.default_rng(seed)
            got = rs.RESAMPLERS[scheme](w, rng)
            np.testing.assert_array_equal(got, expected, err_msg=f"case {i}, seed {seed}")
            after = np.random.default_rng(seed)
            reference(scheme, w, after)
            assert rng.random() == after.random(), "the scheme draws what the plain merge draws"


def test_stratified_points_that_round_up_to_the_running_sum():
    # Point k is float(k) + v_k: with v_k = 1 - 2**-53 it rounds to k + 1, which is not below a running
    # sum of exactly k + 1; with v = 0 it sits on N C_j exactly, not below either.
    from dtpf.entity import _merge

    n = 8
    w = np.full(n, 1.0 / n)
    for v in (np.full(n, 1.0 - 2.0 ** -53), np.zeros(n), np.tile([0.0, 1.0 - 2.0 ** -53], n // 2)):
        expected = _plain_merge(w, lambda k, c: k + v[k] < c * n, n)
        np.testing.assert_array_equal(_merge.stratified(w, v, np.empty(n, dtype=np.int64)), expected)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_out_buffer_and_checked_weights_give_the_same_ancestors(scheme):
    w = skewed_weights(300)
    expected = rs.RESAMPLERS[scheme](w, np.random.default_rng(8))
    out = np.full(300, -1, dtype=np.int64)
    got = rs.RESAMPLERS[scheme](w, np.random.default_rng(8), out=out, checked=True)
    assert got is out
    np.testing.assert_array_equal(out, expected)


@pytest.mark.parametrize("out", [np.empty(5, dtype=np.int64), np.empty(10), np.empty(20, dtype=np.int64)[::2]])
def test_an_out_buffer_that_cannot_hold_the_ancestors_is_named(out):
    with pytest.raises(ValueError, match=r"out must be a writeable C-contiguous int64 array of shape \(10,\)"):
        rs.systematic(np.full(10, 0.1), np.random.default_rng(0), out=out)


def test_checked_weights_of_another_type_are_still_checked():
    with pytest.raises(ValueError, match="weights must sum to 1"):
        rs.systematic([0.2, 0.2], np.random.default_rng(0), checked=True)  # a list: scanned in full


def test_distinct_counts_the_parents():
    assert rs.distinct(np.array([0, 0, 2, 3, 3, 3, 9])) == 4
    assert rs.distinct(np.array([5])) == 1


# --- the inline PCG64 path against numba's Generator methods --------------------
# For a PCG64 the schemes draw from an inline copy of its state (dtpf.entity._merge.pcg_*), merge
# several points at a time and keep their uniforms in a ring or their points in the output
# itself; for any other bit generator they take the Generator's own methods. Both must give the
# same ancestors and leave the generator in the same state, on sets large enough to reach the
# rings, the catch-up and pause of stratified's drawing, and the last points' plain merge.

def large_cases():
    """Weights of 1 to 30,000 particles shaped to stress the merges."""
    rng = np.random.default_rng(41)
    for n in (1, 5, 9, 17, 4099, 30_000):
        lw = rng.standard_normal(n)
        yield np.exp(lw) / np.exp(lw).sum()                      # the benchmark's weights
        w = np.sort(np.exp(2.0 * rng.standard_normal(n)))          # heavy particles last: m lags
        yield w / w.sum()
        yield w[::-1] / w.sum()                                   # heavy particles first: m runs ahead
        w = np.zeros(n)
        w[rng.integers(0, n, max(n // 1000, 1))] = 1.0            # a few particles take everything
        yield w / w.sum()
        yield np.full(n, 1.0 / n)
        w = rng.integers(0, 3, n).astype(float)                   # N C_j on integers, zeros between
        w[-1] += 1.0
        yield w / w.sum()


#: The schemes with an inline PCG64 path in dtpf.entity._merge (and a Generator path of the same name there).
INLINE_PCG64 = ("multinomial", "residual", "stratified", "systematic")


def _generator_path(scheme, w, rng):
    """The scheme through numba's Generator methods (the path of non-PCG64 bit generators)."""
    from dtpf.entity import _merge

    out = np.empty(w.size, dtype=np.int64)
    if scheme == "stratified":
        return _merge.stratified(w, rng.random(w.size), out)
    return getattr(_merge, scheme)(w, rng, out)


@pytest.mark.parametrize("scheme", ["stratified", "multinomial", "residual"])
def test_the_inline_pcg64_path_gives_the_generator_paths_numbers(scheme):
    for i, w in enumerate(large_cases()):
        for seed in range(3):
            rng, reference_rng = np.random.default_rng(seed), np.random.default_rng(seed)
            got = rs.RESAMPLERS[scheme](w, rng)
            np.testing.assert_array_equal(got, _generator_path(scheme, w, reference_rng),
                                          err_msg=f"case {i}, N={w.size}, seed {seed}")
            assert rng.bit_generator.state == reference_rng.bit_generator.state, (i, seed)


def test_inline_pcg64_draws_are_the_generators():
    from dtpf.entity import _merge

    for seed in range(3):
        rng = np.random.default_rng(seed)
        words = _merge.pcg_state(rng)
        np.testing.assert_array_equal(_merge.pcg_uniforms(words, np.empty(50_001)), rng.random(50_001))
        np.testing.assert_array_equal(words, _merge.pcg_state(rng))
        # 300,000 exponentials reach the ziggurat's rejections (about 1 in 100) and its tail.
        np.testing.assert_array_equal(_merge.pcg_exponentials(words, np.empty(300_001)),
                                      rng.standard_exponential(300_001))
        replica = np.random.default_rng(seed + 100)
        replica.bit_generator.state = {**replica.bit_generator.state,
                                       "state": {**rng.bit_generator.state["state"]}}
        _merge.set_pcg_state(replica, words)
        assert replica.bit_generator.state == rng.bit_generator.state


@pytest.mark.parametrize("scheme", SCHEMES)
def test_another_bit_generator_takes_the_generator_methods(scheme):
    w = skewed_weights(3000)
    rng = np.random.Generator(np.random.Philox(5))
    got = rs.RESAMPLERS[scheme](w, rng)
    reference_rng = np.random.Generator(np.random.Philox(5))
    if scheme == "systematic":
        expected = rs.systematic(w, reference_rng)
    elif scheme in INLINE_PCG64:
        expected = _generator_path(scheme, w, reference_rng)
    else:  # no inline path of its own: the Generator's methods are its only path, the same numbers again
        expected = rs.RESAMPLERS[scheme](w, reference_rng)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(rng.integers(0, 2 ** 62, 4), reference_rng.integers(0, 2 ** 62, 4))
