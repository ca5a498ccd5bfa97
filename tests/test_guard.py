"""The decision "off", the guard policy, the relative move rule and the jitters."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dtpf.entity import jitter, models
from dtpf.entity.filter import ParticleFilter
from dtpf.information import rules
from dtpf.information.layer import InformationLayer
from dtpf.information.mirror import summarise
from dtpf.messages.codec import decode_for_key, encode
from dtpf.messages.config import RunConfig
from dtpf.messages.models import PSCommand
from dtpf.scripts.inprocess import run
from dtpf.system import policy as ps_policy
from dtpf.system.predict import Forecast, Predictor, Snapshot

Z = 5.0


def weighted_set(n=2000, d=2, seed=0, offset=0.0):
    rng = np.random.default_rng(seed)
    w = np.exp(rng.normal(scale=1.5, size=n))
    return rng.normal(scale=3.0, size=(n, d)) + offset, w / w.sum()


# --- the relative move rule -----------------------------------------------------


@pytest.mark.parametrize("ps", [0.0, 0.81, 1.0])
def test_relative_rule_translates_with_the_state(ps):
    """Translating every particle (and so the observation) by c translates the result by c."""
    x, w = weighted_set(seed=1)
    shift = np.array([1e3, -250.0])
    a = rules.preprocess(x, w, ps, np.random.default_rng(2), move_rule="relative")
    b = rules.preprocess(x + shift, w, ps, np.random.default_rng(2), move_rule="relative")
    np.testing.assert_allclose(b.particles - shift, a.particles, rtol=0, atol=1e-9)
    assert a.report == b.report
    # The paper's rule is not invariant: the same shift moves its small particles elsewhere.
    p = rules.preprocess(x, w, ps, np.random.default_rng(2))
    q = rules.preprocess(x + shift, w, ps, np.random.default_rng(2))
    assert np.max(np.abs(q.particles - shift - p.particles)) > 1.0


def test_relative_rule_keeps_large_particles_and_lands_within_a_spread_of_the_partner():
    x, w = weighted_set(seed=3)
    result = rules.preprocess(x, w, 0.81, np.random.default_rng(4), move_rule="relative")
    limit = result.report.threshold
    large, small = np.flatnonzero(w > limit), np.flatnonzero(w <= limit)
    np.testing.assert_array_equal(result.particles[large], x[large])
    partners, r, u = rules.draws(np.random.default_rng(4), small.size, large.size)
    x_m = x[large[partners]]
    sigma = rules.spread(x, w)
    distance = np.abs(result.particles[small] - x_m)
    assert np.all(distance <= np.minimum(np.abs(x[small] - x_m), sigma) * (1 + 1e-12))
    # The factor f of Eq. 33-34 is (2r - 1) r or 2r - 1: the signed distance is f c (x_l - x_m).
    np.testing.assert_allclose(result.particles[small],
                               rules.apply_relative(x_m, x[small], r, u, 0.81, sigma), rtol=0, atol=0)
    assert result.report.n_mixed == int(np.sum(u <= 0.81))


def test_relative_rule_scales_with_the_state():
    x, w = weighted_set(seed=5)
    a = rules.preprocess(x, w, 0.5, np.random.default_rng(6), move_rule="relative")
    b = rules.preprocess(7.0 * x, w, 0.5, np.random.default_rng(6), move_rule="relative")
    np.testing.assert_allclose(b.particles, 7.0 * a.particles, rtol=1e-12, atol=1e-12)


def test_relative_rule_moves_the_mean_distance_the_factor_says():
    """Uncapped (sigma large), E|x_tilde - x_m| / |x_l - x_m| = E|f|: PS = 1 gives E|(2r-1) r| = 1/4,
    PS = 0 gives E|2r - 1| = 1/2; the standard error comes from the variance of |f|."""
    rng = np.random.default_rng(7)
    n = 100_000
    x_m, x_l = rng.normal(size=(n, 1)), rng.normal(size=(n, 1))
    r, u = rng.random(n), rng.random(n)
    for ps, mean, second in ((1.0, 0.25, 2.0 / 15.0), (0.0, 0.5, 1.0 / 3.0)):
        ratio = np.abs(rules.apply_relative(x_m, x_l, r, u, ps, np.array([1e9])) - x_m)[:, 0] / np.abs(x_l - x_m)[:, 0]
        se = math.sqrt((second - mean ** 2) / n)
        assert abs(ratio.mean() - mean) <= Z * se


def test_unknown_move_rule_is_refused():
    x, w = weighted_set(n=20)
    with pytest.raises(ValueError, match="move rule 'sideways'"):
        rules.preprocess(x, w, 0.5, np.random.default_rng(0), move_rule="sideways")
    with pytest.raises(ValueError, match="move_rule"):
        RunConfig(move_rule="sideways")


# --- the decision "off" ---------------------------------------------------------


def test_off_gives_the_set_back_unchanged_and_reports_no_processed_particle():
    x, w = weighted_set(seed=8)
    layer = InformationLayer(models.get("ungm"), ps=0.81, seed=1, twin="t")
    on = layer.preprocess(1, x, w, [0.0])
    layer.set_ps(0.81, 2, preprocess=False)
    off = layer.preprocess(2, x, w, [0.0])
    assert on.report.n_processed > 0
    np.testing.assert_array_equal(off.particles, x)
    np.testing.assert_array_equal(off.weights, w)
    assert (off.report.n_processed, off.report.n_mixed, off.report.n_plain) == (0, 0, 0)
    assert off.report.threshold == on.report.threshold and off.report.n_large == on.report.n_large
    layer.set_ps(0.5, 3)  # on again, with a new PS
    again = layer.preprocess(3, x, w, [0.0])
    assert again.report.n_processed > 0 and again.report.ps == 0.5


def test_a_run_always_off_is_the_plain_filter_number_for_number():
    """The guard with an impossible confidence never turns the preprocessing on: the entity then
    resamples exactly the set it sent, as the plain filter does."""
    config = RunConfig(particles=100, steps=30, seed=5, policy="guard")
    plain = run(config.model_copy(update={"preprocess": False}))

    class Never(ps_policy.GuardPS):
        def __init__(self, **options):
            super().__init__(**{**options, "confidence": math.inf})

    saved = ps_policy.POLICIES["guard"]
    ps_policy.POLICIES["guard"] = Never
    try:
        guarded = run(config)
    finally:
        ps_policy.POLICIES["guard"] = saved
    assert all(s.report.n_processed == 0 for s in guarded.steps)
    np.testing.assert_array_equal(guarded.means, plain.means)


def test_the_off_decision_round_trips_as_a_message():
    decision = ps_policy.PSDecision(0.81, 5, "guard", "guard: ...: off", {"error": 1.5}, preprocess=False)
    command = PSCommand(run_id="r", twin_id="t", step=4, **decision.command_fields())
    back = decode_for_key("dtpf/t/system/ps", encode(command))
    assert back.preprocess is False and back.predicted_error == 1.5
    assert PSCommand(run_id="r", twin_id="t", step=4, ps=0.5, applies_from_step=5, policy="fixed",
                     reason="").preprocess is True  # a command of an older log, without the field: on


# --- the guard policy -----------------------------------------------------------


def guard_forecast(sd_particles: float, seed: int = 0, n: int = 1000, move_rule: str = "paper"):
    """A forecast of the random-walk drift model from N particles ~ N(0, sd^2) with skewed weights."""
    rng = np.random.default_rng(seed)
    x = rng.normal(0.0, sd_particles, size=(n, 1))
    w = rng.random(n) ** 4
    w /= w.sum()
    model = models.DriftModel(process_var=0.01, observation_var=1.0)
    predictor = Predictor(model, move_rule=move_rule)
    return predictor.forecast(1, summarise(x, w), Snapshot.of(x, w, [0.0]), np.random.default_rng(seed + 1))


def test_guard_compares_off_and_on_on_the_same_numbers():
    forecast = guard_forecast(3.0, move_rule="relative")
    off, on = forecast.what_if([None, 0.81])
    again_on, again_off = guard_forecast(3.0, move_rule="relative").what_if([0.81, None])
    assert (off.error, on.error) == (again_off.error, again_on.error)
    assert off.ps is None and off.error != on.error


def test_guard_decides_off_without_a_simulation_and_when_the_gain_is_within_the_noise():
    guard = ps_policy.GuardPS(ps=0.81)
    assert guard.initial_preprocess is False
    bare = Forecast(step=3, n=10, ess_ratio=0.5, ess_trend=0.0, distinct_ratio=0.5)
    decision = guard.decide(3, bare)
    assert decision.preprocess is False and decision.applies_from_step == 4 and "no particle set" in decision.reason
    forecast = guard_forecast(3.0)
    off, on = forecast.what_if([None, 0.81])
    diff = on.errors - off.errors
    se = diff.std(ddof=1) / math.sqrt(diff.size)
    decision = guard.decide(1, forecast)
    assert decision.preprocess == bool(-diff.mean() > guard.confidence * se)
    assert decision.reason.startswith("guard: ") and decision.reason.endswith("on" if decision.preprocess else "off")
    # Confidence 0 turns it on exactly when the mean predicted gain is positive; infinite confidence never.
    assert ps_policy.GuardPS(confidence=0.0).decide(1, forecast).preprocess == bool(diff.mean() < 0)
    assert ps_policy.GuardPS(confidence=math.inf).decide(1, forecast).preprocess is False


class Scripted:
    """A simulation whose predicted errors per scenario are given: off, and PS."""

    def __init__(self, off, on):
        self.errors = {None: np.asarray(off, dtype=float), 0.81: np.asarray(on, dtype=float)}

    def outcomes(self, ps_values):
        from dtpf.system.predict import Outcome
        return [Outcome(ps, float(self.errors[ps].mean()), self.errors[ps], 0.5) for ps in ps_values]


@pytest.mark.parametrize("gain, noise, expected", [(1.0, 0.1, True), (1.0, 10.0, False), (-1.0, 0.1, False)])
def test_guard_turns_preprocessing_on_only_for_a_gain_beyond_its_confidence(gain, noise, expected):
    """Paired errors over 8 scenarios: PS better by ``gain`` with scenario-to-scenario ``noise``."""
    off = np.full(8, 5.0)
    on = off - gain + noise * np.array([1, -1, 1, -1, 1, -1, 1, -1.0])
    forecast = Forecast(step=2, n=100, ess_ratio=0.5, ess_trend=0.0, distinct_ratio=0.5,
                        simulation=Scripted(off, on))
    decision = ps_policy.GuardPS(ps=0.81).decide(2, forecast)
    se = np.std(on - off, ddof=1) / math.sqrt(8)
    assert (gain > ps_policy.GuardPS.T95_7 * se) == expected  # the case is what its name says
    assert decision.preprocess is expected
    assert decision.predicted["error"] == pytest.approx((on if expected else off).mean())
    assert decision.ps == 0.81 and decision.applies_from_step == 3


# --- jitters --------------------------------------------------------------------


def test_roughening_adds_the_documented_variance():
    rng = np.random.default_rng(9)
    n, d = 20_000, 2
    x = rng.uniform(-1.0, 1.0, size=(n, d)) * np.array([1.0, 10.0])
    moved = jitter.roughening(x, np.random.default_rng(10))
    sigma = jitter.ROUGHENING_K * np.ptp(x, axis=0) * n ** (-1.0 / d)
    noise = moved - x
    # The sample variance of n normals has relative standard error sqrt(2 / n).
    np.testing.assert_array_less(np.abs(noise.var(axis=0) / sigma ** 2 - 1.0), Z * math.sqrt(2.0 / n))
    assert np.all(np.abs(noise.mean(axis=0)) <= Z * sigma / math.sqrt(n))


def test_regularised_kernel_has_the_covariance_of_the_set_times_h_squared():
    rng = np.random.default_rng(11)
    n = 20_000
    cov = np.array([[4.0, 1.5], [1.5, 1.0]])
    x = rng.multivariate_normal([5.0, -3.0], cov, size=n)
    w = np.full(n, 1.0 / n)
    noise = jitter.regularised(x, x, w, np.random.default_rng(12)) - x
    h = jitter.bandwidth(n, 2)
    assert h == pytest.approx((4.0 / (n * 4.0)) ** (1.0 / 6.0))
    sample = np.cov(noise.T) / h ** 2
    expected = np.cov(x.T, bias=True)
    # Each entry of a sample covariance has standard error about sqrt((s_ii s_jj + s_ij^2) / n).
    se = np.sqrt((np.outer(np.diag(expected), np.diag(expected)) + expected ** 2) / n)
    assert np.all(np.abs(sample - expected) <= Z * se)


def test_jitters_translate_with_the_state_and_leave_a_collapsed_direction_alone():
    rng = np.random.default_rng(13)
    x = rng.normal(size=(500, 2))
    x[:, 1] = 3.0  # every particle at the same second component
    w = np.full(500, 1.0 / 500)
    for name in ("roughening", "regularised"):
        a = jitter.apply(name, x, x, w, np.random.default_rng(14))
        b = jitter.apply(name, x + 100.0, x + 100.0, w, np.random.default_rng(14))
        np.testing.assert_allclose(b - 100.0, a, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a[:, 1], 3.0, rtol=0, atol=1e-12)
        assert np.std(a[:, 0] - x[:, 0]) > 0


def test_a_filter_with_jitter_draws_only_from_its_own_stream():
    model = models.DriftModel()
    truth, z = model.simulate(20, np.random.default_rng(0))
    plain = [s for s in ParticleFilter(model, z, 200, seed=3, twin="t")]
    rough = [s for s in ParticleFilter(model, z, 200, seed=3, twin="t", jitter="roughening")]
    # Step 1 starts from the prior, identical; the resampling of step 1 uses the same ancestors.
    np.testing.assert_array_equal(plain[0].particles, rough[0].particles)
    np.testing.assert_array_equal(plain[0].ancestors, rough[0].ancestors)
    # From step 2 on the particles differ by the jitter the first resampling got.
    assert not np.array_equal(plain[1].particles, rough[1].particles)
    with pytest.raises(ValueError, match="unknown move 'shake'"):
        ParticleFilter(model, z, 10, jitter="shake")


def test_drift_model_kalman_is_the_exact_posterior_mean():
    """For the linear Gaussian drift model a large particle filter converges to the Kalman mean."""
    model = models.DriftModel(process_var=0.01, observation_var=0.25)
    truth, z = model.simulate(10, np.random.default_rng(1))
    kalman = model.kalman(z)
    pf = [s.mean[0] for s in ParticleFilter(model, z, 200_000, seed=2, twin="t")]
    # Posterior sd at step k is below 0.5; Monte Carlo error of the mean with 2e5 particles (ESS
    # above 5e4 here) is below 0.5 / sqrt(5e4) = 0.0022 per step.
    assert np.max(np.abs(np.array(pf) - kalman[:, 0])) <= Z * 0.0022


# --- the evidence of the real observations (guard-observed) ---------------------


def evidence_run(centre: float, move_rule: str = "paper", steps: int = 6, seed: int = 0):
    """Feed Evidence a set collapsed near ``centre`` while the truth stays at 0 (drift model, z ~ N(0, 0.01^2))."""
    from dtpf.system.evidence import Evidence
    model = models.DriftModel()
    evidence = Evidence(model, 0.0, move_rule=move_rule, weight_rule="likelihood", window=20)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(1, steps + 1):
        x = centre + 0.01 * rng.standard_normal((500, 1))
        w = np.full(500, 1.0 / 500)
        z = 0.01 * rng.standard_normal(1)
        out.append(evidence.observe(k, x, w, z, np.random.default_rng([seed, k])))
    return evidence, out


def test_evidence_scores_each_pair_of_arms_with_the_next_real_observation():
    evidence, out = evidence_run(0.0)
    assert out[:2] == [None, None]  # step 1 draws the start, step 2 makes the first arms, step 3 scores them
    assert all(d is not None and math.isfinite(d) for d in out[2:])
    assert len(evidence.differences) == 4 and evidence.total == pytest.approx(sum(out[2:]))
    again, repeat = evidence_run(0.0)
    assert repeat == out  # the generators given are the only source of randomness


def test_evidence_favours_preprocessing_when_the_set_sits_away_from_the_observations():
    """A set at 0.1 (10 observation sds off) under the paper's rule, which scatters small particles by up
    to their own coordinate (0.1) around large ones: some land near 0, the on arm predicts z ~ 0 far
    better. Centred at 0, the scatter is within the set's own width and gains almost nothing."""
    far, far_out = evidence_run(0.1)
    near, near_out = evidence_run(0.0)
    assert all(d > 1.0 for d in far_out[2:])
    assert far.total > 4 * abs(near.total)


