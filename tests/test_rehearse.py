"""The rehearsal (``--choose-base rehearse``): every arm on simulated runs of the model, the best becomes the base."""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import re

import numpy as np
import pytest

from dtpf.entity import models
from dtpf.entity.base import StateSpaceModel
from dtpf.information.layer import ARMS
from dtpf.messages import names
from dtpf.messages.config import RunConfig
from dtpf.scripts.inprocess import build, simulate
from dtpf.scripts.paper.evaluate_guard import DRIFT_PLUS_100
from dtpf.system import rehearse
from dtpf.system.choose import ArmEvidence
from dtpf.system.layer import SystemLayer

FIVE = tuple(ARMS)  # plain, the two DT rules, roughening, the regularised kernel
#: drift+100 through its model reference: the constant 100 away from the origin, where the paper's rule errs.
SHIFTED = dict(model="dtpf.scripts.paper.evaluate_guard:DRIFT_PLUS_100")


@pytest.fixture
def few_runs(monkeypatch):
    """At most 60 simulated runs per rehearsal, looked at once, and nothing kept from another test."""
    monkeypatch.setattr(rehearse, "MOST", 60)
    monkeypatch.setattr(rehearse, "FEWEST", 60)
    monkeypatch.setattr(rehearse, "_CACHE", {})


def test_the_best_arm_on_the_model_becomes_the_base_and_the_paper_rule_is_measured_worse():
    """drift+100: the relative rule's estimate is better than roughening's by more than 2.5 standard errors
    and best of all; the paper's rule, which moves particles by their distance from the origin, is worse."""
    result = rehearse.rehearse(DRIFT_PLUS_100, FIVE, n=100, steps=20, runs=60)
    z = {arm: mean / se for arm, (mean, se) in result.differences.items() if se > 0}
    assert result.arm == "dt-relative" and result.against == "roughening"
    assert z["dt-relative"] < -rehearse.Z
    assert z["dt-paper"] > 3
    assert result.errors["dt-relative"] == min(result.errors.values())
    assert (result.runs, result.steps, result.particles) == (60, 20, 100)
    assert "base dt-relative" in result.summary() and "dt-paper +" in result.summary()


def test_no_arm_significantly_better_leaves_the_default_base():
    """ungm over 20 steps: no arm's error differs from roughening's by 2.5 standard errors; roughening stays."""
    result = rehearse.rehearse(models.get("ungm"), FIVE, n=100, steps=20, runs=60)
    assert result.arm == "roughening"
    assert all(abs(mean) <= rehearse.Z * se for arm, (mean, se) in result.differences.items() if arm != "roughening")


def test_an_arm_that_moves_like_the_base_is_never_chosen(few_runs, tmp_path):
    """The run's own move as an arm, roughening again: with common random numbers every difference is 0."""
    (tmp_path / "same.py").write_text("from dtpf.entity import jitter\n\n\ndef same(resampled, particles, weights, rng):\n"
                                      "    return jitter.apply('roughening', resampled, particles, weights, rng, "
                                      "n=len(weights))\n")
    result = rehearse.rehearse(DRIFT_PLUS_100, ("plain", "roughening", names.OWN_ARM), n=50, steps=10,
                               move=f"{tmp_path / 'same.py'}:same")
    assert result.differences[names.OWN_ARM] == (0.0, 0.0) and result.arm in ("plain", "roughening")


def test_the_rehearsal_depends_on_the_model_n_and_steps_and_not_on_the_run_seed(few_runs):
    configs = [RunConfig(**SHIFTED, policy="choose", choose_base="rehearse", particles=60, steps=15, seed=seed)
               for seed in (1, 2)]
    first, second = (SystemLayer.from_config(c, model=DRIFT_PLUS_100).policy for c in configs)
    assert first.rehearsal is second.rehearsal          # computed once in a process
    rehearse._CACHE.clear()
    again = SystemLayer.from_config(configs[0], model=DRIFT_PLUS_100).policy.rehearsal
    assert again is not first.rehearsal and again == first.rehearsal   # the same numbers when computed again
    longer = RunConfig(**SHIFTED, policy="choose", choose_base="rehearse", particles=60, steps=25, seed=1)
    assert SystemLayer.from_config(longer, model=DRIFT_PLUS_100).policy.rehearsal.steps == 25
    assert rehearse.rehearse(DRIFT_PLUS_100, FIVE, n=60, steps=None, runs=2).steps == rehearse.STEPS


