"""The system layer: degradation predictor, PS policies, and a launched adaptive run."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dtpf.entity.models import StateSpaceModel
from dtpf.information.mirror import summarise
from dtpf.messages.codec import decode_for_key
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate, PSCommand
from dtpf.recording.logfile import read_log
from dtpf.scripts.inprocess import build, run, simulate
from dtpf.scripts.launch import launch
from dtpf.scripts.logs.verify import verify
from dtpf.system import policy as ps_policy
from dtpf.system.layer import SystemLayer
from dtpf.system.predict import Forecast, Predictor, Snapshot


@dataclasses.dataclass(frozen=True)
class RandomWalk(StateSpaceModel):
    """x_k = x_(k-1) + N(0, q), z_k = x_k + N(0, r): every forecast has a closed form."""

    name: str = "random-walk"
    q: float = 0.01
    r: float = 1.0
    dim: int = 1
    obs_dim: int = 1

    def initial_particles(self, n, rng):
        return rng.standard_normal((n, 1))

    def propagate(self, particles, k, rng):
        return particles + math.sqrt(self.q) * rng.standard_normal(particles.shape)

    def log_likelihood(self, particles, observation, k):
        residual = float(np.asarray(observation).reshape(-1)[0]) - particles[:, 0]
        return -0.5 * residual ** 2 / self.r - 0.5 * math.log(2 * math.pi * self.r)

    def sample_observation(self, states, k, rng):
        return states[:, :1] + math.sqrt(self.r) * rng.standard_normal((states.shape[0], 1))

    def simulate(self, steps, rng):
        raise NotImplementedError


N = 1000


def forecast_of(sd: float, seed: int = 0, weights=None, predictor=None, step: int = 1, z: float = 0.0):
    """Forecast from N particles ~ N(0, sd^2) with ``weights`` (default uniform), random-walk model."""
    x = np.random.default_rng(seed).normal(0.0, sd, size=(N, 1))
    w = np.full(N, 1.0 / N) if weights is None else weights
    predictor = predictor or Predictor(RandomWalk())
    return predictor.forecast(step, summarise(x, w), Snapshot.of(x, w, [z]), np.random.default_rng(seed + 100))


# --- predictor ------------------------------------------------------------------


def test_a_set_much_wider_than_the_observation_noise_predicts_collapse_a_tight_one_does_not():
    # Prior variance P after propagation, likelihood variance r = 1: for z drawn from the
    # predictive, E[ESS/N] ~ sqrt(r (r + 2P)) / (r + P) / sqrt(1 + 2P / (2P + r)):
    # P = 100.01 gives about 0.10, P = 0.02 about 0.98.
    wide, tight = forecast_of(10.0), forecast_of(0.1)
    assert wide.predicted_ess_ratio < 0.25
    assert tight.predicted_ess_ratio > 0.9
    # Scenario by scenario, not only on average: every simulated next step of the wide set
    # collapses further than any of the tight set.
    assert wide.simulation.ess.max() < tight.simulation.ess.min()
    assert wide.predicted_distinct_ratio < tight.predicted_distinct_ratio
    # Posterior sd: sqrt(P r / (P + r)) = 0.995 against 0.140.
    assert wide.predicted_spread == pytest.approx(0.995, abs=0.15)
    assert tight.predicted_spread == pytest.approx(0.140, abs=0.03)


def test_surprise_is_large_for_an_observation_the_forecast_did_not_expect():
    # Predictive of z after a tight set at 0: N(0, P + r), P + r = 1.02. A typical z scores
    # about 0 nats; z = 10 about 10^2 / (2 * 1.02) - 1/2 = 48.5 nats of surprise.
    for z, low, high in ((0.0, -2.0, 2.0), (10.0, 40.0, 57.0)):
        predictor = Predictor(RandomWalk())
        forecast_of(0.1, predictor=predictor, step=1)
        second = forecast_of(0.1, predictor=predictor, step=2, z=z)
        assert low < second.surprise < high, z
    first = forecast_of(0.1)
    assert first.surprise is None  # no simulation of the step before


def test_trend_of_a_collapsing_history_points_down_and_of_a_uniform_one_stays_flat():
    x = np.zeros((N, 1))
    collapsing, uniform = Predictor(), Predictor()
    for step, concentration in enumerate([0.0, 0.5, 1.0, 1.5, 2.0], start=1):
        w = np.exp(-concentration * np.arange(N) / 50.0)
        w /= w.sum()
        falling = collapsing.forecast(step, summarise(x, w))
        flat = uniform.forecast(step, summarise(x, np.full(N, 1.0 / N)))
    assert falling.ess_trend < 0
    assert falling.next_ess_ratio < falling.ess_ratio
    assert falling.predicted_ess_ratio is None  # no model, no simulation
    assert flat.ess_trend == 0.0 and flat.next_ess_ratio == pytest.approx(1.0)


def test_what_if_uses_the_same_numbers_for_every_candidate():
    skewed = np.random.default_rng(3).random(N) ** 4
    skewed /= skewed.sum()
    forecast = forecast_of(3.0, weights=skewed)
    together = forecast.what_if([0.0, 0.5, 1.0])
    again = forecast_of(3.0, weights=skewed).what_if([1.0, 0.5])
    assert [o.error for o in together[1:]] == [o.error for o in reversed(again)]
    assert len({o.error for o in together}) == 3  # PS changes where small particles land
    # An uninformative observation (r = 1e12) leaves the simulated weights uniform to ~1e-11:
    # round(ESS) = N, W = 0, nothing is small, the rules move nothing, PS cannot matter.
    flat = forecast_of(3.0, predictor=Predictor(RandomWalk(r=1e12))).what_if([0.0, 0.5, 1.0])
    assert len({o.error for o in flat}) == 1


# --- policies -------------------------------------------------------------------


def forecast(step: int, ess: float, distinct: float = 0.5, surprise: float | None = 0.0) -> Forecast:
    return Forecast(step=step, n=N, ess_ratio=ess, ess_trend=0.0, distinct_ratio=distinct, surprise=surprise,
                    predicted_ess_ratio=ess, predicted_distinct_ratio=distinct, predicted_spread=1.0)


@pytest.mark.parametrize("current, target, rate", [(0.81, 0.0, 0.25), (0.1, -3.0, 0.5), (0.9, 7.0, 0.3),
                                                   (0.5, 0.55, 0.25), (0.0, 1.0, 1.0)])
def test_limit_keeps_ps_in_bounds_and_within_the_rate(current, target, rate):
    new = ps_policy.limit(current, target, rate)
    assert 0.0 <= new <= 1.0
    assert abs(new - current) <= rate + 1e-12
    assert new == pytest.approx(min(1.0, max(0.0, current + np.clip(target - current, -rate, rate))))


def test_rule_policy_moves_at_the_bounded_rate_and_holds_its_state_between_thresholds():
    rule = ps_policy.get("rule", ps=0.81, max_change=0.25)
    figures = [0.05] * 5 + [0.2] * 3 + [0.5] * 5   # collapse, between the thresholds, healthy
    decisions = [rule.decide(k, forecast(k, ess)) for k, ess in enumerate(figures, start=1)]
    ps = [rule.initial_ps] + [d.ps for d in decisions]
    assert np.all(np.abs(np.diff(ps)) <= 0.25 + 1e-12)
    assert min(ps) == 0.0 and max(ps) == 0.81
    assert ps[1:5] == pytest.approx([0.56, 0.31, 0.06, 0.0])
    assert "next ESS/N 0.050 < 0.15" in decisions[0].reason and "PS 0.81 -> 0.56" in decisions[0].reason
    # 0.2 lies between ess_enter (0.15) and ess_exit (0.25): hysteresis keeps PS down.
    assert [d.ps for d in decisions[5:8]] == [0.0] * 3
    assert all("still degraded" in d.reason for d in decisions[5:8])
    assert "recovered" in decisions[8].reason
    assert ps[-5:] == pytest.approx([0.25, 0.5, 0.75, 0.81, 0.81])
    assert decisions[0].predicted["ess_ratio"] == 0.05
    assert decisions[0].command_fields()["predicted_ess_ratio"] == 0.05


def test_rule_policy_enters_on_surprise_and_impoverishment_too():
    for figures, words in ((dict(ess=0.5, surprise=5.0), "surprise 5.00 > 3 nats"),
                           (dict(ess=0.5, distinct=0.1), "next distinct/N 0.100 < 0.2")):
        rule = ps_policy.get("rule")
        decision = rule.decide(1, forecast(1, **figures))
        assert words in decision.reason and decision.ps < 0.81


def test_bad_policy_options_are_refused():
    with pytest.raises(ValueError, match="max_change must be in"):
        ps_policy.get("rule", max_change=0.0)
    with pytest.raises(ValueError, match="ess_enter must be <= ess_exit"):
        ps_policy.get("rule", ess_enter=0.5, ess_exit=0.2)
    with pytest.raises(ValueError, match="unknown PS policy 'psychic'"):
        ps_policy.get("psychic")
    with pytest.raises(ValueError, match="ps_rate"):
        RunConfig(ps_rate=0.0)


def decisions_of(config: RunConfig):
    _, observations = simulate(config)
    pf = build(config, observations)
    for _ in pf:
        pass
    return pf.preprocessor.system.decisions


def test_predictive_policy_is_bounded_rate_limited_and_deterministic_for_a_seed():
    config = RunConfig(policy="predictive", particles=100, steps=30, seed=5, ps_rate=0.2)
    first, second = decisions_of(config), decisions_of(config)
    assert first == second
    ps = [0.81] + [d.ps for d in first]
    assert all(0.0 <= p <= 1.0 for p in ps)
    assert np.all(np.abs(np.diff(ps)) <= 0.2 + 1e-12)
    assert len(set(ps)) > 1
    other = decisions_of(config.model_copy(update={"seed": 6}))
    assert [d.predicted for d in other] != [d.predicted for d in first]


def test_predictive_policy_keeps_ps_without_a_particle_set():
    policy = ps_policy.get("predictive", ps=0.4)
    layer = SystemLayer(policy, Predictor(RandomWalk()))
    x = np.zeros((N, 1))
    decision = layer.observe(1, summarise(x, np.full(N, 1.0 / N)))
    assert decision.ps == 0.4 and "no particle set" in decision.reason


def test_fixed_policy_is_unchanged_and_needs_no_particles():
    layer = SystemLayer.from_config(RunConfig(policy="fixed", ps=0.5))
    assert not layer.needs_particles
    result = run(RunConfig(policy="fixed", ps=0.5, particles=100, steps=10))
    assert set(result.ps) == {0.5}


# --- a launched run -------------------------------------------------------------


@pytest.fixture(scope="module")
def adaptive_log(tmp_path_factory):
    config = RunConfig(policy="predictive", particles=200, steps=30, seed=4, twin="t-adaptive")
    path = tmp_path_factory.mktemp("policy") / "predictive.mcap"
    result = launch(config, log_path=path, timeout=5.0)
    assert result.exit_codes["entity"] == 0
    return config, result, path


def test_a_launched_adaptive_run_changes_ps_with_reasons_and_verifies(adaptive_log):
    config, result, path = adaptive_log
    log = read_log(path)
    messages = [decode_for_key(m.topic, m.data) for m in log.messages]
    commands = {m.step: m for m in messages if isinstance(m, PSCommand)}
    estimates = {m.step: m for m in messages if isinstance(m, Estimate)}
    assert sorted(commands) == list(range(1, 31))
    changes = [k for k in range(2, 31) if commands[k].ps != commands[k - 1].ps]
    assert len(changes) >= 2
    for k in changes:
        assert commands[k].reason.startswith("predictive: ") and "->" in commands[k].reason
    assert all(c.predicted_ess_ratio is not None and c.predicted_error is not None for c in commands.values())
    assert all(c.surprise is not None for k, c in commands.items() if k > 1)
    # The information layer used each PS from the step after the decision on.
    assert all(estimates[k + 1].ps == commands[k].ps for k in range(1, 30))
    # Over Zenoh as in one process, number for number (the launcher sums the RMSE as the steps come,
    # so it may differ in the last bit).
    reference = run(config)
    np.testing.assert_array_equal([e.mean for e in result.estimates], reference.means)
    assert result.rmse == pytest.approx(reference.rmse, rel=1e-12)
    verification = verify(log)
    assert verification.ok, str(verification.mismatch)
    assert verification.checked == list(range(1, 31))


def test_verify_notices_an_altered_predicted_figure(adaptive_log, tmp_path):
    from conftest import altered_log

    _, _, path = adaptive_log
    altered = altered_log(path, tmp_path / "altered.mcap", "system/ps", 9,
                          lambda m: {"predicted_ess_ratio": m.predicted_ess_ratio * 1.001})
    mismatch = verify(read_log(altered)).mismatch
    assert (mismatch.step, mismatch.field) == (9, "predicted_ess_ratio")


def test_the_evaluation_command_prints_every_variant_with_finite_figures(tmp_path, capsys):
    """A reduced ``python -m dtpf.scripts.paper.evaluate_policies``: the table and the plot, not the verdict."""
    from dtpf.scripts.paper import evaluate_policies

    plot = tmp_path / "ps.png"
    assert evaluate_policies.main(["--seeds", "3", "--particles", "50", "--steps", "20", "--workers", "1",
                                   "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith(("| ungm |", "| ungm-printed |"))]
    variants = {row.split("|")[3].strip() for row in rows}
    assert {"systematic", "DT, PS = 0.81", "DT, rule", "DT, predictive"} <= variants
    mse = [float(row.split("|")[4].split("±")[0]) for row in rows if "±" in row.split("|")[4]]
    assert len(mse) == 2 * len(evaluate_policies.VARIANTS)  # two scenarios, one N
    assert all(math.isfinite(v) and v > 0 for v in mse)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
