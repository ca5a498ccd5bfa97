"""DT preprocessing rules (Eq. 28-30) and the mirror summary."""
import numpy as np
import pytest

from dtpf.information import rules
from dtpf.information.mirror import summarise

Z = 5.0


def weighted_set(n=2000, d=1, seed=0):
    rng = np.random.default_rng(seed)
    w = np.exp(rng.normal(scale=1.5, size=n))
    return rng.normal(scale=3.0, size=(n, d)), w / w.sum()


def redraw(particles, weights, ps, seed, threshold_rule="neff"):
    """The draws preprocess makes, replayed with rules.draws: the split, partners, r and u."""
    limit = rules.threshold(weights, threshold_rule)
    large = np.flatnonzero(weights > limit)
    small = np.flatnonzero(weights <= limit)
    positions, r, u = rules.draws(np.random.default_rng(seed), small.size, large.size)
    return large, small, large[positions], r, u


@pytest.mark.parametrize("d", [1, 3])
def test_large_weight_particles_are_unchanged(d):
    x, w = weighted_set(d=d)
    result = rules.preprocess(x, w, 0.81, np.random.default_rng(1))
    large = w > result.report.threshold
    assert large.sum() == result.report.n_large > 0
    np.testing.assert_array_equal(result.particles[large], x[large])
    assert result.report.n_processed == (~large).sum() > 0
    assert np.any(result.particles[~large] != x[~large])


def test_inputs_are_not_modified():
    x, w = weighted_set()
    x0, w0 = x.copy(), w.copy()
    rules.preprocess(x, w, 0.5, np.random.default_rng(1), weight_rule="likelihood",
                     log_likelihood=lambda p: -0.5 * p[:, 0] ** 2)
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(w, w0)


def test_ps_zero_and_r_half_replace_small_particles_by_their_partner():
    rng = np.random.default_rng(2)
    x_m, x_l = rng.normal(size=(100, 2)), rng.normal(size=(100, 2))
    out = rules.apply_rules(x_m, x_l, np.full(100, 0.5), rng.random(100), 0.0)
    np.testing.assert_array_equal(out, x_m)


def test_apply_rules_is_eq29_then_eq30():
    rng = np.random.default_rng(3)
    x_m, x_l = rng.normal(size=(1000, 2)), rng.normal(size=(1000, 2))
    r, u, ps = rng.random(1000), rng.random(1000), 0.6
    x_hat = x_m + (2 * r[:, None] - 1) * x_l                                      # Eq. 29
    x_tilde = np.where((u <= ps)[:, None], (1 - r[:, None]) * x_m + r[:, None] * x_hat, x_hat)  # Eq. 30
    np.testing.assert_allclose(rules.apply_rules(x_m, x_l, r, u, ps), x_tilde, rtol=0, atol=1e-12)


@pytest.mark.parametrize("d", [1, 2])
def test_preprocess_applies_the_rules_with_its_documented_draws(d):
    x, w = weighted_set(d=d)
    result = rules.preprocess(x, w, 0.3, np.random.default_rng(4))
    large, small, partners, r, u = redraw(x, w, 0.3, seed=4)
    expected = x.copy()
    expected[small] = rules.apply_rules(x[partners], x[small], r, u, 0.3)
    np.testing.assert_array_equal(result.particles, expected)
    assert result.report.n_mixed == int(np.sum(u <= 0.3))


@pytest.mark.parametrize("ps", [0.0, 0.81, 1.0])
def test_processed_particles_lie_in_the_theorem_interval(ps):
    """Section 3: x_tilde lies between x_m - |x_l| and x_m + |x_l| (per component)."""
    x, w = weighted_set(d=2, seed=5)
    result = rules.preprocess(x, w, ps, np.random.default_rng(6))
    _, small, partners, _, _ = redraw(x, w, ps, seed=6)
    distance = np.abs(result.particles[small] - x[partners])
    assert np.all(distance <= np.abs(x[small]) * (1 + 1e-12))