def test_the_layers_start_on_the_default_base_and_the_first_decision_puts_the_rehearsed_one_in_force(few_runs):
    config = RunConfig(**SHIFTED, policy="choose", choose_base="rehearse", particles=100, steps=20, seed=5)
    _, z = simulate(config, DRIFT_PLUS_100)
    pf = build(config, z, DRIFT_PLUS_100)
    policy = pf.preprocessor.system.policy
    assert (policy.initial_arm, policy.base) == ("roughening", policy.rehearsal.arm) == ("roughening", "dt-relative")
    steps = list(pf)
    decisions = pf.preprocessor.decisions
    assert decisions[0].arm == "dt-relative" and decisions[0].applies_from_step == 2
    assert decisions[0].reason.startswith("choose: rehearsal over 60 simulated runs of 20 steps")
    # The relative rule preprocesses from step 2 on (the decision of step 1), roughening runs at step 1.
    assert steps[0].report.n_processed == 0
    assert all(step.report.n_processed > 0 or step.report.n_large == config.particles for step in steps[1:])
    assert any(step.report.n_processed > 0 for step in steps[1:])


def test_arms_the_rehearsal_dropped_are_neither_copied_nor_entered(monkeypatch):
    """ungm at N = 50 over 20 steps, looks at 100 and 200 runs: the arms dropped as clearly worse than roughening
    leave the chooser's arms and its copies; plain stays, the reference every arm is scored against."""
    monkeypatch.setattr(rehearse, "FEWEST", 100)
    monkeypatch.setattr(rehearse, "MOST", 200)
    monkeypatch.setattr(rehearse, "_CACHE", {})
    config = RunConfig(scenario="ungm", policy="choose", choose_base="rehearse", particles=50, steps=20, seed=4)
    layer = SystemLayer.from_config(config)
    dropped = layer.policy.rehearsal.dropped
    assert dropped and not set(dropped) & set(layer.policy.arms) - {"plain"}
    assert set(layer.predictor.evidence.names) == set(layer.policy.arms)
    assert set(layer.policy.arms) | set(dropped) == set(FIVE)
    chosen = SystemLayer.from_config(config, policy_options={"arms": ("regularised",)}).policy.arms
    assert chosen == ("plain", "regularised", "roughening")      # arms named by the caller are kept as named


def test_a_model_that_cannot_draw_observations_keeps_the_default_base_and_says_why(caplog, monkeypatch):
    from dtpf.system import layer as system_layer

    monkeypatch.setattr(system_layer, "_SAID", set())
    config = RunConfig(scenario="video", policy="choose", choose_base="rehearse", particles=50, steps=5)
    with caplog.at_level(logging.WARNING):
        layer = SystemLayer.from_config(config)
    assert (layer.policy.base, layer.policy.rehearsal) == ("roughening", None)
    assert "model 'video' cannot draw observations" in caplog.text and "the base is roughening" in caplog.text


def test_why_not_names_what_a_rehearsal_cannot_simulate():
    class Driven(models.DriftModel):
        controls = ("v",)

    assert rehearse.why_not(models.get("ungm")) is None
    assert "driven or has several sensors" in rehearse.why_not(Driven())
    assert "cannot draw observations" in rehearse.why_not(models.get("video"))
    with pytest.raises(ValueError, match="choose_base rehearse: model 'video' cannot draw"):
        rehearse.rehearse(models.get("video"), FIVE, n=10, steps=5)
    with pytest.raises(ValueError, match="at least 2 runs"):
        rehearse.rehearse(DRIFT_PLUS_100, FIVE, n=10, steps=5, runs=1)


