"""Killing resampling: probability-one facts, then seeded statistics.

The offspring count of particle i is B_i + M_i, B_i ~ Bernoulli(p_i), p_i = w_i / max w, M_i ~
Binomial(K, w_i) given the K killed; its variance (entity/resamplers/killing.py) is

    v_i = N w_i (1 - w_i) - w_i^2 (sum_j p_j^2 + (1 - 2 w_i) / m^2),   m = max w,

at most the multinomial N w_i (1 - w_i) and at least f_i (1 - f_i), f_i = frac(N w_i) (the least
variance of any unbiased integer count). Tolerances come from the sampling distributions: the mean of
R counts has standard error sqrt(v_i / R); the sample variance s_i^2 of R counts has standard error
sqrt((m4_i - s_i^4) / R), m4_i the sample fourth central moment (the delta method). Z = 5 of them, as in
tests/test_resampling.py; a sum over particles gets Z times the sum of the standard errors (the standard
deviation of a sum is at most the sum of the standard deviations). With the fixed seeds below a correct
scheme fails with probability below 1e-5 per figure.
"""
import numpy as np
import pytest

from dtpf.entity import resampling as rs
from dtpf.entity.resamplers.killing import killing

Z = 5.0
REPEATS = 4000


def skewed_weights(n=40, seed=1, scale=2.0):
    """Weights exp(N(0, scale^2)), normalised: with scale 2 a few particles carry most of the mass."""
    w = np.exp(np.random.default_rng(seed).normal(scale=scale, size=n))
    return w / w.sum()


def offspring(weights, repeats, seed):
    """(repeats, N) offspring counts of killing resampling on ``weights``."""
    rng = np.random.default_rng(seed)
    return np.array([np.bincount(killing(weights, rng), minlength=weights.size) for _ in range(repeats)])


def killing_variance(w):
    """v_i of the module docstring."""
    n, m = w.size, w.max()
    p = w / m
    return n * w * (1 - w) - w ** 2 * (np.sum(p ** 2) + (1 - 2 * w) / m ** 2)


def variance_and_standard_error(counts):
    """Per particle: the sample variance and its standard error, sqrt((m4 - s^4) / R)."""
    centred = counts - counts.mean(axis=0)
    variance = counts.var(axis=0, ddof=1)
    fourth = np.mean(centred ** 4, axis=0)
    return variance, np.sqrt(np.maximum(fourth - variance ** 2, 0.0) / counts.shape[0])


# --- probability-one facts -------------------------------------------------

def test_killing_is_a_built_in():
    assert rs.RESAMPLERS["killing"] is killing and rs.get("killing") is killing


@pytest.mark.parametrize("n", [1, 2, 3, 49, 1000])
def test_equal_weights_keep_every_particle(n):
    np.testing.assert_array_equal(killing(np.full(n, 1.0 / n), np.random.default_rng(3)), np.arange(n))


def test_equal_weights_keep_every_particle_with_any_bit_generator():
    # No particle is killed: the multinomial part draws one exponential and no point, on either path.
    for rng in (np.random.default_rng(4), np.random.Generator(np.random.Philox(4))):
        np.testing.assert_array_equal(killing(np.full(7, 1.0 / 7), rng), np.arange(7))


def test_a_single_weight_of_one_takes_everything():
    w = np.zeros(10)
    w[6] = 1.0
    np.testing.assert_array_equal(killing(w, np.random.default_rng(0)), np.full(10, 6))


def test_zero_weights_are_never_drawn():
    rng = np.random.default_rng(5)
    w = np.zeros(51)
    w[::2] = skewed_weights(26, seed=2)  # even indices only, including the first and last
    for _ in range(500):
        assert np.all(killing(w, rng) % 2 == 0)


def test_the_heaviest_particles_always_survive():
    w = skewed_weights(40)
    w[[3, 17]] = w.max()  # three particles share the largest weight: each is kept with probability 1
    w /= w.sum()
    heaviest = np.flatnonzero(w == w.max())
    assert heaviest.size == 3
    counts = offspring(w, 500, seed=6)
    assert np.all(counts[:, heaviest] >= 1)


def test_the_ancestors_are_sorted_and_the_draws_are_the_documented_ones():
    w = skewed_weights(300)
    rng, reference = np.random.default_rng(8), np.random.default_rng(8)
    ancestors = killing(w, rng)
    assert ancestors.dtype == np.int64 and np.all(np.diff(ancestors) >= 0)
    kept = reference.random(w.size) < w / w.max()
    reference.standard_exponential(w.size - np.count_nonzero(kept) + 1)
    assert rng.bit_generator.state == reference.bit_generator.state
    # Every survivor has at least its own copy.
    assert np.all(np.bincount(ancestors, minlength=w.size)[kept] >= 1)


# --- statistics --------------------------------------------------------------

def test_offspring_counts_are_unbiased():
    w = skewed_weights(40)
    counts = offspring(w, REPEATS, seed=31)
    standard_error = np.sqrt(killing_variance(w) / REPEATS)
    deviation = np.abs(counts.mean(axis=0) - w.size * w)
    worst = int(np.argmax(deviation / np.maximum(standard_error, 1e-12)))
    assert np.all(deviation <= Z * standard_error + 1e-12), (
        f"particle {worst}: mean {counts.mean(axis=0)[worst]:.4f}, expected {w.size * w[worst]:.4f}")


@pytest.mark.parametrize("scale", [2.0, 0.1])
def test_variance_matches_theory_between_the_fractional_bound_and_multinomial(scale):
    w = skewed_weights(40, seed=4, scale=scale)
    n = w.size
    variance, standard_error = variance_and_standard_error(offspring(w, REPEATS, seed=32).astype(float))
    tolerance = Z * standard_error + 1e-12
    theory = killing_variance(w)
    assert np.all(np.abs(variance - theory) <= tolerance), np.abs(variance - theory) / tolerance
    multinomial = n * w * (1 - w)
    fraction = n * w - np.floor(n * w)
    assert np.all(variance <= multinomial + tolerance)
    assert np.all(variance >= fraction * (1 - fraction) - tolerance)


def test_variance_is_below_multinomial_where_theory_says_it_is_by_far():
    # Mildly uneven weights (scale 0.1): most particles survive, so the total variance is about a third of
    # multinomial's N (1 - sum w^2) (14.2 against 39.0); the gap is far beyond the tolerance of the measured sum.
    w = skewed_weights(40, seed=4, scale=0.1)
    multinomial = float(np.sum(w.size * w * (1 - w)))
    assert killing_variance(w).sum() < 0.5 * multinomial
    variance, standard_error = variance_and_standard_error(offspring(w, REPEATS, seed=33).astype(float))
    assert variance.sum() < multinomial - Z * standard_error.sum(), (variance.sum(), multinomial)
