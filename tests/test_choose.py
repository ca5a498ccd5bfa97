"""The choosing policy: the twin runs every arm on its copies and puts the best in force."""
from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from dtpf.entity import jitter, models
from dtpf.entity.filter import ParticleFilter
from dtpf.information.layer import ARMS, InformationLayer
from dtpf.messages import names
from dtpf.messages.config import RunConfig
from dtpf.messages.models import PSCommand
from dtpf.scripts.inprocess import InProcessTwin, build, simulate
from dtpf.system.choose import ArmEvidence
from dtpf.system.layer import SystemLayer
from dtpf.system.policy import ChoosePS

#: A drift run on the plain base that puts three arms in force (plain, dt-paper from step 10, regularised from
#: step 20); found in process.
CHOSEN = RunConfig(scenario="drift", policy="choose", choose_base="plain", particles=100, steps=30, seed=31,
                   twin="t-choose")


def test_the_arms_the_contract_names_are_the_arms_the_layers_implement():
    assert names.ARMS == (*ARMS, names.OWN_ARM)
    from dtpf.system.policy import POLICIES
    assert POLICIES["choose"] is ChoosePS and not ChoosePS.initial_preprocess and ChoosePS.chooses_arms
    assert not ChoosePS.samples_observations  # no sample_observation: it runs on the video
    assert ChoosePS().arms == tuple(ARMS)
    assert ChoosePS(move="my_moves.py:shake").arms == names.ARMS  # a user's move is one more arm, "own"


def _twin(config: RunConfig, model, enter: float | None = None) -> InProcessTwin:
    system = SystemLayer.from_config(config, model=model)
    if enter is not None:
        system.policy.enter = enter
    information = InformationLayer(model, ps=system.policy.initial_ps, threshold_rule=config.threshold,
                                   seed=config.seed, twin=config.twin, preprocess=False,
                                   arm=system.policy.initial_arm)
    return InProcessTwin(information, system)


@pytest.mark.parametrize("scenario", ["drift", "ungm"])
def test_a_run_that_always_chooses_plain_equals_the_plain_filter_number_for_number(scenario):
    config = RunConfig(scenario=scenario, policy="choose", choose_base="plain", particles=100, steps=40, seed=11,
                       twin="t-choose")
    model = models.get(scenario)
    _, z = simulate(config, model)
    plain = list(ParticleFilter(model, z, 100, seed=config.seed, twin=config.twin))
    twin = _twin(config, model, enter=math.inf)  # the evidence is gathered, never enough to leave plain
    chosen = list(ParticleFilter(model, z, 100, seed=config.seed, twin=config.twin, preprocessor=twin))
    assert [d.arm for d in twin.decisions] == ["plain"] * 40
    assert max(abs(d.predicted.get("evidence", 0.0)) for d in twin.decisions) == 0.0  # plain's own: 0
    assert any(abs(v) > 0 for v in twin.system.forecasts[-1].arm_evidence.values())
    for a, b in zip(plain, chosen):
        assert np.array_equal(a.particles, b.particles) and np.array_equal(a.weights, b.weights)
        assert np.array_equal(a.mean, b.mean) and np.array_equal(a.ancestors, b.ancestors)


def test_the_chosen_arm_applies_from_the_next_step_where_its_move_lives():
    model = models.get("drift")
    _, z = simulate(CHOSEN, model)
    pf = build(CHOSEN, z, model)
    steps = list(pf)
    decisions = pf.preprocessor.decisions
    arms = [d.arm for d in decisions]
    assert {"plain", "dt-paper", "regularised"} <= set(arms)
    for k in range(2, CHOSEN.steps + 1):
        arm = ARMS[arms[k - 2]]  # the decision of step k - 1
        report = steps[k - 1].report
        assert decisions[k - 2].applies_from_step == k
        if arm.preprocess:
            assert report.ps == arm.ps and report.n_processed > 0 or report.n_large == CHOSEN.particles
        else:
            assert report.n_processed == 0
    # A jitter arm moves the resampled particles (the entity); a DT or plain arm leaves them as resampled.
    k = arms.index("regularised") + 2
    jittered = pf.preprocessor.information
    assert jittered is not None and steps[k - 1].report.n_processed == 0
    assert all(d.reason.startswith("choose: ") for d in decisions)