@pytest.mark.parametrize("ps", [0.1, 0.5, 0.81])
def test_fraction_on_the_first_branch_matches_ps(ps):
    x, w = weighted_set(n=20_000, seed=7)
    report = rules.preprocess(x, w, ps, np.random.default_rng(8)).report
    n = report.n_processed
    assert report.n_mixed + report.n_plain == n
    assert abs(report.n_mixed / n - ps) <= Z * np.sqrt(ps * (1 - ps) / n)


def test_ps_bounds_are_all_or_nothing():
    x, w = weighted_set()
    assert rules.preprocess(x, w, 1.0, np.random.default_rng(0)).report.n_plain == 0
    assert rules.preprocess(x, w, 0.0, np.random.default_rng(0)).report.n_mixed <= 1  # u == 0 has prob 2**-53


def test_draws_are_uniform_and_independent():
    """The rules' xoshiro256** stream: r and u ~ U(0, 1), partners uniform over the large set."""
    positions, r, u = rules.draws(np.random.default_rng(14), 200_000, 7)
    n = r.size
    for values in (r, u):
        # Mean and variance of U(0, 1): 1/2 and 1/12; standard errors sqrt(1/12/n) and about sqrt(1/180/n).
        assert abs(values.mean() - 0.5) <= Z * np.sqrt(1 / 12 / n)
        assert abs(values.var() - 1 / 12) <= Z * np.sqrt(1 / 180 / n)
        assert values.min() >= 0.0 and values.max() < 1.0
    assert abs(np.corrcoef(r, u)[0, 1]) <= Z / np.sqrt(n)
    counts = np.bincount(positions, minlength=7)
    assert counts.size == 7
    assert np.all(np.abs(counts - n / 7) <= Z * np.sqrt(n / 7 * 6 / 7))


def test_partners_are_uniform_over_the_large_set():
    x = np.arange(4000, dtype=float)
    w = np.where(np.arange(4000) < 10, 1.0, 1e-9)
    w /= w.sum()
    _, _, partners, _, _ = redraw(x[:, None], w, 0.5, seed=9, threshold_rule=1e-6)
    counts = np.bincount(partners, minlength=10)[:10]
    expected = partners.size / 10
    assert np.all(np.abs(counts - expected) <= Z * np.sqrt(expected * 0.9))


def test_same_seed_same_numbers():
    x, w = weighted_set()
    a = rules.preprocess(x, w, 0.81, np.random.default_rng(10))
    b = rules.preprocess(x, w, 0.81, np.random.default_rng(10))
    np.testing.assert_array_equal(a.particles, b.particles)
    assert a.report == b.report


def test_neff_threshold_marks_round_ess_particles_as_large():
    x, w = weighted_set(n=1000)
    limit = rules.threshold(w, "neff")
    assert np.sum(w > limit) == round(1.0 / np.sum(w ** 2))


def test_threshold_rules():
    w = np.array([0.1, 0.2, 0.3, 0.4])
    assert rules.threshold(w, "inverse-n") == 0.25
    assert rules.threshold(w, 0.15) == 0.15
    assert rules.threshold(np.full(8, 1 / 8), "neff") == 0.0  # ESS = N: all large, nothing to process
    with pytest.raises(ValueError, match="unknown threshold rule 'median'"):
        rules.threshold(w, "median")