def test_evidence_is_zero_when_the_preprocessing_moves_nothing():
    from dtpf.system.evidence import Evidence
    model = models.DriftModel(observation_var=1e12)  # flat likelihood: equal weights, W = 0, nothing small
    evidence = Evidence(model, 0.81)
    rng = np.random.default_rng(3)
    for k in range(1, 6):
        x = rng.standard_normal((200, 1))
        evidence.observe(k, x, np.full(200, 1 / 200), [0.0], np.random.default_rng(k))
    assert list(evidence.differences) == [0.0, 0.0, 0.0]


def test_guard_observed_turns_on_with_evidence_above_log_19_and_runs_where_nothing_can_be_sampled():
    policy = ps_policy.GuardObservedPS(ps=0.5)
    base = dict(step=7, n=10, ess_ratio=0.5, ess_trend=0.0, distinct_ratio=0.5)
    assert policy.decide(7, Forecast(**base, evidence=math.log(19) + 0.01, evidence_steps=20)).preprocess
    off = policy.decide(7, Forecast(**base, evidence=math.log(19) - 0.01, evidence_steps=20))
    assert not off.preprocess and off.predicted["evidence"] == pytest.approx(math.log(19) - 0.01)
    assert not policy.decide(7, Forecast(**base)).preprocess
    # It needs no sample_observation: the video scenario accepts it, as it refuses the what-if guard.
    RunConfig(scenario="video", policy="guard-observed")
    with pytest.raises(ValueError, match="simulates observations"):
        RunConfig(scenario="video", policy="guard")