def _evidence_after_one_step(arm: str, n: int = 4000, d: int = 2, seed: int = 5):
    """The copies of ArmEvidence after its first step on a set from N(0, C), with a model whose
    propagation adds nothing (process variance 0): each copy is its arm's move of the same resampled set."""
    model = models.DriftModel(process_var=0.0, dim=d)
    rng = np.random.default_rng(seed)
    cov = np.array([[1.0, 0.6], [0.6, 2.0]])
    particles = rng.standard_normal((n, d)) @ np.linalg.cholesky(cov).T
    weights = np.full(n, 1.0 / n)
    evidence = ArmEvidence(model, ("plain", arm), n=n, particles=n)
    evidence.observe(1, particles, weights, np.zeros(d), np.random.default_rng(seed + 1))
    copies = evidence.copies
    return particles, weights, copies["plain"], copies[arm]


def test_the_roughening_arm_adds_the_documented_variance():
    n, d = 4000, 2
    particles, weights, plain, rough = _evidence_after_one_step("roughening", n, d)
    added = rough - plain
    sigma = jitter.ROUGHENING_K * np.ptp(plain, axis=0) * n ** (-1.0 / d)
    var = added.var(axis=0)
    se = sigma ** 2 * math.sqrt(2.0 / (n - 1))  # SE of a normal sample variance
    assert np.all(np.abs(var - sigma ** 2) < 4 * se)
    assert abs(np.corrcoef(added.T)[0, 1]) < 4 / math.sqrt(n)  # independent components


def test_the_regularised_arm_adds_the_documented_covariance():
    n, d = 4000, 2
    particles, weights, plain, moved = _evidence_after_one_step("regularised", n, d)
    added = moved - plain
    mean = weights @ particles
    centred = particles - mean
    expected = jitter.bandwidth(n, d) ** 2 * (centred * weights[:, None]).T @ centred
    got = np.cov(added.T)
    for i in range(d):
        for j in range(d):  # Var of a sample covariance: (s_ii s_jj + s_ij^2) / (n - 1)
            se = math.sqrt((expected[i, i] * expected[j, j] + expected[i, j] ** 2) / (n - 1))
            assert abs(got[i, j] - expected[i, j]) < 4 * se, (i, j)


def test_the_jitter_arms_use_the_entity_n_in_their_bandwidth():
    model = models.DriftModel(process_var=0.0, dim=1)
    rng = np.random.default_rng(3)
    particles, weights = rng.standard_normal((2000, 1)), np.full(2000, 1 / 2000)
    evidence = ArmEvidence(model, ("roughening",), n=100_000, particles=500)
    evidence.observe(1, particles, weights, np.zeros(1), np.random.default_rng(4))
    copies = evidence.copies
    assert copies["plain"].shape == (500, 1)  # M copies of N
    added = copies["roughening"] - copies["plain"]
    sigma = jitter.ROUGHENING_K * float(np.ptp(copies["plain"])) * 100_000 ** -1.0
    assert added.std() == pytest.approx(sigma, rel=4 * math.sqrt(1 / (2 * 499)))


def test_the_dt_arm_moves_the_copy_by_the_rules_with_its_own_random_numbers():
    """The DT arm's copy is the information layer's rules on the same weighted set, resampled by the same points."""
    from dtpf.entity import resampling
    from dtpf.information import rules

    model = models.DriftModel(process_var=0.0, dim=1)
    rng = np.random.default_rng(8)
    particles = rng.standard_normal((400, 1))
    weights = np.exp(-0.5 * (particles[:, 0] / 0.3) ** 2)
    weights /= weights.sum()
    evidence = ArmEvidence(model, ("dt-paper",), n=400, particles=400)
    draws = np.random.default_rng(9)
    evidence.observe(1, particles, weights, np.zeros(1), draws)
    copies = evidence.copies
    replay = np.random.default_rng(9)
    points = (replay.random() + np.arange(400)) / 400
    plain = particles[resampling.inverse_cdf(points, weights)]
    moved = rules.preprocess(particles, weights, 0.81, replay, move_rule="paper")
    assert np.array_equal(copies["plain"], plain)
    assert np.array_equal(copies["dt-paper"], moved.particles[resampling.inverse_cdf(points, moved.weights)])
    assert not np.array_equal(copies["dt-paper"], plain)


