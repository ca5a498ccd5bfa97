"""Kernels on every core (dtpf.entity.cores): the numbers of a run do not depend on the thread count, and a
set of at most B particles (or a config from a log recorded before blocks) keeps the numbers it had."""
from __future__ import annotations

import hashlib

import numba
import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from dtpf.entity import _merge, cores, resampling, sources
from dtpf.information import mirror, rules, select
from dtpf.messages.config import BLOCK_PARTICLES, RunConfig, recorded_config
from dtpf.messages.streams import block_stream, seed_sequence
from dtpf.scripts.inprocess import build

pytestmark = pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 of numba's threads")

B = BLOCK_PARTICLES
#: Three blocks and a part block.
N_BLOCKED = 3 * B + 17

#: Digests of 3 steps of the default in-process run (seed 0) made by the code before blocks (commit 303051b),
#: on one BLAS thread as every layer and dtpf command runs (OpenBLAS sums a dot product of more than 10,000
#: numbers, the ESS's, on several threads in another order).
BEFORE_BLOCKS = {1000: "94a59cd9e5926e4aa32d", B: "df4e8f00fcafe035bfe7", N_BLOCKED: "6e7f4f2e0de4394f0ac0"}


@pytest.fixture()
def threads(monkeypatch):
    """Set the process's thread count for a test, and put back every core after it; the kernels share sets
    from 4,096 particles on (not PARALLEL_MIN), so that these sizes run on the threads. BLAS on one thread,
    as in the layers, whatever other tests of the process set."""
    monkeypatch.setattr(cores, "PARALLEL_MIN", 1 << 12)
    monkeypatch.setattr(resampling, "PARALLEL_GATHER", 1 << 12)
    with threadpool_limits(limits=1, user_api="blas"):
        yield cores.set_threads
    cores.set_threads(None)


def _steps(config: RunConfig, steps: int = 3):
    model = sources.load_model(config, check=False)
    _, z = model.simulate(steps, np.random.default_rng(0))
    return list(build(config, z))


def _digest(steps) -> str:
    h = hashlib.sha256()
    for s in steps:
        for a in (s.particles, s.weights, s.ancestors, s.mean, s.var, [s.ess], [s.log_predictive]):
            h.update(np.ascontiguousarray(a, dtype=np.float64 if not isinstance(a, np.ndarray) else a.dtype).tobytes())
        r = s.report
        h.update(repr((r.threshold, r.n_large, r.n_processed, r.n_mixed, r.n_plain, r.ps)).encode())
    return h.hexdigest()[:20]


def test_a_run_in_blocks_has_the_same_numbers_on_one_and_two_threads(threads):
    config = RunConfig(particles=N_BLOCKED, steps=3, seed=0, run_id="t")
    threads(1)
    one = _steps(config)
    threads(2)
    two = _steps(config)
    for a, b in zip(one, two, strict=True):
        for name in ("particles", "weights", "ancestors", "mean", "var", "ess", "log_predictive"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"step {a.step}: {name}")
        assert a.report == b.report
    assert _digest(one) == _digest(two)
    # ... and the blocks were used: one block gives other numbers.
    assert _digest(one) != BEFORE_BLOCKS[N_BLOCKED]


@pytest.mark.parametrize("n", [1000, B])
def test_at_most_b_particles_keep_the_numbers_of_the_code_before_blocks(n, threads):
    config = RunConfig(particles=n, steps=3, seed=0, run_id="t")
    for count in (1, 2):
        threads(count)
        assert _digest(_steps(config)) == BEFORE_BLOCKS[n], f"{count} threads"


def test_a_config_from_a_log_before_blocks_keeps_that_logs_numbers(threads):
    text = RunConfig(particles=N_BLOCKED, steps=3, seed=0, run_id="t").model_dump_json(exclude={"block_particles"})
    old = recorded_config(text)
    assert old.block_particles is None
    threads(2)
    assert _digest(_steps(old)) == BEFORE_BLOCKS[N_BLOCKED]


def test_a_new_run_records_b_and_reads_it_back():
    config = RunConfig()
    assert config.block_particles == B
    assert recorded_config(config.model_dump_json()).block_particles == B
    assert recorded_config(RunConfig(block_particles=None).model_dump_json()).block_particles is None
    assert cores.blocks(B, B) == 1 and cores.blocks(B + 1, B) == 2 and cores.blocks(10 ** 6, None) == 1


def test_a_blocks_stream_is_the_steps_seed_sequence_spawned():
    for seed, twin, step, block in ((0, "ungm-1", 1, 1), (2 ** 40 + 3, "x", 7, 15)):
        expected = np.random.Generator(np.random.PCG64(np.random.SeedSequence(
            seed_sequence(seed, twin, step, "entity").entropy, spawn_key=(block,))))
        np.testing.assert_array_equal(block_stream(seed, twin, step, "entity", block).random(5), expected.random(5))
    with pytest.raises(ValueError):
        block_stream(0, "t", 1, "entity", 0)


def test_systematic_in_blocks_is_systematic_for_one_block_and_the_same_on_any_thread_count(threads):
    rng = np.random.default_rng(3)
    w = rng.lognormal(size=N_BLOCKED)
    w /= w.sum()
    one = resampling.systematic_blocks(w, np.random.default_rng(5), N_BLOCKED)
    np.testing.assert_array_equal(one, resampling.systematic(w, np.random.default_rng(5)))
    threads(1)
    single = resampling.systematic_blocks(w, np.random.default_rng(5), 1000)
    threads(2)
    double = resampling.systematic_blocks(w, np.random.default_rng(5), 1000)
    np.testing.assert_array_equal(single, double)
    assert np.all(np.diff(single) >= 0)
    counts = np.bincount(single, minlength=w.size)
    assert np.abs(counts - w.size * w).max() < 1.0 + 1e-6  # systematic: floor or ceil of N w