# --- over Zenoh, in the log, through dtpf verify ----------------------------------


@pytest.fixture(scope="module")
def guarded_log(tmp_path_factory):
    """A launched guard-observed run on the drift scenario that turns the preprocessing on for
    steps 23-26 only (decisions of steps 22-25; found in process, seed 2) and off everywhere else."""
    from dtpf.scripts.launch import launch
    config = RunConfig(scenario="drift", policy="guard-observed", particles=100, steps=40, seed=2, twin="t-guard")
    path = tmp_path_factory.mktemp("guard") / "guard.mcap"
    result = launch(config, log_path=path, timeout=5.0)
    assert result.exit_codes["entity"] == 0
    return config, result, path


def test_the_off_decision_travels_over_zenoh_is_recorded_and_verifies(guarded_log):
    from dtpf.recording.logfile import read_log
    from dtpf.scripts.logs.verify import verify

    config, result, path = guarded_log
    log = read_log(path)
    messages = [(m.topic, decode_for_key(m.topic, m.data)) for m in log.messages]
    commands = {m.step: m for topic, m in messages if isinstance(m, PSCommand)}
    entity = {m.step: m for topic, m in messages if topic.endswith("entity/particles")}
    preprocessed = {m.step: m for topic, m in messages if topic.endswith("information/preprocessed")}
    assert sorted(commands) == list(range(1, 41))
    on = sorted(k for k, c in commands.items() if c.preprocess)
    assert on == [22, 23, 24, 25]
    assert all(commands[k].reason.endswith(": off") for k in commands if k not in on)
    assert all(c.evidence is not None for k, c in commands.items() if k >= 3)
    for k in range(2, 41):  # the decision of step k - 1 is in force at step k
        processed = preprocessed[k].n_processed
        if commands[k - 1].preprocess:  # every small particle moved (none are small when ESS rounds to N)
            assert processed == config.particles - preprocessed[k].n_large
        else:
            assert processed == 0
            np.testing.assert_array_equal(preprocessed[k].particles, entity[k].particles)
    assert sum(preprocessed[k].n_processed for k in range(23, 27)) > 0
    assert preprocessed[1].n_processed == 0  # the guard starts off
    reference = run(config)
    np.testing.assert_array_equal([e.mean for e in result.estimates], reference.means)
    verification = verify(log)
    assert verification.ok, str(verification.mismatch)
    assert verification.checked == list(range(1, 41))
    from dtpf.scripts.logs.summary import format_summary, summarise
    assert "preprocessing off in 36 of 40 commands" in format_summary(summarise(log))