def test_the_policy_switches_only_on_strong_evidence_and_back_when_it_fades():
    from dtpf.system.predict import Forecast

    policy = ChoosePS(base="plain")

    def decide(step, **evidence):
        forecast = Forecast(step, 100, 1.0, 0.0, 1.0, arm_evidence={"plain": 0.0, "dt-relative": 0.0, "dt-paper": 0.0,
                                                                    "roughening": 0.0, "regularised": 0.0, **evidence},
                            evidence_steps=20)
        return policy.decide(step, forecast)

    assert decide(1, regularised=math.log(99) - 0.01).arm == "plain"
    chosen = decide(2, regularised=math.log(99) + 0.01)
    assert (chosen.arm, chosen.applies_from_step, chosen.preprocess) == ("regularised", 3, False)
    assert decide(3, regularised=2.0).arm == "regularised"        # hysteresis: above log 3 it stays
    assert decide(4, regularised=2.0, roughening=6.0).arm == "regularised"  # 4 nats better: not enough
    assert decide(5, regularised=2.0, roughening=7.0).arm == "roughening"
    back = decide(6, roughening=1.0)
    assert back.arm == "plain" and "faded" in back.reason
    dt = decide(7, **{"dt-paper": 9.0})
    assert (dt.arm, dt.ps, dt.preprocess) == ("dt-paper", 0.81, True)
    assert dt.command_fields()["arm"] == "dt-paper" and dt.command_fields()["evidence"] == 9.0
    with pytest.raises(ValueError):
        ChoosePS(arms=("plain", "teleport"))
    with pytest.raises(ValueError):
        ChoosePS(enter=1.0, leave=2.0)


def test_a_base_arm_is_in_force_without_evidence_and_the_others_are_scored_against_it():
    """ChoosePS(base=...): the thresholds hold against the base arm's copy (the sums are against plain's)."""
    from dtpf.system.predict import Forecast

    policy = ChoosePS()  # the default base: roughening, entered from by odds of 999 to 1
    assert (policy.base, policy.arm, policy.initial_ps, policy.enter) == ("roughening", "roughening", 0.0,
                                                                          math.log(999.0))
    assert ChoosePS(base="plain").enter == math.log(99.0)

    def decide(step, evidence, points=None):
        zero = dict.fromkeys(("plain", "dt-relative", "dt-paper", "roughening", "regularised"), 0.0)
        forecast = Forecast(step, 100, 1.0, 0.0, 1.0, arm_evidence={**zero, **evidence},
                            arm_point_evidence={**zero, **(points or {})}, evidence_steps=20)
        return policy.decide(step, forecast)

    # 10 nats above plain, but only 2 above the base: roughening stays.
    kept = decide(1, {"roughening": 8.0, "regularised": 10.0})
    assert kept.arm == "roughening" and "against roughening" in kept.reason
    assert decide(2, {"roughening": 8.0, "regularised": 8.0 + math.log(999) - 0.01}).arm == "roughening"
    assert decide(2, {"roughening": 8.0, "regularised": 8.0 + math.log(999) + 0.01}).arm == "regularised"
    faded = decide(3, {"roughening": 8.0, "regularised": 8.0})
    assert faded.arm == "roughening" and "faded" in faded.reason
    # Plain is an arm like the others: it is entered when it beats the base, and stays while it does.
    worse = dict.fromkeys(("roughening", "regularised", "dt-relative", "dt-paper"), -10.0)
    assert decide(4, worse).arm == "plain"
    assert decide(5, {**worse, "regularised": -9.0}).arm == "plain"
    assert decide(6, {}).arm == "roughening"
    # The veto is against the base's predicted means too.
    assert decide(7, {"regularised": 50.0}, {"roughening": 5.0, "regularised": 4.0}).arm == "roughening"
    with pytest.raises(ValueError, match="unknown arm 'teleport'"):
        ChoosePS(base="teleport")


def test_an_arm_whose_estimate_predicts_worse_is_not_entered_and_is_left():
    """The point-estimate veto: strong predictive evidence is not enough when the arm's predicted means
    predict the observations worse than plain's (or than the arm in force's)."""
    from dtpf.system.predict import Forecast

    def decide(policy, step, evidence, points):
        zero = dict.fromkeys(("plain", "dt-relative", "dt-paper", "roughening", "regularised"), 0.0)
        forecast = Forecast(step, 100, 1.0, 0.0, 1.0, arm_evidence={**zero, **evidence},
                            arm_point_evidence={**zero, **points}, evidence_steps=20)
        return policy.decide(step, forecast)

    policy = ChoosePS(base="plain")
    assert decide(policy, 1, {"dt-paper": 1000.0}, {"dt-paper": -0.01}).arm == "plain"
    assert decide(policy, 2, {"dt-paper": 1000.0, "dt-relative": 600.0},
                  {"dt-paper": -200.0, "dt-relative": 600.0}).arm == "dt-relative"
    # From the arm in force, another arm with more predictive evidence but a worse estimate is not taken.
    assert decide(policy, 3, {"dt-paper": 1000.0, "dt-relative": 600.0},
                  {"dt-paper": 30.0, "dt-relative": 600.0}).arm == "dt-relative"
    # The arm in force is left once its estimate predicts worse than plain's by more than leave (log 3).
    left = decide(policy, 4, {"dt-relative": 600.0}, {"dt-relative": -math.log(3.0) - 0.01})
    assert left.arm == "plain" and "predicts worse than plain's" in left.reason
    assert decide(policy, 5, {"roughening": 9.0}, {"roughening": 0.0}).arm == "roughening"
    assert decide(policy, 6, {"roughening": 9.0}, {"roughening": -math.log(3.0) + 0.01}).arm == "roughening"
    # Without the veto, the predictive evidence alone decides.
    assert decide(ChoosePS(base="plain", veto=False), 1, {"dt-paper": 1000.0}, {"dt-paper": -200.0}).arm == "dt-paper"


