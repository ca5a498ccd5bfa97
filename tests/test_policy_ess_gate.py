"""The ``ess-gate`` PS policy: preprocess at k + 1 only while the mirrored ESS/N of step k is below the threshold."""
import numpy as np
import pytest

from dtpf.messages import family
from dtpf.messages.config import RunConfig
from dtpf.scripts.inprocess import run
from dtpf.system import policy as ps_policy
from dtpf.system.layer import SystemLayer
from dtpf.system.policies.ess_gate import EssGatePS
from dtpf.system.predict import Forecast

N = 200


def observed(step: int, ess_ratio: float, **figures) -> Forecast:
    """A forecast with the weight-state figures only (what a policy that does not simulate sees)."""
    return Forecast(**{"step": step, "n": N, "ess_ratio": ess_ratio, "ess_trend": 0.0, "distinct_ratio": 0.5,
                       **figures})


# --- decisions -------------------------------------------------------------------


def test_on_below_the_threshold_off_at_and_above_it_with_ps_fixed():
    gate = ps_policy.get("ess-gate", ps=0.81, max_change=0.25)
    decisions = [gate.decide(k, observed(k, r)) for k, r in enumerate([0.3, 0.49, 0.5, 0.7, 0.05], start=1)]
    assert [d.preprocess for d in decisions] == [True, True, False, False, True]
    assert {d.ps for d in decisions} == {0.81}
    assert [d.applies_from_step for d in decisions] == [2, 3, 4, 5, 6]
    assert all(d.policy == "ess-gate" for d in decisions)
    assert decisions[0].reason == "ess-gate: ESS/N 0.300 at step 1 < threshold 0.5: on (PS 0.81)"
    assert decisions[2].reason == "ess-gate: ESS/N 0.500 at step 3 >= threshold 0.5: off (PS 0.81)"
    assert decisions[3].predicted == {}  # the figure is observed, not forecast
    assert decisions[3].command_fields()["preprocess"] is False


def test_the_gate_reads_the_current_ess_not_a_forecast_one():
    gate = ps_policy.get("ess-gate")
    assert gate.decide(4, observed(4, 0.2, predicted_ess_ratio=0.9, ess_trend=0.5)).preprocess
    assert not gate.decide(5, observed(5, 0.8, predicted_ess_ratio=0.1)).preprocess


def test_threshold_and_ps_are_options_and_a_bad_threshold_is_one_line():
    gate = EssGatePS(ps=0.4, threshold=0.2)
    assert gate.initial_ps == 0.4
    decision = gate.decide(7, observed(7, 0.25))
    assert not decision.preprocess and decision.ps == 0.4
    assert "ESS/N 0.250 at step 7 >= threshold 0.2: off (PS 0.4)" in decision.reason
    assert gate.decide(8, observed(8, 0.15)).preprocess
    for bad in (0.0, 1.5, -0.1, float("nan")):
        with pytest.raises(ValueError, match=r"^the ESS/N threshold must be in \(0, 1\], got"):
            EssGatePS(threshold=bad)


# --- the family ------------------------------------------------------------------


def test_listed_with_its_traits_and_accepted_by_the_run_configuration():
    assert ps_policy.POLICIES["ess-gate"] is EssGatePS
    assert "ess-gate" in family.POLICIES.names()
    assert family.POLICIES.summaries()["ess-gate"].startswith("Preprocess only while the mirrored ESS/N is below")
    assert RunConfig(policy="ess-gate").policy == "ess-gate"
    assert not EssGatePS.simulates and not EssGatePS.initial_preprocess and not EssGatePS.constant
    assert not EssGatePS.uses_evidence and not EssGatePS.samples_observations and not EssGatePS.chooses_arms
    layer = SystemLayer.from_config(RunConfig(policy="ess-gate", ps=0.6))
    assert not layer.needs_particles and layer.ps == 0.6


# --- a run -------------------------------------------------------------------------


def test_a_run_preprocesses_exactly_the_steps_after_one_below_the_threshold():
    result = run(RunConfig(policy="ess-gate", particles=N, steps=30))
    processed = np.array([step.report.n_processed for step in result.steps])
    below = result.ess / N < 0.5  # the mirrored ESS/N of each step, as the gate saw it
    assert processed[0] == 0  # the gate starts off
    np.testing.assert_array_equal(processed[1:] > 0, below[:-1])
    assert 0 < np.count_nonzero(processed[1:] > 0) < len(processed) - 1  # some steps on, some off
    assert np.isfinite(result.rmse)