def test_weight_and_move_rules_are_registries_of_built_ins_only():
    import argparse

    from dtpf.messages import names
    from dtpf.messages.config import RunConfig, add_run_arguments
    from dtpf.messages.references import ReferenceLoadError

    parser = argparse.ArgumentParser()
    add_run_arguments(parser)
    text = " ".join(parser.format_help().split())
    assert rules.WEIGHT_RULES == tuple(names.WEIGHT_RULE_REGISTRY.names()) and "likelihood" in rules.WEIGHT_RULES
    assert rules.MOVE_RULES == tuple(names.MOVE_RULE_REGISTRY.names()) and "relative" in rules.MOVE_RULES
    for registry, field in ((names.WEIGHT_RULE_REGISTRY, "weight_rule"), (names.MOVE_RULE_REGISTRY, "move_rule")):
        for name, summary in registry.summaries().items():
            assert getattr(RunConfig(**{field: name}), field) == name
            assert f"'{name}' ({summary})" in text  # --weight-rule and --move-rule list them from the registry
        with pytest.raises(ValueError, match=f"unknown {registry.kind} 'my.py:rule'; expected one of "
                                             f"{', '.join(registry.names())} \\(built-in only\\)"):
            RunConfig(**{field: "my.py:rule"})
        with pytest.raises(ReferenceLoadError, match="built-in only"):
            registry.get("my.py:rule")
        with pytest.raises(ReferenceLoadError, match="built-in only"):
            registry.contract().adapt(len, f"{registry.kind} 'my.py:rule'")
    assert names.WEIGHT_RULE_REGISTRY.trait("likelihood", "needs_likelihood", False)
    assert not names.WEIGHT_RULE_REGISTRY.trait("inherit", "needs_likelihood", False)


@pytest.mark.parametrize("n", [1000, 100_000])
@pytest.mark.parametrize("k", [1, 2, 17, 500, 1000])
def test_kth_largest_matches_sorting(n, k):
    values = np.random.default_rng(11).exponential(size=n) ** 3
    values[::7] = 0.0
    assert rules.kth_largest(values, k) == np.sort(values)[-k]


@pytest.mark.parametrize("spread", [0.0, 1e-3, 3.0], ids=["ties", "near-uniform", "spread"])
def test_order_statistics_match_sorting_when_the_values_bunch(spread):
    # Near-uniform weights put most values in one bucket of the radix select (its worst case).
    from dtpf.information import select

    rng = np.random.default_rng(21)
    values = np.exp(spread * rng.standard_normal(200_000)) / 200_000
    values[::11] = values[5]  # ties
    ranks = [0, 1, 20_000, 99_999, 100_000, 180_000, 199_998, 199_999]
    np.testing.assert_array_equal(select.order_statistics(values, ranks), np.sort(values)[ranks])
    shuffled = [180_000, 0, 99_999]  # any order of ranks
    np.testing.assert_array_equal(select.order_statistics(values, shuffled), np.sort(values)[shuffled])
    np.testing.assert_allclose(select.quantiles(values, [0.1, 0.5, 0.9, 0.99]),
                               np.quantile(values, [0.1, 0.5, 0.9, 0.99]), rtol=1e-15)


def test_likelihood_rule_reweights_processed_particles_by_the_likelihood_ratio():
    x, w = weighted_set(n=500, seed=12)

    def log_likelihood(p):
        return -0.5 * (p[:, 0] - 1.0) ** 2

    result = rules.preprocess(x, w, 0.81, np.random.default_rng(13), weight_rule="likelihood",
                              log_likelihood=log_likelihood)
    small = w <= result.report.threshold
    unnormalised = w.copy()
    unnormalised[small] *= np.exp(log_likelihood(result.particles[small]) - log_likelihood(x[small]))
    np.testing.assert_allclose(result.weights, unnormalised / unnormalised.sum(), rtol=1e-10)
    inherit = rules.preprocess(x, w, 0.81, np.random.default_rng(13))
    np.testing.assert_array_equal(inherit.weights, w)
    assert not inherit.weights.flags.writeable