def test_an_arm_is_entered_only_on_steady_evidence_not_on_a_lucky_sum():
    """The same sum (6 nats > log 99) from twenty steady differences enters; from a noisy walk, it does not."""
    from dtpf.system.predict import Forecast

    def decide(policy, differences):
        steps = tuple({"plain": 0.0, "roughening": d} for d in differences)
        forecast = Forecast(1, 100, 1.0, 0.0, 1.0, arm_evidence={"plain": 0.0, "roughening": float(sum(differences))},
                            arm_differences=steps, evidence_steps=len(steps))
        return policy.decide(1, forecast)

    steady = [0.3] * 20                                          # mean 0.3, SE ~0: far above 2 SE
    noisy = [3.6, -3.0] * 10                                     # sum 6, mean 0.3, SE 0.74: 0.4 SE
    assert decide(ChoosePS(base="plain"), steady).arm == "roughening"
    refused = decide(ChoosePS(base="plain"), noisy)
    assert refused.arm == "plain" and "steadily" in refused.reason
    assert decide(ChoosePS(base="plain", steady=0.0), noisy).arm == "roughening"  # the sum alone
    assert decide(ChoosePS(base="plain"), [6.0]).arm == "plain"   # one difference has no spread to judge


def test_the_point_evidence_scores_the_copies_predicted_means():
    """e_a(k) of ArmEvidence: log p(z | mean of the copy) minus plain's, as the model's likelihood gives it."""
    from dtpf.system.choose import point_log_likelihood

    model = models.DriftModel(process_var=0.0, dim=1, observation_var=0.25)
    particles = np.array([[1.0], [3.0]])
    z = np.array([1.5])
    expected = float(model.log_likelihood(np.array([[2.0]]), z, 1)[0])
    assert point_log_likelihood(model, particles, z, 1) == pytest.approx(expected)
    assert point_log_likelihood(model, np.array([[np.nan]]), z, 1) == -np.inf
    rng = np.random.default_rng(3)
    particles = rng.normal(0.0, 1.0, (200, 1))
    evidence = ArmEvidence(model, ("roughening",), n=200, particles=200)
    evidence.observe(1, particles, np.full(200, 1 / 200), np.zeros(1), np.random.default_rng(4))
    copies = {name: x.copy() for name, x in evidence.copies.items()}
    evidence.observe(2, particles, np.full(200, 1 / 200), z, np.random.default_rng(5))
    plain = point_log_likelihood(model, copies["plain"], z, 2)
    rough = point_log_likelihood(model, copies["roughening"], z, 2)
    assert evidence.point_totals() == pytest.approx({"plain": 0.0, "roughening": rough - plain})
    assert rough != plain


def test_a_decision_message_must_name_a_known_arm_and_fit_it():
    from types import SimpleNamespace

    from dtpf.information.service import PSInbox

    base = dict(twin_id="t", run_id="r", step=3, applies_from_step=4, policy="choose", reason="")
    assert PSCommand(**base, ps=0.81, preprocess=True, arm="dt-paper").arm == "dt-paper"
    with pytest.raises(ValueError):
        PSCommand(**base, ps=0.0, arm="teleport")
    from dtpf.information.layer import arms_for

    inbox = PSInbox.__new__(PSInbox)
    inbox.policy = "choose"
    inbox.layer = SimpleNamespace(arms=arms_for("none"))
    assert inbox.problem(PSCommand(**base, ps=0.81, preprocess=True, arm="dt-paper")) is None
    assert "a run without a move of its own" in inbox.problem(PSCommand(**base, ps=0.0, arm="own"))
    inbox.layer = SimpleNamespace(arms=arms_for("my.py:shake"))
    assert inbox.problem(PSCommand(**base, ps=0.0, preprocess=False, arm="own")) is None
    assert "the arm's" in inbox.problem(PSCommand(**base, ps=0.3, preprocess=True, arm="dt-paper"))
    assert "names an arm" in inbox.problem(PSCommand(**base, ps=0.0))
    inbox.policy = "fixed"
    assert "from a run whose policy is fixed" in inbox.problem(PSCommand(**base, ps=0.0, preprocess=False, arm="plain"))
    del SimpleNamespace