def test_the_moves_in_blocks_draw_block_zero_from_the_unblocked_stream(threads):
    rng = np.random.default_rng(4)
    n, block = 3000, 1024
    x, w = rng.standard_normal((n, 1)), rng.random(n)
    w /= w.sum()
    small, rows, _ = rules.split(w, np.median(w), x, n)
    state = rules._seed(np.random.default_rng(9))
    plain, blocked_one, blocked_two = x.copy(), x.copy(), x.copy()
    rules._move_blocked(x, small, rows, 0.8, state, plain)
    threads(1)
    mixed_one = rules.move_blocks(x, small, rows, 0.8, state, blocked_one, block)
    threads(2)
    mixed_two = rules.move_blocks(x, small, rows, 0.8, state, blocked_two, block)
    np.testing.assert_array_equal(blocked_one, blocked_two)
    assert mixed_one == mixed_two
    np.testing.assert_array_equal(blocked_one[:block], plain[:block])
    assert not np.array_equal(blocked_one[block:], plain[block:])
    np.testing.assert_array_equal(rules._jumped(state, 2)[0], state)


def test_the_kernels_shared_among_threads_give_the_one_thread_numbers(threads):
    rng = np.random.default_rng(6)
    w = rng.random(N_BLOCKED) ** 4
    w /= w.sum()
    x = rng.standard_normal((N_BLOCKED, 1))
    ranks = np.array([10, N_BLOCKED // 2, N_BLOCKED - 3])
    for few in (select.FEW_MEMBERS, -1):  # one level of buckets, and two
        np.testing.assert_array_equal(select._order_statistics_parallel(w, ranks, 5, few),
                                      select._order_statistics(w, ranks))
        for values in (np.full(N_BLOCKED, 1.0 / N_BLOCKED), np.round(rng.random(N_BLOCKED) * 10) / 10,
                       rng.exponential(size=N_BLOCKED)):  # ties, one bucket, many buckets
            np.testing.assert_array_equal(select._order_statistics_parallel(values, ranks, 3, few),
                                          np.sort(values)[ranks])
    threads(2)
    limit = float(np.quantile(w, 0.6))
    for parts in (2, 7):
        for a, b in zip(rules._split_parallel(w, limit, x, N_BLOCKED, parts), rules._split(w, limit, x, N_BLOCKED)):
            np.testing.assert_array_equal(a, b)
    a = rng.integers(0, N_BLOCKED, N_BLOCKED)
    np.testing.assert_array_equal(_merge.gather_parallel(x, a, np.empty_like(x)), x[a])
    a.sort()
    assert resampling.distinct(a) == _merge.distinct(a) == np.unique(a).size
    summary = mirror.summarise(x, w, float(np.quantile(w, 0.7)), N_BLOCKED // 3, block=1000)
    assert summary.max_weight == w.max() and summary.n_above_threshold == np.count_nonzero(w > summary.threshold)


def test_the_blocks_propagation_noise_is_drawn_on_every_thread(threads):
    """From PARALLEL_MIN particles on, the blocks' draws share the threads (block 0 on the calling one)."""
    import threading

    from dtpf.entity import blocks

    drawn_on = set()

    class Model:
        dim = 1

        def propagation_noise(self, n, k, rng):
            drawn_on.add(threading.get_ident())
            return rng.standard_normal((n, 1))

    threads(2)
    n = 8 * 4096
    noise = blocks.noise(Model(), n, 1, np.random.default_rng(0), 4096, (0, "t"))
    assert noise.shape == (n, 1) and len(drawn_on) == 2
    threads(1)
    drawn_on.clear()
    assert np.array_equal(blocks.noise(Model(), n, 1, np.random.default_rng(0), 4096, (0, "t")), noise)
    assert len(drawn_on) == 1


def test_the_checks_of_a_large_set_in_parts_find_what_one_pass_finds(monkeypatch):
    """check_weights and check_particles cut a large array into parts on the check threads: a NaN, a
    negative weight or a sum off 1 in the last part is named as in one pass."""
    from dtpf.messages import arrays

    monkeypatch.setattr(arrays, "PARALLEL_CHECK", 1 << 10)
    arrays.set_check_threads(2)
    try:
        n = 1 << 12
        weights = np.full(n, 1.0 / n)
        assert arrays.check_weights(weights) is weights
        bad = weights.copy()
        bad[-1] = np.nan
        with pytest.raises(ValueError, match=f"NaN values at index {n - 1}"):
            arrays.check_weights(bad)
        bad[-1] = -1e-9
        with pytest.raises(ValueError, match=f"negative values at index {n - 1}"):
            arrays.check_weights(bad)
        bad[-1] = 0.5
        with pytest.raises(ValueError, match="must sum to 1"):
            arrays.check_weights(bad)
        particles = np.ones((n, 2))
        particles[-1, 1] = np.inf
        with pytest.raises(ValueError, match=f"non-finite values at index {2 * n - 1}"):
            arrays.check_particles(particles)
    finally:
        arrays.set_check_threads(1)