def test_keeping_the_estimates_changes_no_number_of_the_copies_and_a_dt_arm_s_is_after_its_move():
    model = DRIFT_PLUS_100
    truth, z = model.simulate(6, np.random.default_rng(3))
    runs = []
    for keep in (False, True):
        copies = ArmEvidence(model, FIVE, n=80, particles=80)
        if keep:
            copies.estimates = {}
        rng = np.random.default_rng(11)
        particles = model.initial_particles(80, np.random.default_rng(1))
        log_w = model.log_likelihood(particles, z[0], 1)
        weights = np.exp(log_w - log_w.max())
        weights /= weights.sum()
        scored = [copies.observe(k, particles, weights, z[k - 1], rng) for k in range(1, 7)]
        runs.append((scored, copies.copies, copies.estimates))
    (plain_scores, plain_copies, none), (kept_scores, kept_copies, estimates) = runs
    assert none is None and plain_scores == kept_scores
    assert all(np.array_equal(plain_copies[a], kept_copies[a]) for a in plain_copies)
    # Plain's estimate is its weighted mean; the paper's rule reports the set it moved, far from plain's.
    assert set(estimates) == set(copies.names)
    assert abs(estimates["dt-paper"][0] - estimates["plain"][0]) > 10 * abs(estimates["plain"][0] - truth[5, 0])


def test_the_configuration_and_the_command_line_take_rehearse_for_the_choosing_policy_only():
    from dtpf.messages.config import add_run_arguments, config_from_args
    import argparse

    assert names.REHEARSE in names.CHOOSE_BASES and names.REHEARSE not in names.ARMS
    assert RunConfig(policy="choose", choose_base="rehearse").choose_base == "rehearse"
    with pytest.raises(ValueError, match="a base arm \\(rehearse\\) is for policy 'choose'"):
        RunConfig(policy="fixed", choose_base="rehearse")
    parser = argparse.ArgumentParser()
    add_run_arguments(parser)
    args = parser.parse_args(["--policy", "choose", "--choose-base", "rehearse"])
    assert config_from_args(args).choose_base == "rehearse"
    assert "simulated runs of the model" in " ".join(parser.format_help().split())


def test_the_boundary_over_the_looks_errs_as_one_look_at_2_5_standard_errors():
    """An arm no better than the base crosses -Z at one of the looks 200, 400, 800, 1600 about as often as it
    would cross -2.5 at a single look (one-sided 0.62%: at most 2.5% over four arms). The paired mean after n runs
    is a random walk's sum over n: 200,000 such walks, the tolerance four binomial standard errors."""
    looks = np.array(rehearse.looks(1600))
    rng = np.random.default_rng(11)
    sums = np.cumsum(rng.standard_normal((200_000, looks.size)) * np.sqrt(np.diff(looks, prepend=0)), axis=1)
    crossed = float(np.mean((sums / np.sqrt(looks) < -rehearse.Z).any(axis=1)))
    single = 0.5 * math.erfc(2.5 / math.sqrt(2.0))
    assert abs(crossed - single) < 4 * math.sqrt(single * (1 - single) / 200_000)
    assert 4 * single <= 0.025


def test_a_launched_rehearsal_decides_as_the_inprocess_one_and_its_log_verifies(tmp_path):
    """Over Zenoh the system service rehearses before its first decision (runs of 15 steps here), and
    dtpf verify, rehearsing again, reproduces every decision."""
    from dtpf.recording.logfile import read_log
    from dtpf.scripts.launch import launch
    from dtpf.scripts.logs.verify import verify

    config = RunConfig(**SHIFTED, policy="choose", choose_base="rehearse", particles=60, steps=15, seed=2,
                       twin="t-rehearse")
    result = launch(config, log_path=tmp_path / "run.mcap", timeout=30.0)
    assert result.exit_codes["entity"] == 0
    log = read_log(tmp_path / "run.mcap")
    commands = {m.step: m for _, m in log.decoded(lambda topic: topic.endswith("/system/ps"))}
    assert sorted(commands) == list(range(1, 16))
    assert commands[1].arm == "dt-relative" and re.search("rehearsal over [0-9]+ simulated runs of 15 steps",
                                                          commands[1].reason)
    checked = verify(log)
    assert checked.ok and len(checked.checked) == 15