def test_the_switching_scenario_drops_its_sensor_noise_and_its_kalman_filter_is_exact():
    model = models.get("switching")
    truth, z = model.simulate(100, np.random.default_rng(0))
    residual = z - truth
    assert 0.7 < residual[:50].std() < 1.3 and residual[50:].std() < 0.02
    means = model.kalman(z)
    assert np.mean((means[60:] - truth[60:]) ** 2) < 1e-3
    assert RunConfig(scenario="switching", policy="choose").scenario == "switching"


def test_the_moving_scenario_leaves_the_origin_at_its_velocity_and_its_kalman_filter_is_exact():
    model = models.get("moving")
    truth, z = model.simulate(100, np.random.default_rng(0))
    steps = np.diff(truth[:, 0])
    assert abs(steps.mean() - model.velocity) < 4 * 0.001 / np.sqrt(99) and (z - truth).std() < 0.02
    assert truth[-1, 0] - truth[0, 0] == pytest.approx(99 * model.velocity, abs=0.05)
    means = model.kalman(z)
    assert np.mean((means[10:] - truth[10:]) ** 2) < 1e-4  # the exact filter: within the sensor's variance
    moved = model.propagate(np.zeros((4, 1)), 2, np.random.default_rng(1))
    assert np.all(np.abs(moved - model.velocity) < 0.01)
    assert RunConfig(scenario="moving", policy="choose").scenario == "moving"


def test_the_quick_evaluation_prints_every_variant_and_a_verdict_per_cell(capsys):
    """``python -m dtpf.scripts.paper.evaluate_chooser --quick`` on two cells, in one process."""
    from dtpf.scripts.paper import evaluate_chooser

    assert evaluate_chooser.main(["--quick", "--workers", "1"]) == 0
    out = capsys.readouterr().out
    for scenario in evaluate_chooser.SCENARIOS:
        block = out.split(f"**{scenario}, N = 50**")[1].split("**")[0]
        rows = {line.split("|")[1].strip().split(" (")[0]: line for line in block.splitlines() if line.startswith("| ")}
        assert set(evaluate_chooser.VARIANTS) <= set(rows), scenario
        for chooser in evaluate_chooser.CHOOSERS:
            assert f"- {scenario}, N = 50: {chooser} " in out
    assert "every target met by choose: " in out and "every target met by choose, plain base: " in out


def test_the_dtpf_compare_command_the_evaluation_prints_gives_every_run_s_error(tmp_path, capsys):
    """The variants are dtpf compare's: the command printed for a cell (drift+100, the model reference of
    evaluate_guard) runs each of them on each seed to the error the evaluation's CSV holds, to the last digit."""
    import shlex
    import subprocess
    import sys

    from conftest import ROOT
    from dtpf.scripts.compare_csv import CompareCsv
    from dtpf.scripts.paper import evaluate_chooser as ev

    path = tmp_path / "chooser.csv"
    assert ev.main(["--cells", "drift+100:20", "--seeds", "2", "--steps", "6", "--workers", "1", "--csv",
                    str(path)]) == 0
    out = capsys.readouterr().out
    command = out.split("\n\n    dtpf compare ")[1].split("\n\n")[0]
    assert command.startswith("--model dtpf.scripts.paper.evaluate_guard:DRIFT_PLUS_100 -n 20 -T 6 --twin choose-1 "
                              "--seeds 2 ")
    table = tmp_path / "compare.csv"
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "compare", *shlex.split(command.replace(
        "\\\n", " ")), "--workers", "1", "--csv", str(table)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    direct = {(label, seed): row.value for (_, label, seed), row in CompareCsv(table).read()[0].items()}
    with open(path, newline="") as handle:
        held = {(row["variant"], int(row["seed"])): float(row["error"]) for row in csv.DictReader(handle)
                if row["variant"] in ev.COMPARE_LABELS}
    assert len(direct) == 2 * len(ev.COMPARE_LABELS) and direct == held