def test_verify_notices_a_flipped_off_decision(guarded_log, tmp_path):
    from dtpf.recording.logfile import read_log
    from dtpf.scripts.logs.verify import verify

    from conftest import altered_log

    _, _, path = guarded_log
    flipped = altered_log(path, tmp_path / "flipped.mcap", "system/ps", 30, lambda m: {"preprocess": True})
    mismatch = verify(read_log(flipped)).mismatch
    assert (mismatch.step, mismatch.field) == (30, "preprocess")


def test_the_evaluation_quick_form_prints_every_variant_of_every_scenario(capsys):
    """``python -m dtpf.scripts.paper.evaluate_guard --quick``, in one process: a table per scenario with every
    variant that can run there, finite errors, and a verdict per scenario."""
    from dtpf.scripts.paper import evaluate_guard

    assert evaluate_guard.main(["--quick", "--workers", "1"]) == 0
    out = capsys.readouterr().out
    for scenario in evaluate_guard.SCENARIOS:
        block = out.split(f"**{scenario}, N = 50**")[1].split("**")[0]
        rows = {line.split("|")[1].strip(): line for line in block.splitlines() if line.startswith("| ")}
        expected = {label for label in evaluate_guard.VARIANTS if evaluate_guard.runs_on(scenario, label)}
        assert expected <= set(rows), scenario
        errors = [float(rows[label].split("|")[2].split("±")[0]) for label in expected]
        assert all(math.isfinite(e) and e >= 0 for e in errors)
        assert f"- {scenario}, N = 50: best guard " in out
    assert "guard, paper rule" not in out.split("**video, N = 50**")[1].split("Verdicts")[0]
    # A translation-invariant variant errs the same on drift and on drift shifted by 100; the paper's rule not.
    drift = out.split("**drift, N = 50**")[1].split("**")[0]
    shifted = out.split("**drift+100, N = 50**")[1].split("**")[0]

    def error(block, label):
        line = next(l for l in block.splitlines() if l.startswith(f"| {label} |"))
        return float(line.split("|")[2].split("±")[0])

    for label in ("systematic", "DT relative rule, PS 0", "regularised"):
        assert error(drift, label) == pytest.approx(error(shifted, label), rel=1e-6)
    assert error(shifted, "DT paper rule, PS 0.81") > 100 * error(drift, "DT paper rule, PS 0.81")