def test_the_looks_double_up_to_the_budget_and_a_clear_winner_stops_the_rehearsal_at_the_first():
    assert rehearse.looks(1600) == [200, 400, 800, 1600] and rehearse.looks(300) == [200, 300]
    assert rehearse.looks(60) == [60]
    assert (rehearse.most_runs(100, 100), rehearse.most_runs(1000, 100), rehearse.most_runs(10, 10)) == (1600, 200, 1600)
    result = rehearse.rehearse(DRIFT_PLUS_100, FIVE, n=60, steps=20)
    assert (result.arm, result.runs, result.most) == ("dt-relative", 200, 1600)


def test_an_arm_clearly_worse_than_the_base_is_dropped_at_a_look(monkeypatch):
    """ungm over 20 steps at N = 50, looks at 100 and 200 runs: arms worse than roughening by more than one
    standard error at the first look run no more; none passes, roughening stays."""
    monkeypatch.setattr(rehearse, "FEWEST", 100)
    monkeypatch.setattr(rehearse, "_CACHE", {})
    result = rehearse.rehearse(models.get("ungm"), FIVE, n=50, steps=20, runs=200)
    assert result.arm == "roughening" and result.dropped
    for arm in result.dropped:
        mean, se = result.differences[arm]
        assert mean > rehearse.DROP * se
    assert result.runs == 200 or set(result.dropped) == set(FIVE) - {"roughening"}


def test_an_entity_waits_for_a_rehearsing_system_layer_longer_than_its_startup_timeout():
    from dtpf.entity.service import startup_wait

    rehearsing = RunConfig(policy="choose", choose_base="rehearse")
    assert startup_wait(rehearsing, 20.0, {"information", "system"}) == 20.0 + names.REHEARSAL_WAIT
    assert startup_wait(rehearsing, 20.0, {"information"}) == 20.0          # not waiting for the system layer
    assert startup_wait(RunConfig(policy="choose"), 20.0, {"information", "system"}) == 20.0
    assert rehearsing.rehearses and not RunConfig(policy="choose", choose_base="regularised").rehearses


def test_equal_built_in_models_share_one_rehearsal_and_other_models_do_not(few_runs):
    first = rehearse.rehearse(models.DriftModel(prior_mean=100.0), FIVE, n=40, steps=8)
    assert rehearse.rehearse(models.DriftModel(prior_mean=100.0), FIVE, n=40, steps=8) is first
    assert rehearse.rehearse(models.DriftModel(prior_mean=50.0), FIVE, n=40, steps=8) is not first

    class Plain(StateSpaceModel):   # not a dataclass: told apart by the object
        name, dim, obs_dim = "plain-drift", 1, 1
        inner = models.DriftModel(prior_mean=100.0)

        def initial_particles(self, n, rng):
            return self.inner.initial_particles(n, rng)

        def propagate(self, particles, k, rng, noise=None):
            return self.inner.propagate(particles, k, rng, noise)

        def log_likelihood(self, particles, observation, k):
            return self.inner.log_likelihood(particles, observation, k)

        def sample_observation(self, states, k, rng):
            return self.inner.sample_observation(states, k, rng)

    one, two = Plain(), Plain()
    assert rehearse.rehearse(one, FIVE, n=40, steps=8) is rehearse.rehearse(one, FIVE, n=40, steps=8)
    assert rehearse.rehearse(two, FIVE, n=40, steps=8) is not rehearse.rehearse(one, FIVE, n=40, steps=8)