def test_the_hindsight_reference_takes_per_seed_the_arm_whose_run_was_likeliest(tmp_path):
    """The hindsight row: per seed the error of the arm whose fixed filter had the highest summed log
    predictive; its share of seeds in the row's name; the sums go through the CSV and back; a run
    without them (an older CSV) has no such row."""
    from dtpf.scripts.paper import evaluate_chooser as ev

    arms = list(ev.ARM_VARIANTS)
    by_seed = {}
    for seed in range(4):
        picked = arms[seed % 2 + 3]  # roughening on even seeds, regularised on odd ones
        by_seed[seed] = {label: dict(error=10.0 + seed + i, ms=0.1, evidence=(0.0 if label == picked else -5.0 - i))
                         for i, label in enumerate([*ev.VARIANTS])}
    errors, share = ev.hindsight(by_seed)
    assert errors == {s: by_seed[s][arms[s % 2 + 3]]["error"] for s in range(4)}
    assert share == {"plain": 0.0, "dt-relative": 0.0, "dt-paper": 0.0, "roughening": 0.5, "regularised": 0.5}
    rows = {row["variant"]: row for row in ev.cell_rows(by_seed)}
    expected = np.mean([errors[s] - by_seed[s]["systematic"]["error"] for s in range(4)])
    assert rows[ev.HINDSIGHT]["vs_systematic"] == pytest.approx(expected)
    assert "(roughening 50%, regularised 50% of runs; not causal)" in ev.table("ungm", 100, 4, list(rows.values()))
    path = tmp_path / "runs.csv"
    with open(path, "w", newline="") as handle:
        csv.writer(handle).writerows([ev.CSV_FIELDS, *([
            "ungm", 100, s, label, f["error"], f["ms"], "", f["evidence"]]
            for s, runs in by_seed.items() for label, f in runs.items())])
    assert ev.hindsight(ev.read_csv(path)[("ungm", 100)]) == (errors, share)
    del by_seed[0]["regularised"]["evidence"]
    assert ev.hindsight(by_seed) is None and ev.HINDSIGHT not in {r["variant"] for r in ev.cell_rows(by_seed)}


def test_the_verdict_gives_the_share_of_the_gap_with_its_interval_and_the_paired_test_against_80_percent():
    """The share of the best fixed method's gap a chooser closes, with its 95% (Fieller) interval: the shares r
    whose paired difference (chooser - systematic) - r (best - systematic) has an interval that holds 0; 80% is
    told apart exactly when that difference at r = 0.8 has an interval without 0."""
    from dtpf.scripts.compare_stats import mean_interval
    from dtpf.scripts.paper import evaluate_chooser as ev

    rng = np.random.default_rng(7)
    gap = -1.0 + rng.normal(0.0, 2.0, 400)              # the best fixed method against systematic, per seed
    closed = 0.5 * gap + rng.normal(0.0, 1.0, 400)      # a chooser that closes about half of it
    low, high = ev.share_interval(closed, gap)
    assert low < closed.mean() / gap.mean() < high
    for r in (low, high):                               # the ends: the paired test at r exactly at its edge
        d, h = mean_interval(closed - r * gap, ev.Z95)
        assert abs(d) == pytest.approx(h, rel=1e-9)
    inside = ev.share_interval(gap + rng.normal(0.0, 0.01, 400), gap)
    assert inside[0] < 1.0 < inside[1] and inside[1] - inside[0] < 0.05
    assert ev.share_interval(closed, rng.normal(0.0, 2.0, 400) + 0.01) == (-math.inf, math.inf)  # no gap to share
    rows = [dict(variant="systematic", significant=0, vs_systematic=0.0, vs_systematic_ci=0.0,
                 per_seed=np.zeros(400)),
            dict(variant="regularised", significant=-1, vs_systematic=float(gap.mean()), vs_systematic_ci=0.2,
                 per_seed=gap),
            dict(variant=ev.CHOOSE, significant=-1, vs_systematic=float(closed.mean()), vs_systematic_ci=0.1,
                 per_seed=closed)]
    words, met = ev.verdict("ungm", 100, rows)
    d, h = mean_interval(closed - 0.8 * gap, ev.Z95)
    assert not met["80% of the gap"] and f"The share's 95% interval: {100 * low:.0f}% to {100 * high:.0f}%" in words
    assert f"{ev._num(d)} ± {ev._num(h)}, 80% outside the interval" in words and high < 0.8
    rows[2]["per_seed"] = 0.8 * gap + rng.normal(0.0, 1.0, 400)
    assert "80% inside the interval: not told apart" in ev.verdict("ungm", 100, rows)[0]


def test_resuming_a_csv_written_before_the_likelihood_column_gives_it_today_s_header(tmp_path, capsys):
    """A file without the ``evidence`` column is rewritten with today's header before rows are appended, so
    every row sits under its own fields; a CSV of something else is a one-line error."""
    from dtpf.scripts.paper import evaluate_chooser as ev

    path = tmp_path / "old.csv"
    old_fields = ev.CSV_FIELDS[:-1]
    with open(path, "w", newline="") as handle:
        csv.writer(handle).writerows([old_fields, ["drift", 20, 0, "systematic", 0.5, 0.1, ""]])
    assert ev.main(["--csv", str(path), "--resume", "--cells", "drift:20", "--seeds", "2", "--steps", "4",
                    "--workers", "1"]) == 0
    rows = list(csv.DictReader(path.open(newline="")))
    assert tuple(rows[0]) == ev.CSV_FIELDS
    assert rows[0]["variant"] == "systematic" and rows[0]["error"] == "0.5" and rows[0]["evidence"] == ""
    assert all(r["evidence"] not in ("", None) for r in rows[1:] if r["variant"] in ev.ARM_VARIANTS)
    assert {r["seed"] for r in rows[1:]} == {"0", "1"}
    capsys.readouterr()
    other = tmp_path / "other.csv"
    other.write_text("a,b\n1,2\n")
    with pytest.raises(SystemExit) as stop:
        ev.main(["--csv", str(other), "--resume", "--cells", "drift:20", "--seeds", "2"])
    assert stop.value.code == 2 and "not a CSV of this evaluation" in capsys.readouterr().err


