"""The cheaper chooser: its copies are scored and propagated in one call each over all arms, with the numbers
the per-arm copies had, so the decisions (and every log a chooser recorded) do not change."""
from __future__ import annotations

import hashlib

import numpy as np
import pytest

from dtpf.entity import models
from dtpf.messages.config import RunConfig
from dtpf.scripts.inprocess import build, simulate
from dtpf.system.choose import ArmEvidence, point_log_likelihood
from dtpf.system.evidence import predictive_log_likelihood


def _run(evidence: ArmEvidence, model, steps: int = 12, n: int = 200, d: int = 1, seed: int = 3):
    """Feed ``evidence`` a filter-like sequence of weighted sets and observations; its differences and copies."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, d)) * 2.0
    out = []
    for k in range(1, steps + 1):
        z = rng.standard_normal(model.obs_dim)
        w = np.exp(model.log_likelihood(x, z, k) - np.max(model.log_likelihood(x, z, k)))
        w /= w.sum()
        evidence.observe(k, x, w, z, np.random.default_rng([seed, k]))
        out.append({name: c.copy() for name, c in evidence.copies.items()})
        x = model.propagate(x[rng.integers(0, n, n)], k + 1, rng)
    return list(evidence.differences), list(evidence.point_differences), out


class _NoNoise:
    """A model that draws inside ``propagate`` only (no ``propagation_noise``): the copies go one call each."""

    def __init__(self, model):
        self._model = model

    def __getattr__(self, name):
        return getattr(self._model, name)

    def propagation_noise(self, n, k, rng):
        return None


def _model(name: str):
    if name == "range-bearing":
        from dtpf.scripts.paper import evaluate_guard
        return evaluate_guard.scenario_model(name)[1]
    return models.get(name)


@pytest.mark.parametrize("name, m", [("ungm", 300), ("ungm", 2500), ("drift", 300), ("range-bearing", 200)])
def test_one_propagation_call_gives_each_copy_the_numbers_of_its_own_call(name, m):
    """2500 particles of ungm: its compiled draws (from 2048 numbers on) in both paths."""
    model = _model(name)
    d = np.asarray(model.initial_particles(2, np.random.default_rng(0))).shape[1]
    stacked = np.random.default_rng(1).standard_normal((5, m, d)) * 3.0
    got = ArmEvidence(model, n=m, particles=m)._propagate(7, stacked, np.random.default_rng(5))
    for row, copy in zip(stacked, got):   # each copy alone, from the same generator state
        assert np.array_equal(copy, model.propagate(row, 7, np.random.default_rng(5)))
    assert not np.array_equal(got[0] - stacked[0], got[1] - stacked[1]) or name == "drift"


@pytest.mark.parametrize("name", ["ungm", "drift"])
def test_the_batched_copies_have_the_numbers_of_one_call_per_copy(name):
    model = models.get(name)
    batched = ArmEvidence(model, n=200, particles=150)
    single = ArmEvidence(model, n=200, particles=150)
    single.batched = False
    a, b = _run(batched, model), _run(single, model)
    assert a[0] == b[0] and a[1] == b[1]      # every difference, bit for bit
    for x, y in zip(a[2], b[2]):
        assert x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)
    assert len({float(v) for d in a[0] for v in d.values()}) > 5   # the arms differ: a test that can fail


class _DrawsMore:
    """A model whose ``propagate`` draws one more number per particle after its noise (as a driven step over
    two pieces of control does): one call over all copies would give each copy other numbers."""

    def __init__(self, model):
        self._model = model

    def __getattr__(self, name):
        return getattr(self._model, name)

    def propagate(self, particles, k, rng, noise=None):
        out = self._model.propagate(particles, k, rng, noise=noise)
        return out + rng.standard_normal(out.shape)


def test_a_model_that_draws_more_than_its_noise_gets_one_call_per_copy():
    model = _DrawsMore(models.get("ungm"))
    stacked = np.random.default_rng(1).standard_normal((5, 300, 1))
    got = ArmEvidence(model, n=300, particles=300)._propagate(4, stacked, np.random.default_rng(5))
    for row, copy in zip(stacked, got):
        assert np.array_equal(copy, model.propagate(row, 4, np.random.default_rng(5)))


def test_a_model_without_its_own_noise_gets_one_call_per_copy_with_the_same_numbers():
    model = models.get("ungm")
    plain = _run(ArmEvidence(model, n=200, particles=150), model)
    wrapped = _run(ArmEvidence(_NoNoise(model), n=200, particles=150), model)
    assert plain[0] == wrapped[0] and plain[1] == wrapped[1]


def test_the_scores_are_each_copys_predictive_and_point_log_likelihood():
    """The one likelihood call over all copies scores each copy as a call on its own copy does."""
    model = models.get("ungm")
    evidence = ArmEvidence(model, n=200, particles=200)
    _run(evidence, model, steps=5)
    copies, k = evidence.copies, 6
    z = np.array([3.0])
    evidence.observe(k, copies["plain"], np.full(200, 1 / 200), z, np.random.default_rng(1))
    predictive = {name: predictive_log_likelihood(model, x, z, k) for name, x in copies.items()}
    point = {name: point_log_likelihood(model, x, z, k) for name, x in copies.items()}
    expected = {name: float(np.clip(predictive[name] - predictive["plain"], -50, 50)) for name in copies}
    assert evidence.differences[-1] == expected
    assert evidence.point_differences[-1] == {name: min(point[name] - point["plain"], 50.0) for name in copies}
    assert len(set(expected.values())) > 2


def _digest(scenario: str, n: int, steps: int, seed: int) -> str:
    from dtpf.scripts.paper import evaluate_guard

    options, model = evaluate_guard.scenario_model(scenario)
    config = RunConfig(**options, particles=n, steps=steps, seed=seed, policy="choose", twin="t-cost")
    _, z = simulate(config, model)
    pf = build(config, z, model)
    steps_run = list(pf)
    h = hashlib.sha256()
    for forecast in pf.preprocessor.system.forecasts:
        for figures in (forecast.arm_evidence or {}, forecast.arm_point_evidence or {}):
            for key in sorted(figures):
                h.update(key.encode())
                h.update(np.float64(figures[key]).tobytes())
    for decision in pf.preprocessor.decisions:
        h.update(decision.arm.encode())
    for step in steps_run:
        h.update(np.asarray(step.mean, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


#: Digests of choose runs (estimates, every arm's evidence, every decision) recorded with the per-arm copies
#: of commit 303051b (one likelihood call and one propagation per arm): a log of that chooser still verifies.
#: drift+100 puts the relative rule in force; range-bearing has four state dimensions; N = 1,500 copies M = 1,000.
RECORDED = {("ungm", 100, 60, 3): "d8c4a2f6818adf2f", ("moving", 100, 60, 4): "c1063f9ad27c577c",
            ("ungm", 1500, 12, 7): "f25dc4ae56e1eef5", ("drift+100", 100, 40, 2): "adf36bd34079277c",
            ("range-bearing", 100, 40, 5): "b00950edd548a100"}


@pytest.mark.parametrize("case", sorted(RECORDED))
def test_a_choose_run_decides_and_estimates_as_the_per_arm_copies_did(case):
    assert _digest(*case) == RECORDED[case]