def test_the_evaluation_runs_dtpf_compare_cells_and_prints_the_command_of_one(capsys, tmp_path):
    """evaluate_guard's cells are dtpf compare plans: its --csv is a compare CSV whose video rows are the squared
    distance of the estimated to the true centre (worked out here from an in-process run), the same command
    again runs nothing and prints the same tables, and the dtpf compare command it prints for the video cell
    gives every run's error to the last digit."""
    import shlex
    import subprocess
    import sys

    from conftest import ROOT
    from dtpf.scripts.compare_csv import CompareCsv
    from dtpf.scripts.paper import evaluate_guard

    path = tmp_path / "guard.csv"
    argv = ["--seeds", "2", "--steps", "5", "--particles", "20", "--scenarios", "video", "drift+100", "--workers",
            "1", "--csv", str(path)]
    assert evaluate_guard.main(argv) == 0
    out = capsys.readouterr().out
    held, _ = CompareCsv(path).read()
    video = {(label, seed): row for (cell, label, seed), row in held.items() if cell == "video, N = 20"}
    assert {label for label, _ in video} == {label for label in evaluate_guard.VARIANTS
                                             if evaluate_guard.runs_on("video", label)}
    assert all(row.metric == "squared-distance[0,1]" for row in video.values())
    result = run(RunConfig(scenario="video", particles=20, steps=5, seed=1, twin="guard-1", preprocess=False,
                           resampler="stratified"))
    centre = float(np.mean(np.sum((result.means[:, :2] - result.truth[:, :2]) ** 2, axis=1)))
    assert video[("stratified", 1)].value == centre
    assert "| Kalman (exact) |" in out.split("**drift+100, N = 20**")[1]
    assert evaluate_guard.main(argv) == 0
    again = capsys.readouterr().out
    assert again.split("(")[:-1] == out.split("(")[:-1]  # the same report but the time it took
    assert len(CompareCsv(path).read()[0]) == len(held)

    command = out.split("\n\n    dtpf compare ")[1].split("\n\n")[0]
    assert command.startswith("--scenario video -n 20 -T 5 --twin guard-1 --seeds 2 --metric squared-distance "
                              "--components 0,1")
    table = tmp_path / "compare.csv"
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "compare", *shlex.split(command.replace(
        "\\\n", " ")), "--workers", "1", "--csv", str(table)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    direct = {(label, seed): row.value for (_, label, seed), row in CompareCsv(table).read()[0].items()}
    assert direct == {key: row.value for key, row in video.items()}