@pytest.fixture
def own_cache(monkeypatch, tmp_path, few_runs):
    """An empty rehearsal cache folder of this test's own, and nothing kept in the process."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache" / "dtpf" / "rehearsals"


def _no_runs(*args, **kwargs):
    raise AssertionError("rehearsed again: the kept rehearsal was not used")


def test_a_rehearsal_is_kept_on_disk_and_another_process_reads_it_instead_of_rehearsing(own_cache, monkeypatch):
    model = models.DriftModel(prior_mean=100.0)
    first = rehearse.rehearse(model, FIVE, n=40, steps=8)
    files = list(own_cache.iterdir())
    assert len(files) == 1 and files[0].suffix == ".json"
    rehearse._CACHE.clear()                                   # as a new process finds it
    monkeypatch.setattr(rehearse, "_one_run", _no_runs)
    again = rehearse.rehearse(models.DriftModel(prior_mean=100.0), FIVE, n=40, steps=8)
    assert again == first and again is not first
    # Another N, T, model or arms is another rehearsal: it is not read from that file.
    for changed in (dict(n=41, steps=8), dict(n=40, steps=9)):
        with pytest.raises(AssertionError, match="rehearsed again"):
            rehearse.rehearse(model, FIVE, **changed)
    with pytest.raises(AssertionError, match="rehearsed again"):
        rehearse.rehearse(models.DriftModel(prior_mean=50.0), FIVE, n=40, steps=8)
    with pytest.raises(AssertionError, match="rehearsed again"):
        rehearse.rehearse(model, FIVE[:3], n=40, steps=8)


@pytest.mark.parametrize("damage", ["cut short", "not json", "another format", "wrong kinds", "unknown arm",
                                    "an arm no run has", "too large", "deep nesting", "a folder"])
def test_a_damaged_rehearsal_file_is_not_used_and_is_written_again(own_cache, damage, caplog):
    model = models.DriftModel(prior_mean=100.0)
    first = rehearse.rehearse(model, FIVE, n=40, steps=8)
    (file,) = own_cache.iterdir()
    text = file.read_text()
    good = json.loads(text)
    if damage == "cut short":
        file.write_text(text[: len(text) // 2])
    elif damage == "not json":
        file.write_bytes(b"\xff\x00" * 50)
    elif damage == "another format":
        file.write_text(json.dumps({**good, "format": 99}))
    elif damage == "wrong kinds":
        file.write_text(json.dumps({**good, "rehearsal": {**good["rehearsal"], "runs": "many"}}))
    elif damage == "unknown arm":
        file.write_text(json.dumps({**good, "rehearsal": {**good["rehearsal"], "arm": "teleport"}}))
    elif damage == "an arm no run has":   # a well-formed file whose base is no arm at all
        rehearsal = good["rehearsal"]
        file.write_text(json.dumps({**good, "rehearsal": {**rehearsal, "arm": "teleport",
                                                          "errors": {**rehearsal["errors"], "teleport": 0.0}}}))
    elif damage == "too large":
        file.write_text(text + " " * (rehearse._LARGEST_FILE + 1))
    elif damage == "deep nesting":
        file.write_text("[" * 30_000 + "]" * 30_000)
    else:
        file.unlink()
        file.mkdir()
    rehearse._CACHE.clear()
    with caplog.at_level(logging.WARNING):
        again = rehearse.rehearse(model, FIVE, n=40, steps=8)
    assert again == first
    if damage not in ("too large", "a folder"):
        assert "not used" in caplog.text and file.name in caplog.text
    if damage != "a folder":
        assert json.loads(file.read_text()) == good        # written again, whole
    assert not list(own_cache.glob("*.part"))


def test_a_rehearsal_folder_that_cannot_be_written_is_logged_and_the_run_goes_on(monkeypatch, tmp_path, few_runs,
                                                                                caplog):
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))
    with caplog.at_level(logging.WARNING):
        result = rehearse.rehearse(models.DriftModel(prior_mean=100.0), FIVE, n=40, steps=8)
    assert result.arm in FIVE and "rehearsal not kept in" in caplog.text


def test_a_model_that_is_not_a_dataclass_is_rehearsed_once_a_process_and_not_kept_on_disk(own_cache):
    class Shifted:
        """drift+100 behind an object of its own (a user's model that is no dataclass)."""
        samples_observations = True

        def __init__(self):
            self.inner = models.DriftModel(prior_mean=100.0)

        def __getattr__(self, name):
            return getattr(self.__dict__["inner"], name)

    model = Shifted()
    first = rehearse.rehearse(model, FIVE, n=40, steps=8)
    assert rehearse.rehearse(model, FIVE, n=40, steps=8) is first
    assert first.arm == rehearse.rehearse(models.DriftModel(prior_mean=100.0), FIVE, n=40, steps=8).arm
    assert [file.suffix for file in own_cache.iterdir()] == [".json"]     # the dataclass's alone


@pytest.mark.parametrize("flags, policy, base", [
    ([], "choose", "rehearse"),
    (["--choose-base", "regularised"], "choose", "regularised"),
    (["--threshold", "neff", "--resampler", "stratified"], "choose", "rehearse"),
    (["--move", "roughening"], "fixed", None),
    (["--policy", "fixed"], "fixed", None),
    (["--ps", "0.81"], "fixed", None),
    (["--weight-rule", "inherit"], "fixed", None),
    (["--move-rule", "paper"], "fixed", None),
    (["--no-preprocess"], "fixed", None),
    (["--policy", "choose"], "choose", None),
])
def test_the_command_line_chooses_by_default_and_a_fixed_setting_keeps_the_papers_policy(flags, policy, base):
    """dtpf launch and dtpf run: the choosing policy on a rehearsed base unless the run names a policy or sets a
    setting of the fixed one; RunConfig itself (and dtpf compare's variants) keep the paper's fixed PS 0.81."""
    import argparse

    from dtpf.messages.config import add_run_arguments, config_from_args

    parser = argparse.ArgumentParser()
    add_run_arguments(parser, choose_by_default=True)
    config = config_from_args(parser.parse_args(flags), choose_by_default=True)
    assert (config.policy, config.choose_base) == (policy, base)
    assert (RunConfig().policy, RunConfig().ps) == ("fixed", 0.81)
    if "--choose-base" not in flags:   # the services, dtpf compare: RunConfig's default unless named
        assert config_from_args(parser.parse_args(flags)).policy == \
            ("choose" if "choose" in flags else "fixed")


def test_a_config_file_that_sets_ps_keeps_the_fixed_policy_and_one_that_sets_nothing_chooses(tmp_path):
    import argparse

    from dtpf.messages.config import add_run_arguments, config_from_args

    parser = argparse.ArgumentParser()
    add_run_arguments(parser, choose_by_default=True)
    (tmp_path / "ps.toml").write_text("ps = 0.5\n")
    (tmp_path / "n.toml").write_text("particles = 300\n")
    args = parser.parse_args(["--config", str(tmp_path / "ps.toml")])
    assert config_from_args(args, choose_by_default=True).policy == "fixed"
    chosen = config_from_args(parser.parse_args(["--config", str(tmp_path / "n.toml")]), choose_by_default=True)
    assert (chosen.policy, chosen.choose_base, chosen.particles) == ("choose", "rehearse", 300)
    help_text = " ".join(parser.format_help().split())
    assert "default: choose on a rehearsed base; fixed (PS 0.81, the paper's) with --ps, --weight-rule, " \
        "--move-rule, --move or --no-preprocess" in help_text


def test_helper_processes_give_the_numbers_of_one_process_for_a_models_file_and_for_one_that_does_not_pickle(
        few_runs, monkeypatch, tmp_path, caplog):
    """A look shared among two cores: helper processes import the user's model file under its name here and make the
    later runs; a model that does not pickle (a class defined in a function) is rehearsed here alone, with a word."""
    from dtpf.entity import cores, model_ref

    (tmp_path / "shifted.py").write_text("from dtpf.entity.models import DriftModel\n\nMODEL = DriftModel(prior_mean=100.0)\n")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(cores, "threads", lambda: 2)
    model = model_ref.resolve(f"{tmp_path / 'shifted.py'}:MODEL")

    class Local(models.DriftModel):
        pass

    for each in (model, Local(prior_mean=100.0)):
        monkeypatch.setattr(rehearse, "SHARED_WORK", 10 ** 18)
        rehearse._CACHE.clear()
        alone = rehearse.rehearse(each, FIVE, n=40, steps=8, runs=60)
        monkeypatch.setattr(rehearse, "SHARED_WORK", 0)
        monkeypatch.setattr(rehearse, "_file_of", lambda *args: None)   # nothing read from disk
        rehearse._CACHE.clear()
        with caplog.at_level(logging.WARNING):
            shared = rehearse.rehearse(each, FIVE, n=40, steps=8, runs=60)
        assert shared == alone
    assert "helper process failed" not in caplog.text
    assert "does not pickle" in caplog.text


@dataclasses.dataclass(frozen=True)
class Mapped(models.DriftModel):
    """drift with a table it does not use: a model whose repr summarises a field."""
    table: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(5000))