@pytest.mark.parametrize("kwargs, message", [
    (dict(ps=1.5), r"PS must be in \[0, 1\], got 1.5"),
    (dict(ps=float("nan")), r"PS must be in \[0, 1\], got nan"),
    (dict(weights=np.array([0.5, np.nan, 0.5])), "weights contain NaN values at index 1"),
    (dict(particles=np.zeros(4)), "particles and weights differ in length: 4 particles, 3 weights"),
    (dict(weight_rule="bayes"), "unknown weight rule 'bayes'"),
    (dict(weight_rule="likelihood"), "weight rule 'likelihood' needs the observation's log_likelihood"),
])
def test_bad_input_is_named(kwargs, message):
    args = dict(particles=np.zeros(3), weights=np.full(3, 1 / 3), ps=0.5)
    args.update(kwargs)
    weight_rule = args.pop("weight_rule", "inherit")
    with pytest.raises(ValueError, match=message):
        rules.preprocess(args["particles"], args["weights"], args["ps"], np.random.default_rng(0),
                         weight_rule=weight_rule)


# --- mirror --------------------------------------------------------------------

def test_mirror_of_uniform_weights():
    s = summarise(np.arange(100.0), np.full(100, 0.01))
    assert s.ess == pytest.approx(100) and s.ess_ratio == pytest.approx(1)
    assert s.entropy_ratio == pytest.approx(1)
    assert s.distinct == 100 and s.n_above_threshold == 100


def test_mirror_of_a_collapsed_set():
    w = np.zeros(100)
    w[3] = 1.0
    s = summarise(np.repeat([[1.0, 2.0]], 100, axis=0), w)
    assert s.ess == 1.0 and s.entropy == 0.0 and s.max_weight == 1.0
    assert s.distinct == 1 and s.n_above_threshold == 1
    assert s.q50 == 0.0


def test_mirror_takes_the_parents_count_when_given():
    s = summarise(np.arange(100.0), np.full(100, 0.01), parents=37)
    assert s.distinct == 37
    with pytest.raises(ValueError, match=r"parents must be in \[1, 100\], got 101"):
        summarise(np.arange(100.0), np.full(100, 0.01), parents=101)


@pytest.mark.parametrize("n", [1000, 200_000])
def test_mirror_quantiles_match_numpy(n):
    w = np.random.default_rng(n).exponential(size=n) ** 2
    w /= w.sum()
    s = summarise(np.zeros(n), w, parents=1)
    np.testing.assert_allclose([s.q10, s.q50, s.q90, s.q99], np.quantile(w, [0.1, 0.5, 0.9, 0.99]), rtol=1e-12)


def test_mirror_rejects_bad_weights():
    with pytest.raises(ValueError, match="weights contain negative values"):
        summarise(np.zeros(2), np.array([1.5, -0.5]))


def test_a_stream_prepared_ahead_changes_no_number_and_only_serves_its_step():
    from dtpf.entity import models
    from dtpf.information.layer import InformationLayer

    particles, weights = weighted_set(3000, seed=4)

    def layer():
        return InformationLayer(models.get("ungm"), ps=0.81, seed=9, twin="t")

    expected = layer().preprocess(5, particles, weights, [1.0])
    prepared = layer()
    prepared.prepare(5)
    got = prepared.preprocess(5, particles, weights, [1.0])
    np.testing.assert_array_equal(got.particles, expected.particles)
    assert got.report == expected.report
    wrong = layer()
    wrong.prepare(6)  # prepared for another step: not used for step 5
    np.testing.assert_array_equal(wrong.preprocess(5, particles, weights, [1.0]).particles, expected.particles)
    other_step = layer().preprocess(6, particles, weights, [1.0])
    assert not np.array_equal(other_step.particles, expected.particles)