def test_an_arm_from_step_j_is_in_force_from_j_on_and_the_base_before_without_evidence(monkeypatch, capsys):
    """``--from-step 4 --from-arms regularised``: roughening's filter number for number up to step 4 (the
    arm of step k is the decision of step k - 1), regularised from the decision of step 3 on, no copies run."""
    from dtpf.scripts.paper import evaluate_chooser as ev

    monkeypatch.setattr(ev, "VARIANTS", dict(ev.VARIANTS))
    monkeypatch.setattr(ev, "FROM_STEP", {})
    label = ev.add_from_step("regularised", 4)
    assert label == "regularised from step 4" and ev.FROM_STEP[label] == ("regularised", 4)
    task = ev.Task("range-bearing", 60, 5, 12)
    options, model = ev.scenario_model("range-bearing")
    _, z = simulate(ev.task_config(task, options), model)
    pf = ev.build_variant(task, label, model, options, z)
    steps = list(pf)
    rough = list(ev.build_variant(task, "roughening", model, options, z))
    assert [d.arm for d in pf.preprocessor.system.decisions] == ["roughening"] * 2 + ["regularised"] * 10
    assert not pf.preprocessor.system.needs_particles and not pf.preprocessor.system.forecasts[-1].arm_evidence
    assert all(np.array_equal(a.mean, b.mean) for a, b in zip(steps[:4], rough[:4]))
    assert not np.array_equal(steps[4].mean, rough[4].mean)
    with pytest.raises(SystemExit) as stop:
        ev.main(["--from-step", "1"])
    assert stop.value.code == 2 and "--from-step: an arm of" in capsys.readouterr().err


def test_a_tuned_chooser_runs_with_its_setting_and_equals_the_chooser_at_the_default(monkeypatch, capsys):
    """``--tune window=20`` (the default) runs the chooser number for number; ``--tune window=5`` runs it
    with that window; a setting ChoosePS does not have, or refuses, is a one-line error."""
    from dtpf.scripts.paper import evaluate_chooser as ev

    for name in ("VARIANTS", "CHOOSERS", "TUNED"):
        monkeypatch.setattr(ev, name, dict(getattr(ev, name)))
    same, short = ev.add_tuned("window=20"), ev.add_tuned("window=5")
    assert (same, short) == ("choose, window 20", "choose, window 5") and ev.CHOOSERS[short] == "roughening"
    task = ev.Task("drift", 50, 2, 30)
    options, model = ev.scenario_model("drift")
    _, z = simulate(ev.task_config(task, options), model)
    runs = {}
    for label in (ev.CHOOSE, same, short):
        pf = ev.build_variant(task, label, model, options, z)
        runs[label] = [s.mean for s in pf]
        assert pf.preprocessor.system.predictor.evidence.window == (5 if label == short else 20)
    np.testing.assert_array_equal(runs[same], runs[ev.CHOOSE])
    for bad, words in (("windows=3", "KEY=VALUE with KEY one of"), ("steady=x", "steady takes a number"),
                       ("window=0", "window and particles must be at least 1")):
        with pytest.raises(SystemExit) as stop:
            ev.main(["--tune", bad])
        assert stop.value.code == 2 and words in capsys.readouterr().err, bad


def test_the_evaluation_runs_the_chooser_on_other_bases_with_their_verdicts(capsys, monkeypatch):
    """``--bases regularised`` adds the chooser on that base (``--choose-base regularised``) as a variant of
    its own, with a verdict per cell; an arm that does not exist is one line."""
    from dtpf.scripts.paper import evaluate_chooser

    monkeypatch.setattr(evaluate_chooser, "VARIANTS", dict(evaluate_chooser.VARIANTS))
    monkeypatch.setattr(evaluate_chooser, "CHOOSERS", dict(evaluate_chooser.CHOOSERS))
    assert evaluate_chooser.main(["--cells", "range-bearing:30", "--seeds", "2", "--steps", "8", "--workers", "1",
                                  "--bases", "regularised", "roughening"]) == 0
    out = capsys.readouterr().out
    assert evaluate_chooser.VARIANTS["choose, regularised base"].fields == dict(policy="choose", choose_base="regularised")
    assert evaluate_chooser.CHOOSERS["choose, regularised base"] == "regularised"
    assert "| choose, regularised base (not regularised at " in out
    assert "- range-bearing, N = 30: choose, regularised base " in out
    assert "every target met by choose, regularised base: " in out
    assert out.count("- range-bearing, N = 30: choose ") == 1  # roughening is the default chooser's own base
    with pytest.raises(SystemExit) as stop:
        evaluate_chooser.main(["--bases", "kalman"])
    assert stop.value.code == 2 and "--bases: unknown arm 'kalman'" in capsys.readouterr().err