def test_the_file_of_a_rehearsal_tells_models_apart_by_every_field_and_a_move_by_its_file(own_cache, tmp_path):
    """Two models whose array field differs in one element deep inside (their reprs summarise it alike), and one
    move file before and after an edit, are four rehearsals on disk."""
    first, second = Mapped(), Mapped()
    second.table[2500] = 1.0          # the array itself is writable
    assert repr(first) == repr(second)
    key = ("model", FIVE, 40, 8, 60, (60,), rehearse.DROP, "neff", "none", 40, rehearse.Z, rehearse.SEED)
    assert rehearse._file_of(first, key) != rehearse._file_of(second, key) is not None
    move = tmp_path / "mine.py"
    move.write_text("def f(resampled, particles, weights, rng):\n    return resampled\n")
    with_move = key[:8] + (f"{move}:f",) + key[9:]
    before = rehearse._file_of(first, with_move)
    move.write_text("def f(resampled, particles, weights, rng):\n    return resampled + 0.0\n")
    assert before is not None and rehearse._file_of(first, with_move) != before
    move.unlink()
    assert rehearse._file_of(first, with_move) is None      # a file that is gone: nothing kept on disk


def test_dtpf_launch_leaves_a_rehearsal_it_cannot_keep_to_the_system_service_and_makes_one_it_can(
        own_cache, capsys):
    """A model whose rehearsal is not kept on disk would be rehearsed twice (here, then in the system service): the
    launcher only says that the service rehearses. A dataclass model is rehearsed here, and the line says so."""
    from dtpf.scripts.cli import REHEARSING, rehearse_first

    class Plain:
        samples_observations = True

        def __getattr__(self, name):
            return getattr(models.DriftModel(prior_mean=100.0), name)

    config = RunConfig(**SHIFTED, policy="choose", choose_base="rehearse", particles=40, steps=8)
    rehearse_first(config, Plain(), for_services=True)
    assert capsys.readouterr().err.strip() == REHEARSING and not rehearse._CACHE
    rehearse_first(config, DRIFT_PLUS_100, for_services=True)
    said = capsys.readouterr().err
    assert re.search(r"dtpf: rehearsal: base \S+ \(60 simulated runs, T = 8, 40 particles an arm, made in", said)
    assert rehearse.kept_on_disk(DRIFT_PLUS_100) and not rehearse.kept_on_disk(Plain())