@pytest.mark.parametrize("n", [rules.SMALL_SET - 1, rules.SMALL_SET, 3 * rules.SMALL_SET])
@pytest.mark.parametrize("d", [1, 3])
@pytest.mark.parametrize("ps", [0.0, 0.3, 1.0])
def test_both_paths_apply_the_rules_with_their_documented_draws(n, d, ps):
    # Below SMALL_SET one compiled call, from it on three; the split copies the set the moves write
    # into, and u <= PS is decided on the draw's bits: the numbers of the rules as documented.
    x, w = weighted_set(n=n, d=d, seed=n + d)
    rng = np.random.default_rng(15)
    result = rules.preprocess(x, w, ps, rng)
    large, small, partners, r, u = redraw(x, w, ps, seed=15)
    expected = x.copy()
    expected[small] = rules.apply_rules(x[partners], x[small], r, u, ps)
    np.testing.assert_array_equal(result.particles, expected)
    assert result.report.n_mixed == int(np.sum(u <= ps))
    assert result.report.n_large == large.size and result.report.n_processed == small.size
    after = np.random.default_rng(15)
    rules.draws(after, 0, 1)  # the seed words: what preprocess takes from the generator
    assert rng.random() == after.random()


@pytest.mark.parametrize("n_small", [1, rules.MOVE_BLOCK - 1, rules.MOVE_BLOCK, rules.MOVE_BLOCK + 1, 5 * rules.MOVE_BLOCK + 7])
@pytest.mark.parametrize("d", [1, 2])
def test_blocked_moves_are_the_particle_by_particle_moves(n_small, d):
    # _move_blocked makes a block's draws before its moves: the same numbers in the same order as
    # _move, whatever the count's remainder by the block size.
    rng = np.random.default_rng(n_small + d)
    n = 2 * n_small + 3
    particles = rng.standard_normal((n, d))
    small = np.sort(rng.choice(n, n_small, replace=False)).astype(np.int32)
    rows = rng.standard_normal((n - n_small, d))
    state = rng.integers(0, 2 ** 64, size=4, dtype=np.uint64)
    one, blocked = particles.copy(), particles.copy()
    mixed_one = rules._move(particles, small, rows, 0.4, state, one)
    mixed_blocked = rules._move_blocked(particles, small, rows, 0.4, state, blocked)
    np.testing.assert_array_equal(blocked, one)
    assert mixed_blocked == mixed_one and 0 <= mixed_one <= n_small
    assert not np.array_equal(one[small], particles[small])


_FIRST_STEP = """
import numba, numpy as np
import dtpf.information.mirror, dtpf.information.rules, dtpf.information.select
from dtpf.entity import models
from dtpf.information.layer import InformationLayer

def compiled():
    return sum(len(f.signatures) for module in (dtpf.information.rules, dtpf.information.select, dtpf.information.mirror)
               for f in vars(module).values() if isinstance(f, numba.core.registry.CPUDispatcher))

layer = InformationLayer(models.get("ungm"), ps=0.81, seed=0, twin="t")
rng = np.random.default_rng(1)
counts = []
for n in (1000, 5000, 70000):  # the three size classes: one compiled call, three, the radix select
    layer.warm_up(n)
    before = compiled()
    x, w = rng.standard_normal((n, 1)), rng.random(n)  # a decoded message's arrays: read-only
    w /= w.sum()
    x.flags.writeable = w.flags.writeable = False
    result = layer.preprocess(1, x, w, [0.5], checked=True)
    layer.mirror(x, w, n // 2, result.report.threshold, checked=True)
    counts.append(compiled() - before)
    if n == 1000:  # a small run's warm-up leaves the radix select alone (compiling every class took 21 s cold)
        counts.append(len(dtpf.information.select._order_statistics.signatures))
print(compiled(), *counts)
"""


def test_the_information_layers_warm_up_compiles_what_its_first_real_step_needs():
    # numba compiles read-only arrays apart; a service that warmed up on writable arrays only compiled on
    # its first decoded set, for seconds, past the entity's lockstep timeout (a fleet's first run: every
    # twin's first step degraded), and the radix select of N >= 2**16 was never warmed up. In a fresh
    # process, so that nothing else compiled those kinds first.
    import subprocess
    import sys

    from conftest import ROOT
    done = subprocess.run([sys.executable, "-c", _FIRST_STEP], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    total, *added = map(int, done.stdout.split())
    assert total > 0 and added == [0, 0, 0, 0]
