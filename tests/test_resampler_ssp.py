"""SSP resampling (Gerber, Chopin and Whiteley 2019): probability-one facts, then seeded statistics.

The offspring count of particle i is floor(N w_i) + B_i, B_i ~ Bernoulli(f_i), f_i = N w_i - floor(N w_i),
so its variance is f_i (1 - f_i). Tolerances come from that: the mean of R counts has standard error
sqrt(f (1 - f) / R), and Z = 5 of them (as tests/test_resampling.py). The sample variance of R counts is
R / (R - 1) p (1 - p) for the Bernoulli mean p = f + e, so |s^2 - f (1 - f)| <= |e| |1 - 2 f| + e^2 +
1 / (4 (R - 1)), with |e| <= Z sqrt(f (1 - f) / R). A sample covariance gets Z of its own standard error
(the standard deviation of the products of centred counts over sqrt(R)). With the fixed seeds below a
correct scheme fails with probability below 1e-5 per figure.
"""
import numpy as np
import pytest

from dtpf.entity import resampling as rs
from dtpf.entity.resamplers.ssp import ssp

Z = 5.0
REPEATS = 4000


def skewed_weights(n=40, seed=1):
    """Strongly skewed weights: a few particles carry most of the mass (as tests/test_resampling.py)."""
    w = np.exp(np.random.default_rng(seed).normal(scale=2.0, size=n))
    return w / w.sum()


def offspring(weights, repeats, seed, scheme=ssp):
    """(repeats, N) offspring counts of ``scheme`` on ``weights``."""
    rng = np.random.default_rng(seed)
    return np.array([np.bincount(scheme(weights, rng), minlength=weights.size) for _ in range(repeats)])


def fractional_parts(weights):
    scaled = weights.size * weights
    return scaled - np.floor(scaled)


# --- probability-one facts -------------------------------------------------

def test_ssp_is_a_built_in():
    assert rs.RESAMPLERS["ssp"] is ssp and rs.get("ssp") is ssp


def test_every_count_is_the_floor_of_n_w_or_one_more():
    w = skewed_weights(40)
    counts = offspring(w, 2000, seed=11)
    floor = np.floor(w.size * w)
    assert np.all((counts == floor) | (counts == floor + 1))
    assert np.all(counts.sum(axis=1) == w.size)


def test_integer_n_w_gives_exactly_those_counts():
    w = np.array([2.0, 0.0, 1.0, 3.0, 0.0, 1.0, 1.0, 0.0]) / 8
    rng = np.random.default_rng(4)
    for _ in range(50):
        np.testing.assert_array_equal(ssp(w, rng), [0, 0, 2, 3, 3, 3, 5, 6])


@pytest.mark.parametrize("n", [1, 2, 3, 49, 1000])
def test_equal_weights_give_identity(n):
    np.testing.assert_array_equal(ssp(np.full(n, 1.0 / n), np.random.default_rng(3)), np.arange(n))


def test_a_single_weight_of_one_takes_everything():
    w = np.zeros(10)
    w[6] = 1.0
    np.testing.assert_array_equal(ssp(w, np.random.default_rng(0)), np.full(10, 6))


def test_zero_weights_are_never_drawn():
    rng = np.random.default_rng(5)
    w = np.zeros(51)
    w[::2] = skewed_weights(26, seed=2)  # even indices only, including the first and last
    for _ in range(500):
        assert np.all(ssp(w, rng) % 2 == 0)


def test_the_ancestors_are_sorted_and_the_draws_are_n_minus_one_uniforms():
    w = skewed_weights(300)
    rng, reference = np.random.default_rng(8), np.random.default_rng(8)
    ancestors = ssp(w, rng)
    assert ancestors.dtype == np.int64 and np.all(np.diff(ancestors) >= 0)
    reference.random(w.size - 1)
    assert rng.bit_generator.state == reference.bit_generator.state


def test_weights_summing_slightly_off_one_still_give_n_ancestors():
    for total in (1.0 - 9e-7, 1.0 + 9e-7):  # within the accepted tolerance of 1e-6
        w = skewed_weights(1000, seed=3) * total
        counts = np.bincount(ssp(w, np.random.default_rng(1)), minlength=w.size)
        assert counts.sum() == w.size and np.all(counts[w == 0] == 0)
        assert np.all(np.abs(counts - w.size * w / total) < 1 + 1e-9)


# --- statistics --------------------------------------------------------------

def test_offspring_counts_are_unbiased():
    w = skewed_weights(40)
    counts = offspring(w, REPEATS, seed=21)
    f = fractional_parts(w)
    standard_error = np.sqrt(f * (1 - f) / REPEATS)
    deviation = np.abs(counts.mean(axis=0) - w.size * w)
    worst = int(np.argmax(deviation / np.maximum(standard_error, 1e-12)))
    assert np.all(deviation <= Z * standard_error + 1e-12), (
        f"particle {worst}: mean {counts.mean(axis=0)[worst]:.4f}, expected {w.size * w[worst]:.4f}")


def variance_tolerance(f):
    """Z-bound on |s^2 - f (1 - f)| of R Bernoulli(f) counts (see the module docstring)."""
    e = Z * np.sqrt(f * (1 - f) / REPEATS)
    return e * np.abs(1 - 2 * f) + e * e + 1 / (4 * (REPEATS - 1))


def test_variance_is_that_of_the_fractional_part_as_systematic_and_below_multinomial():
    w = skewed_weights(40)
    n = w.size
    f = fractional_parts(w)
    theory, tolerance = f * (1 - f), variance_tolerance(f)
    ours = offspring(w, REPEATS, seed=22).var(axis=0, ddof=1)
    systematic = offspring(w, REPEATS, seed=23, scheme=rs.systematic).var(axis=0, ddof=1)
    assert np.all(np.abs(ours - theory) <= tolerance), np.abs(ours - theory) / tolerance
    # Systematic's marginal counts are floor or ceil of N w too: the same variance, particle by particle.
    assert np.all(np.abs(ours - systematic) <= 2 * tolerance)
    # f (1 - f) is the smallest variance of an unbiased integer count: at most multinomial's N w (1 - w),
    # and far below it in sum on these weights.
    multinomial = n * w * (1 - w)
    assert np.all(ours <= multinomial + tolerance)
    assert ours.sum() + tolerance.sum() < 0.5 * multinomial.sum()


def test_counts_are_negatively_correlated():
    # Negative association (Dubhashi, Jonasson and Ranjan 2007; Gerber, Chopin and Whiteley 2019) gives
    # Cov(count_i, count_j) <= 0 for i != j; systematic resampling's counts are positively correlated for
    # some pairs (z above 60 with these weights and draws).
    w = skewed_weights(40)
    counts = offspring(w, REPEATS, seed=24).astype(float)
    centred = counts - counts.mean(axis=0)
    products = np.einsum("ri,rj->rij", centred, centred)
    covariance = products.sum(axis=0) / (REPEATS - 1)
    standard_error = products.std(axis=0, ddof=1) / np.sqrt(REPEATS)
    pairs = np.triu_indices(w.size, 1)
    z = covariance[pairs] / np.maximum(standard_error[pairs], 1e-12)
    assert np.all(covariance[pairs] <= Z * standard_error[pairs] + 1e-12), f"largest z = {z.max():.1f}"