def test_a_model_that_raises_in_the_system_layers_forecast_is_said_once_counted_and_the_layer_decides_on(caplog):
    """The arms' copies call the model: a propagate that raises at steps 3 and 4 gives those steps a forecast of the
    weight history alone (one warning, then counted); the policy keeps deciding, and the copies start again."""
    from dtpf.information.mirror import summarise
    from dtpf.system.predict import Snapshot

    class Failing(models.DriftModel):
        def propagate(self, particles, k, rng, noise=None):
            if k in (3, 4):
                raise IndexError("a bug of the model's")
            return super().propagate(particles, k, rng, noise=noise)

    model = Failing(prior_mean=100.0)
    layer = SystemLayer.from_config(RunConfig(policy="choose", particles=50, steps=8, seed=1), model=model)
    rng = np.random.default_rng(0)
    truth, z = model.simulate(8, rng)
    particles = np.asarray(model.initial_particles(50, rng), dtype=np.float64).reshape(50, -1)
    weights = np.full(50, 1 / 50)
    decisions = []
    with caplog.at_level(logging.WARNING):
        for k in range(1, 9):
            summary = summarise(particles, weights, "neff", 50)
            decisions.append(layer.observe(k, summary, Snapshot.of(particles, weights, z[k - 1])))
            kept = [step for step, _ in layer.predictor.history]    # each step once, a failed one too
            assert kept == list(range(k + 1 - len(kept), k + 1)), kept
    assert [d.applies_from_step for d in decisions] == list(range(2, 10)) and layer.model_failures == 2
    assert caplog.text.count("the model raised IndexError: a bug of the model's") == 1
    assert layer.forecasts[-1].arm_evidence is not None
