"""Threshold rules (W of Eq. 28), one family: the registry, the built-ins' split, a user's rule end to end."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from dtpf.entity import models
from dtpf.information import rules
from dtpf.information.layer import InformationLayer
from dtpf.messages.config import RunConfig
from dtpf.messages.family import THRESHOLDS
from dtpf.messages.references import ReferenceLoadError
from dtpf.scripts.inprocess import run

from conftest import ROOT

RULES = '''
"""A user's threshold rules, good and bad."""


def half_max(weights):
    return 0.5 * weights.max()


def nan(weights):
    return float("nan")


def negative(weights):
    return -0.25


def array(weights):
    return weights / 2


def raising(weights):
    raise RuntimeError("no rule today")


def late_nan(weights):
    # Fine on the small set it is tried on before the run, NaN on the run's own sets.
    return 0.1 if weights.size <= 8 else float("nan")


def writes(weights):
    weights[0] = 1.0
    return 0.1


def two(weights, ess):
    return 0.1


NOT_A_RULE = 3
'''


@pytest.fixture
def rules_file(tmp_path):
    path = tmp_path / "my_rules.py"
    path.write_text(RULES)
    return path


def dtpf(cwd, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=300, check=False)


def weights(n: int, seed: int = 0) -> np.ndarray:
    w = np.random.default_rng(seed).random(n) ** 6
    return w / w.sum()


# --- the registry -------------------------------------------------------------------------------------------

def test_the_registry_holds_one_module_per_built_in():
    builtins = THRESHOLDS.builtins()
    assert {"neff", "inverse-n"} <= set(builtins)
    assert all(obj.__module__.startswith("dtpf.information.thresholds.") for obj in builtins.values())
    assert THRESHOLDS.names()[: len(builtins)] == list(builtins)
    assert all(THRESHOLDS.summaries()[name] for name in builtins)  # each says what it does in --help


def test_help_lists_every_rule_and_how_to_give_your_own():
    done = dtpf(ROOT, "run", "--help")
    assert done.returncode == 0
    text = " ".join(done.stdout.split())
    for name, summary in THRESHOLDS.summaries().items():
        assert f"'{name}' ({summary})" in text
    assert "your own W = rule(weights) as path/to/file.py:NAME" in text


def test_the_run_configuration_takes_a_name_a_reference_or_a_number():
    assert RunConfig(threshold="0.002").threshold == 0.002  # a number is W itself
    assert RunConfig(threshold=0.5).threshold == 0.5
    assert RunConfig(threshold="missing.py:rule").threshold == "missing.py:rule"  # checked when loaded
    with pytest.raises(ValueError, match="unknown threshold rule 'median'; expected one of inverse-n, neff.*"
                                         "or a number") as error:
        RunConfig(threshold="median")
    assert "\n" not in str(error.value)
    for bad in (-0.1, "nan", "inf"):
        with pytest.raises(ValueError, match="threshold W must be a finite non-negative number"):
            RunConfig(threshold=bad)


# --- the built-ins ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("n", [50, 5000])
def test_neff_gives_W_and_its_capacity_k(n):
    w = weights(n)
    k = round(1.0 / float(np.dot(w, w)))
    assert 1 <= k < n
    limit, capacity = THRESHOLDS.get("neff")(w)
    assert limit == np.sort(w)[n - k - 1] and capacity == k == np.count_nonzero(w > limit)
    rank, capacity = THRESHOLDS.get("neff").order(w)  # what the compiled small path selects itself
    assert np.sort(w)[rank] == limit and capacity == k
    # ESS = N: every particle is large, W = 0 and the capacity is N.
    assert tuple(THRESHOLDS.get("neff")(np.full(n, 1 / n))) == (0.0, n)
    assert THRESHOLDS.get("neff").order(np.full(n, 1 / n)) == (-1, n)


def test_inverse_n_and_a_number_can_leave_every_weight_above_W():
    w = weights(40)
    assert tuple(THRESHOLDS.get("inverse-n")(w)) == (1 / 40, 40)
    assert rules._threshold(w, 0.01) == (0.01, 40)
    assert rules.threshold(w, "inverse-n") == 1 / 40


# --- a user's rule ------------------------------------------------------------------------------------------

def test_a_users_rule_gives_W_of_every_step_with_capacity_n(rules_file):
    reference = f"{rules_file}:half_max"
    w = weights(300)
    assert tuple(THRESHOLDS.get(reference)(w)) == (0.5 * w.max(), 300)
    assert rules.threshold(w, reference) == 0.5 * w.max()
    assert not THRESHOLDS.resolve(reference).builtin and THRESHOLDS.resolve(reference).sha256
    # The rule in force in a run: each step's W is the rule's value on the weights the twin was given.
    config = RunConfig(threshold=reference, particles=300, steps=20, seed=1)
    result = run(config)
    for step in result.steps:
        assert step.report.threshold == 0.5 * step.weights.max()
        assert step.report.n_large == np.count_nonzero(step.weights > step.report.threshold)
    assert any(step.report.n_processed > 0 for step in result.steps)
    assert result.rmse != run(config.model_copy(update={"threshold": "neff"})).rmse


@pytest.mark.parametrize("n", [100, 5000])  # the small sets' one compiled call, and the split in blocks
def test_the_layer_and_its_mirror_use_the_users_W(rules_file, n):
    model = models.get("ungm")
    layer = InformationLayer(model, ps=0.81, threshold_rule=f"{rules_file}:half_max", seed=2)
    x = np.random.default_rng(3).standard_normal((n, 1)) * 5
    w = weights(n, seed=4)
    out = layer.process(1, x, w, np.array([1.0]), parents=n)
    limit = 0.5 * w.max()
    assert out.preprocessed.report.threshold == limit == out.summary.threshold
    assert out.preprocessed.report.n_large == np.count_nonzero(w > limit) == out.summary.n_above_threshold
    moved = np.flatnonzero(np.any(out.preprocessed.particles != x, axis=1))
    assert set(moved) <= set(np.flatnonzero(w <= limit)) and moved.size > 0


def test_dtpf_run_takes_a_users_rule_from_a_file(rules_file):
    done = dtpf(rules_file.parent, "run", "-q", "--policy", "fixed", "-n", "300", "-T", "20", "--seed", "1",
                "--threshold", "my_rules.py:half_max")
    assert done.returncode == 0, done.stderr
    rmse = run(RunConfig(threshold=f"{rules_file}:half_max", particles=300, steps=20, seed=1)).rmse
    assert f"RMSE            {rmse:.4f}" in done.stdout


@pytest.mark.parametrize("name, problem", [
    ("nan", "returned nan, expected W, a finite non-negative number"),
    ("negative", "returned -0.25, a negative W"),
    ("array", "returned an ndarray of shape (8,), expected W, one finite non-negative number"),
    ("raising", "raised RuntimeError: no rule today"),
    ("late_nan", "returned nan"),  # passed the check before the run: the check at every call stops it
])
def test_dtpf_run_stops_on_a_rule_that_breaks_the_contract(rules_file, name, problem):
    done = dtpf(rules_file.parent, "run", "-q", "-n", "100", "-T", "5", "--threshold", f"my_rules.py:{name}")
    assert done.returncode == 2, (done.stdout, done.stderr)
    assert "Traceback" not in done.stderr
    [line] = [line for line in done.stderr.splitlines() if line.startswith("dtpf run: error:")]
    assert f"threshold rule 'my_rules.py:{name}' {problem}" in line


@pytest.mark.parametrize("name, problem", [
    ("nan", "returned nan"),
    ("writes", ("raised ValueError: assignment destination is read-only (a threshold rule must not change the "
                "weights)")),
    ("two", "a threshold rule takes (weights), got the parameters (weights, ess)"),
    ("NOT_A_RULE", "expected a function rule(weights) -> W, got an int"),
    ("missing", "has no attribute 'missing'"),
])
def test_a_rule_is_tried_before_the_first_step(rules_file, name, problem):
    reference = f"{rules_file}:{name}"
    with pytest.raises(ReferenceLoadError) as error:
        InformationLayer(models.get("ungm"), ps=0.81, threshold_rule=reference)
    assert problem in str(error.value) and f"threshold rule {reference!r}" in str(error.value)
    assert "\n" not in str(error.value)


def test_a_predictive_policy_runs_with_the_users_rule(rules_file):
    # The system layer's predictions replay the preprocessing on simulated scenarios with the run's threshold
    # rule: they load the user's rule as the information layer does.
    result = run(RunConfig(threshold=f"{rules_file}:half_max", policy="predictive", particles=200, steps=6,
                           seed=5))
    assert all(step.report.threshold == 0.5 * step.weights.max() for step in result.steps)
