"""A twin of a real system: the user's model, the user's observations, from a file or a live sensor.

Real processes on free loopback ports; every process is stopped by the
``processes`` fixture, pass or fail.
"""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh
from test_services import read_with_mcap_only

from dtpf.entity import sources
from dtpf.messages.codec import encode
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate, Observation, ServiceState, Status
from dtpf.scripts import inprocess
from dtpf.scripts.launch import launch

from conftest import ROOT, service_args

EXAMPLE = "docs/examples/range_bearing.py:RangeBearingTarget"
EXAMPLE_CSV = "docs/examples/range_bearing.csv"
EXAMPLE_NO_TRUTH = "docs/examples/range_bearing_no_truth.csv"


def dtpf(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


# --- the worked example, from a file ---------------------------------------------------------

def test_the_example_model_launched_on_a_file_equals_dtpf_run_and_verifies(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)  # the model reference and the file are relative, as a user types them
    config = RunConfig(model=EXAMPLE, observations=EXAMPLE_NO_TRUTH, particles=400, steps=30, seed=4,
                       twin="t-rb")
    log = tmp_path / "rb.mcap"
    result = launch(config, log_path=log, timeout=5.0)
    assert result.exit_codes == {"recorder": 0, "system": 0, "information": 0, "entity": 0}
    reference = inprocess.run(config)
    means = np.array([e.mean for e in sorted(result.estimates, key=lambda e: e.step)])
    np.testing.assert_array_equal(means, reference.means)  # number for number
    assert means.shape == (30, 4)
    # Without truth: no RMSE, the log predictive likelihood instead, the same on both sides.
    assert all(e.truth is None for e in result.estimates)
    lp = np.array([e.log_predictive for e in sorted(result.estimates, key=lambda e: e.step)])
    np.testing.assert_array_equal(lp, reference.log_predictive)
    assert "RMSE" not in result.summary() and "log predictive" in result.summary()

    done = dtpf("verify", str(log))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "OK: 30 steps reproduced exactly" in done.stdout
    summary = dtpf("summary", str(log))
    assert summary.returncode == 0, summary.stderr
    assert "log predictive" in summary.stdout and "RMSE" not in summary.stdout
    assert EXAMPLE in summary.stdout  # the run configuration names the model reference
    plotted = dtpf("plot", str(log), "-o", str(tmp_path / "rb.png"))
    assert plotted.returncode == 0, plotted.stderr
    assert (tmp_path / "rb.png").stat().st_size > 10_000


def test_verify_says_what_to_pass_when_the_model_has_moved(tmp_path, monkeypatch):
    model_file = tmp_path / "walk.py"
    model_file.write_text((ROOT / "docs/examples/range_bearing.py").read_text())
    monkeypatch.chdir(tmp_path)
    config = RunConfig(model="walk.py:RangeBearingTarget", observations=str(ROOT / EXAMPLE_CSV), particles=200,
                       steps=8, twin="t-moved")
    log = tmp_path / "moved.mcap"
    result = launch(config, log_path=log, timeout=5.0)
    assert result.exit_codes["entity"] == 0
    assert np.isfinite(result.rmse)  # this file has truth columns
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    model_file.rename(moved / "walk.py")
    done = dtpf("verify", str(log))
    assert done.returncode == 2
    assert "walk.py:RangeBearingTarget" in done.stdout and "pass --model" in done.stdout
    done = dtpf("verify", str(log), "--model", f"{moved / 'walk.py'}:RangeBearingTarget")
    assert done.returncode == 0, done.stdout
    assert "OK: 8 steps reproduced exactly" in done.stdout


def test_dtpf_run_on_a_file_with_truth_prints_rmse():
    done = dtpf("run", "-q", "--model", EXAMPLE, "--observations", EXAMPLE_CSV, "-n", "300", "--steps", "20")
    assert done.returncode == 0, done.stderr
    assert "RMSE" in done.stdout and "T = 20" in done.stdout


# --- mistakes: one line, exit 2, no traceback ---------------------------------------------------

BAD_MODELS = {
    "missing method": ("""
from dtpf.entity.models import StateSpaceModel
class M(StateSpaceModel):
    name, dim, obs_dim = "m", 1, 1
    def initial_particles(self, n, rng): return rng.normal(size=(n, 1))
    def propagate(self, particles, k, rng, noise=None): return particles + 1.0
""", "does not implement the abstract method log_likelihood"),
    "wrong shape": ("""
import numpy as np
from dtpf.entity.models import StateSpaceModel
class M(StateSpaceModel):
    name, dim, obs_dim = "m", 2, 1
    def initial_particles(self, n, rng): return rng.normal(size=(n, 2))
    def propagate(self, particles, k, rng, noise=None): return particles[:, :1]
    def log_likelihood(self, particles, z, k): return -particles[:, 0] ** 2
""", r"propagate returned shape \(5, 1\), expected \(5, 2\)"),
    "NaN likelihood": ("""
import numpy as np
from dtpf.entity.models import StateSpaceModel
class M(StateSpaceModel):
    name, dim, obs_dim = "m", 1, 1
    def initial_particles(self, n, rng): return rng.normal(size=(n, 1))
    def propagate(self, particles, k, rng, noise=None): return particles + 1.0
    def log_likelihood(self, particles, z, k): return np.full(len(particles), np.nan)
""", "log_likelihood returned NaN at index 0"),
    "import error": ("import not_a_module_anywhere\n", "No module named 'not_a_module_anywhere'"),
}


@pytest.mark.parametrize("case", sorted(BAD_MODELS))
@pytest.mark.parametrize("command", ["run", "launch", "dtpf.entity.service"])
def test_a_bad_model_is_one_line_and_exit_2(case, command, tmp_path):
    source, expected = BAD_MODELS[case]
    (tmp_path / "bad.py").write_text(source)
    observations = tmp_path / "z.csv"
    observations.write_text("z\n1.0\n2.0\n")
    options = ["--model", f"{tmp_path / 'bad.py'}:M", "--observations", str(observations)]
    if command == "dtpf.entity.service":
        done = subprocess.run([sys.executable, "-m", "dtpf.entity.service", *options, "--listen", "tcp/127.0.0.1:0"],
                              cwd=ROOT, capture_output=True, text=True, timeout=60)
    else:
        done = dtpf(command, *options, "-o" if command == "launch" else "-q", *(
            [str(tmp_path / "x.mcap")] if command == "launch" else []))
    assert done.returncode == 2, done.stdout + done.stderr
    errors = [line for line in done.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and "Traceback" not in done.stderr, done.stderr
    assert __import__("re").search(expected, errors[0]), errors[0]
    assert "bad.py:M" in errors[0]


BAD_FILES = {
    "missing column": ("time,range\n1,40.0\n2,41.0\n", "1 observation column (range), the model observes 2"),
    "ragged rows": ("time,range,bearing\n1,40.0,1.1\n2,41.0\n", "line 3: 2 values, the header has 3 columns"),
    "NaN": ("time,range,bearing\n1,40.0,1.1\n2,nan,1.2\n", "line 3, column 'range': NaN"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
@pytest.mark.parametrize("command", ["run", "launch"])
def test_a_bad_observation_file_is_one_line_and_exit_2(case, command, tmp_path):
    text, expected = BAD_FILES[case]
    path = tmp_path / "obs.csv"
    path.write_text(text)
    extra = ["-o", str(tmp_path / "x.mcap")] if command == "launch" else ["-q"]
    done = dtpf(command, "--model", EXAMPLE, "--observations", str(path), *extra)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], done.stderr
    assert not (tmp_path / "x.mcap").exists()  # nothing started


def test_a_live_run_is_refused_by_dtpf_run_and_a_bad_live_key_at_startup():
    done = dtpf("run", "--observations", "live")
    assert done.returncode == 2 and "live observations need dtpf launch" in done.stderr
    done = dtpf("run", "--observations", "live:dtpf/a/entity/estimate")
    assert done.returncode == 2 and "dtpf/<twin>/sensor/observation" in done.stderr


# --- live: a sensor process feeding a launched twin ----------------------------------------------

def _start_layers(processes, router, run, log, *entity_extra):
    # Every layer runs the same configuration (a live run has no last step), as dtpf launch starts them.
    run = [*run, "--observations", "live"]
    processes.start("recorder", service_args("dtpf.scripts.record", router.endpoint, *run, "--output", str(log)))
    processes.start("system", service_args("dtpf.system.service", router.endpoint, *run))
    processes.start("information", service_args("dtpf.information.service", router.endpoint, *run))
    return processes.start("entity", service_args(
        "dtpf.entity.service", router.endpoint, *run, "--wait-for", "recorder",
        "--wait-for", "information", "--wait-for", "system", *entity_extra))


def _entity_statuses(router):
    return [m for m in router.messages if isinstance(m, Status) and m.layer.value == "entity"]


def _entity_done(steps: int):
    """Until the entity's final status and the estimates of steps 1..``steps`` have come (a fixed wait for
    them was too short on a loaded machine)."""
    def done(messages) -> bool:
        return (any(isinstance(m, Status) and m.layer.value == "entity" and m.state == ServiceState.FINISHED
                    for m in messages)
                and {m.step for m in messages if isinstance(m, Estimate)} >= set(range(1, steps + 1)))
    return done


def test_a_live_twin_follows_its_sensor_waits_when_it_dies_and_continues_when_it_is_back(processes, router,
                                                                                         tmp_path):
    run = ["--particles", "300", "--twin", "t-live", "--seed", "5"]
    log = tmp_path / "live.mcap"
    entity = _start_layers(processes, router, run, log, "--observation-timeout", "1")
    sensor_args = ["-m", "dtpf.scripts.sensor", "--connect", router.endpoint, *run, "--steps", "60", "--rate", "25"]
    sensor = processes.start("sensor", sensor_args)

    def estimates():
        return sorted((m for m in router.messages if isinstance(m, Estimate)), key=lambda e: e.step)

    assert router.collect(lambda m: any(isinstance(x, Estimate) and x.step >= 15 for x in m), 60), \
        processes.output(entity) + processes.output(sensor)
    sensor.kill()
    sensor.wait()
    # The twin waits for its sensor and says so; it never invents a step. (A status of before the sensor's
    # first observation says waiting too: a loaded machine started the sensor after the entity's first look.)
    heard = len(router.messages)

    def waiting_statuses(messages):
        return [m for m in messages[heard:] if isinstance(m, Status) and m.layer.value == "entity"
                and m.state == ServiceState.WAITING]

    assert router.collect(waiting_statuses, 20), processes.output(entity)
    waiting = waiting_statuses(router.messages)[0]
    assert "no observation for" in waiting.detail and waiting.observations.accepted >= 15
    stalled = len(estimates())
    router.collect(lambda m: False, timeout=1.0)
    assert len(estimates()) == stalled
    assert entity.poll() is None

    restarted = processes.start("sensor", sensor_args)
    entity.wait(timeout=120)
    assert entity.returncode == 0, processes.output(entity)
    assert restarted.wait(timeout=30) == 0, processes.output(restarted)
    assert "continuing after observation" in processes.output(restarted)
    router.collect(_entity_done(60), timeout=30)
    steps = [e.step for e in estimates()]
    assert steps == list(range(1, 61)), steps  # every observation became exactly one step
    # The restarted sensor went on along the same simulated path: the numbers are dtpf run's.
    reference = inprocess.run(RunConfig(particles=300, steps=60, twin="t-live", seed=5))
    np.testing.assert_array_equal([e.mean for e in estimates()], reference.means)
    final = _entity_statuses(router)[-1]
    assert final.observations.accepted == 60 and final.observations.last_sequence == 60

    for process in processes.started:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    for process in processes.started:
        process.wait(timeout=20)
    recorded = read_with_mcap_only(log)
    observations = recorded["dtpf/t-live/sensor/observation"]
    assert sorted(m["step"] for m in observations if not m["end"]) == list(range(1, 61))
    assert sum(m["end"] for m in observations) == 1
    assert len(recorded["dtpf/t-live/entity/estimate"]) == 60


def test_hostile_live_observations_are_counted_and_the_run_goes_on(processes, router, tmp_path):
    run = ["--particles", "200", "--twin", "t-hostile", "--seed", "2"]
    entity = _start_layers(processes, router, run, tmp_path / "h.mcap")
    steps = 200
    config = RunConfig(particles=200, steps=steps, twin="t-hostile", seed=2)
    data = sources.observations_of(config, sources.load_model(config))
    assert router.collect(lambda m: any(isinstance(s, Status) and s.layer.value == "entity"
                                        and s.state == ServiceState.RUNNING for s in m), 60), \
        processes.output(entity)
    key = "dtpf/t-hostile/sensor/observation"
    publisher = router.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)

    def observation(sequence, values, **extra):
        return encode(Observation(run_id="run", twin_id="t-hostile", step=sequence, values=values, **extra))

    sent = {"duplicate": 0, "out_of_order": 0, "wrong_length": 0, "malformed": 0}
    nan = json.loads(observation(1, [1.0]).decode())
    for k in range(1, steps + 1):
        z = data.observations[k - 1].tolist()
        publisher.put(observation(k, z, truth=data.truth[k - 1].tolist()))
        publisher.put(observation(k, z))                                   # duplicate
        sent["duplicate"] += 1
        if k > 1:
            publisher.put(observation(k - 1, z))                           # late, out of order
            sent["out_of_order"] += 1
        publisher.put(observation(k + 1, z + [0.5]))                       # wrong length
        sent["wrong_length"] += 1
        nan["step"] = k + 1
        publisher.put(json.dumps(nan).replace("1.0]", "NaN]"))             # NaN value
        publisher.put(b"\x00\x01 not json")                                 # garbage
        publisher.put(b"[" * 1000 + b"]" * 1000 if k % 50 == 0 else b"{}")   # nesting, empty object
        sent["malformed"] += 3
        if k % 20 == 0:
            time.sleep(0.05)
    publisher.put(observation(steps + 1, [], end=True))
    entity.wait(timeout=120)
    assert entity.returncode == 0, processes.output(entity)
    router.collect(_entity_done(steps), timeout=30)
    estimates = sorted((m for m in router.messages if isinstance(m, Estimate)), key=lambda e: e.step)
    assert [e.step for e in estimates] == list(range(1, steps + 1))
    reference = inprocess.run(config)
    np.testing.assert_array_equal([e.mean for e in estimates], reference.means)
    final = _entity_statuses(router)[-1]
    counts = final.observations
    assert counts.accepted == steps
    for name, number in sent.items():
        assert getattr(counts, name) == number, (name, counts)
    assert final.rejected == sum(sent.values())
    # Logged once per reason, not once per message.
    output = processes.output(entity)
    assert output.count("rejected a message (duplicate observation") == 1, output
    publisher.undeclare()


def test_a_recorded_sensor_stream_re_drives_a_twin_with_dtpf_play(processes, router, tmp_path):
    run = ["--particles", "200", "--twin", "t-replay", "--seed", "9"]
    log = tmp_path / "first.mcap"
    entity = _start_layers(processes, router, run, log)
    sensor = processes.start("sensor", ["-m", "dtpf.scripts.sensor", "--connect", router.endpoint, *run,
                                        "--steps", "25", "--rate", "50", "--no-truth"])
    assert entity.wait(timeout=120) == 0, processes.output(entity)
    assert sensor.wait(timeout=30) == 0, processes.output(sensor)
    for process in processes.started:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    for process in processes.started:
        process.wait(timeout=20)
    router.collect(_entity_done(25), timeout=30)
    first = sorted((m for m in router.messages if isinstance(m, Estimate)), key=lambda e: e.step)
    assert [e.step for e in first] == list(range(1, 26)) and all(e.truth is None for e in first)
    router.messages.clear()

    replay_log = tmp_path / "replay.mcap"
    entity = _start_layers(processes, router, run, replay_log)
    assert router.collect(lambda m: any(isinstance(s, Status) and s.layer.value == "entity"
                                        and s.state == ServiceState.RUNNING for s in m), 60), \
        processes.output(entity)
    played = dtpf("play", str(log), "--topics", "sensor/observation", "--rate", "0", "--wait", "0.5", "-q",
                  "--connect", router.endpoint)
    assert played.returncode == 0, played.stderr
    assert "published 26 messages" in played.stderr  # 25 observations and the end
    assert entity.wait(timeout=120) == 0, processes.output(entity)
    router.collect(_entity_done(25), timeout=30)
    again = sorted((m for m in router.messages if isinstance(m, Estimate)), key=lambda e: e.step)
    np.testing.assert_array_equal([e.mean for e in again], [e.mean for e in first])
    np.testing.assert_array_equal([e.log_predictive for e in again], [e.log_predictive for e in first])