# --- over Zenoh, in the log, through dtpf verify ----------------------------------


@pytest.fixture(scope="module")
def chosen_log(tmp_path_factory):
    from dtpf.scripts.launch import launch
    path = tmp_path_factory.mktemp("choose") / "choose.mcap"
    result = launch(CHOSEN, log_path=path, timeout=5.0)
    assert result.exit_codes["entity"] == 0
    return result, path


def test_the_decision_travels_over_zenoh_is_recorded_equals_the_inprocess_run_and_verifies(chosen_log):
    from dtpf.messages.codec import decode_for_key
    from dtpf.messages.models import Estimate, ParticleSet
    from dtpf.recording.logfile import read_log
    from dtpf.scripts.inprocess import run
    from dtpf.scripts.logs.verify import verify

    _, path = chosen_log
    log = read_log(path)
    messages = [(m.topic, decode_for_key(m.topic, m.data)) for m in log.messages]
    commands = {m.step: m for _, m in messages if isinstance(m, PSCommand)}
    preprocessed = {m.step: m for topic, m in messages
                    if isinstance(m, ParticleSet) and topic.endswith("information/preprocessed")}
    estimates = {m.step: m for _, m in messages if isinstance(m, Estimate)}
    reference = run(CHOSEN)
    assert sorted(commands) == list(range(1, CHOSEN.steps + 1))
    assert [commands[k].arm for k in sorted(commands)] == [d.arm for d in build_decisions()]
    for k in range(2, CHOSEN.steps + 1):
        arm = ARMS[commands[k - 1].arm]
        assert preprocessed[k].jitter == arm.jitter
    for k, step in enumerate(reference.steps, 1):
        assert estimates[k].mean == [float(v) for v in step.mean]
    result = verify(log)
    assert result.ok and len(result.checked) == CHOSEN.steps


def build_decisions():
    model = models.get("drift")
    _, z = simulate(CHOSEN, model)
    pf = build(CHOSEN, z, model)
    list(pf)
    return pf.preprocessor.decisions


def test_verify_notices_a_flipped_arm(chosen_log, tmp_path):
    from dtpf.recording.logfile import read_log
    from dtpf.scripts.logs.verify import verify

    from conftest import altered_log

    _, path = chosen_log
    arms = [d.arm for d in build_decisions()]
    step = arms.index("regularised") + 1
    flipped = altered_log(path, tmp_path / "flipped.mcap", "system/ps", step, lambda m: {"arm": "plain"})
    mismatch = verify(read_log(flipped)).mismatch
    assert (mismatch.step, mismatch.field) == (step, "arm")
    moved = altered_log(path, tmp_path / "moved.mcap", "information/preprocessed", step + 1,
                        lambda m: {"jitter": "roughening"})
    mismatch = verify(read_log(moved)).mismatch
    assert (mismatch.step, mismatch.field) == (step + 1, "jitter")


def test_rerunning_a_variant_in_some_cells_keeps_its_rows_in_the_others(tmp_path):
    from dtpf.scripts.paper import evaluate_chooser

    path = tmp_path / "runs.csv"
    path.write_text("scenario,particles,seed,variant,error,ms,off_plain,evidence\n"
                    "ungm,100,0,choose,1.0,0.1,0.0,-3\nungm,100,0,systematic,2.0,0.1,,-4\n"
                    "drift,100,0,choose,3.0,0.1,0.0,-5\nungm,1000,0,choose,4.0,0.1,0.0,-6\n")
    evaluate_chooser._drop_variants(path, {"choose"}, [("ungm", 100)])
    kept = [line.split(",")[:4] for line in path.read_text().splitlines()[1:]]
    assert kept == [["ungm", "100", "0", "systematic"], ["drift", "100", "0", "choose"], ["ungm", "1000", "0", "choose"]]
    evaluate_chooser._drop_variants(path, {"choose"})
    assert [line.split(",")[3] for line in path.read_text().splitlines()[1:]] == ["systematic"]