_SYSTEM_FIRST_STEPS = """
import numba, numpy as np
import dtpf.entity._growth, dtpf.entity._merge, dtpf.information.mirror, dtpf.information.rules, dtpf.information.select, dtpf.messages._seedseq
from dtpf.entity import models
from dtpf.information.mirror import summarise
from dtpf.messages.config import RunConfig
from dtpf.system.layer import SystemLayer, warm_up
from dtpf.system.predict import Snapshot

def compiled():
    return sum(len(f.signatures) for module in (dtpf.entity._growth, dtpf.entity._merge, dtpf.information.rules, dtpf.information.select,
                                                dtpf.information.mirror, dtpf.messages._seedseq)
               for f in vars(module).values() if isinstance(f, numba.core.registry.CPUDispatcher))

config = RunConfig(policy="guard-observed", move_rule="relative", weight_rule="likelihood", ps=0.0, particles=300)
model = models.get("ungm")
warm_up(config, model)
before = compiled()
layer = SystemLayer.from_config(config, model=model, keep=16)
rng = np.random.default_rng(3)
for step in range(1, 6):  # what the service decodes: read-only arrays
    x, w = rng.standard_normal((300, 1)) * 5, rng.random(300)
    w /= w.sum()
    x.flags.writeable = w.flags.writeable = False
    layer.observe(step, summarise(x, w, "neff", 300), Snapshot.of(x, w, np.array([float(step)])))
print(before, compiled())
"""


def test_the_system_layers_warm_up_compiles_what_its_first_real_steps_need():
    # On a cold cache guard-observed compiled at step 4, for seconds, past the lockstep timeout: three steps
    # degraded. In a fresh process, so that nothing else compiled those kernels first.
    import subprocess
    import sys

    from conftest import ROOT
    done = subprocess.run([sys.executable, "-c", _SYSTEM_FIRST_STEPS], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    before, after = map(int, done.stdout.split())
    assert before > 0 and after == before
