"""A twin of a driven machine: time steps, control inputs, several sensors (docs/guides/driven.md).

The unicycle of docs/examples/unicycle.py, driven by wheel odometry and seen by a GPS and three beacons,
simulated into CSV files by docs/examples/make_unicycle_csv.py. One end-to-end test launches the three
layers; the rest run in process.
"""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from dtpf.entity import sources, stamped
from dtpf.entity.calls import ModelCalls
from dtpf.entity.filter import ParticleFilter
from dtpf.entity.model_check import check_model
from dtpf.entity.model_ref import ModelError, resolve
from dtpf.entity.models import StateSpaceModel
from dtpf.entity.observations import ObservationError
from dtpf.entity.timeline import MAX_PIECES, NS, Reorder, TimeError, Timeline
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate, ServiceState, Status
from dtpf.scripts import inprocess

from conftest import ROOT, example_module, service_args

MODEL = "docs/examples/unicycle.py:Unicycle"


def dtpf(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """2 s of the robot: 40 odometry rows, 20 beacon rows, 2 GPS rows (at 1.000 and 2.000, beacon stamps too)."""
    return example_module("make_unicycle_csv").main(tmp_path_factory.mktemp("robot"), duration=2.0, seed=5)


def config_of(robot, **options) -> RunConfig:
    return RunConfig(model=str(ROOT / MODEL), sensor_files={"gps": str(robot["gps"]), "beacons": str(robot["beacons"])},
                     controls=str(robot["odometry"]), **{"particles": 150, "seed": 3, "twin": "robot-1", **options})


# --- the model contract: old models are called as before ------------------------------------------

class Spy(StateSpaceModel):
    """A model of one sensor written before the contract grew: it records how it is called."""

    name, dim, obs_dim = "spy", 1, 1

    def __init__(self):
        self.calls = []

    def initial_particles(self, n, rng):
        return rng.standard_normal((n, 1))

    def propagate(self, particles, k, rng, noise=None, **kwargs):  # a catch-all gets nothing new
        self.calls.append(("propagate", tuple(sorted(kwargs))))
        return particles + rng.standard_normal(particles.shape)

    def log_likelihood(self, particles, observation, k):
        self.calls.append(("log_likelihood", ()))
        return -0.5 * (particles[:, 0] - observation[0]) ** 2


def test_a_model_written_without_dt_control_or_sensor_is_called_as_before():
    spy = Spy()
    calls = ModelCalls(spy)
    assert not calls.driven and calls.sensors == {None: 1}
    steps = list(ParticleFilter(spy, np.arange(4.0), 50, seed=1))
    assert {name for name, kwargs in spy.calls if kwargs} == set()  # no dt, control or sensor was passed
    # and the same numbers as a filter that never heard of drives
    again = list(ParticleFilter(Spy(), np.arange(4.0), 50, seed=1, drives=None, sensors=None))
    np.testing.assert_array_equal([s.mean for s in steps], [s.mean for s in again])


def test_a_driven_model_gets_dt_control_and_sensor():
    unicycle = resolve(str(ROOT / MODEL))
    calls = ModelCalls(unicycle)
    assert calls.driven and calls.takes_dt and calls.takes_control and calls.named_sensors
    assert calls.sensors == {"gps": 2, "beacons": 3} and calls.controls == ("v", "omega") and unicycle.obs_dim == 3
    check_model(unicycle, observation={"gps": [0.0, 0.0], "beacons": [30.0, 31.6, 29.2]})


# --- the timeline: dt from integer stamps, controls held -------------------------------------------

def test_an_interval_is_split_at_the_control_changes_inside_it():
    timeline = Timeline(controls=1, piecewise=True)
    for stamp, u in ((0, 1.0), (50_000_000, 2.0), (150_000_000, 3.0), (200_000_000, 4.0)):
        timeline.control(stamp, [u])
    assert timeline.step(100_000_000) is None  # the first step starts from the prior
    # (0.1, 0.2]: u = 2 (held from 0.05) until 0.15, then 3; the control at 0.2 acts from 0.2 on
    np.testing.assert_array_equal(timeline.step(200_000_000).pieces, [[0.05, 2.0], [0.05, 3.0]])
    np.testing.assert_array_equal(timeline.step(200_000_000).pieces, [[0.0, 4.0]])  # two sensors, one stamp
    with pytest.raises(TimeError, match="before the last step"):
        timeline.step(199_999_999)
    fast = Timeline(controls=1)  # 4999 control changes in one interval: runs of them merged, u dt kept
    fast.step(0)
    for i in range(1, 5000):
        fast.control(i * 20_000, [float(i % 3)])
    pieces = fast.step(100_000_000).pieces
    assert pieces.shape == (MAX_PIECES, 2)
    assert abs(pieces[:, 0].sum() - 0.1) < 1e-12
    exact = 20_000 * sum(i % 3 for i in range(1, 5000)) / NS  # u = 0 before the first control, u_i after s_i
    assert abs(pieces[:, 0] @ pieces[:, 1] - exact) < 1e-12
    held = Timeline(controls=1, piecewise=False)  # a model that takes control but not dt: one piece
    held.control(0, [1.0]), held.control(50_000_000, [2.0]), held.step(0)
    np.testing.assert_array_equal(held.step(100_000_000).pieces, [[0.1, 1.0]])


class Walk(StateSpaceModel):
    """x moves at the control's speed over dt, plus a random walk of variance q dt (Brownian: splitting an
    interval does not change the law)."""

    name, dim, obs_dim, controls, q = "walk", 1, 1, ("speed",), 0.5

    def initial_particles(self, n, rng):
        return np.zeros((n, 1))

    def propagate(self, particles, k, rng, noise=None, *, dt=None, control=None):
        return particles + control[0] * dt + np.sqrt(self.q * dt) * rng.standard_normal(particles.shape)

    def log_likelihood(self, particles, observation, k):
        return -0.5 * (particles[:, 0] - observation[0]) ** 2


def test_a_step_over_three_control_pieces_has_the_law_of_the_held_controls():
    timeline = Timeline(controls=1, piecewise=True)
    for stamp, u in ((0, 1.0), (20_000_000, 2.0), (70_000_000, -1.0)):
        timeline.control(stamp, [u])
    timeline.step(0)
    drive = timeline.step(100_000_000)
    np.testing.assert_array_equal(drive.pieces, [[0.02, 1.0], [0.05, 2.0], [0.03, -1.0]])
    n = 20_000
    x = ModelCalls(Walk()).advance(np.zeros((n, 1)), 2, np.random.default_rng(11), drive)[:, 0]
    # mean sum dt_i u_i = 0.09 (one piece held from the start would give 0.1), variance q * 0.1; 4 standard errors
    variance = Walk.q * 0.1
    assert abs(x.mean() - 0.09) < 4 * np.sqrt(variance / n)
    assert abs(x.var(ddof=1) / variance - 1) < 4 * np.sqrt(2 / (n - 1))


def test_dt_comes_from_integer_nanoseconds_exactly():
    timeline = Timeline()
    timeline.step(1_700_000_000 * NS + 950_000_000)
    # a float of seconds near 1.7e9 s cannot hold 950000128 ns apart from 950000000; integers can
    assert timeline.step(1_700_000_000 * NS + 1_000_000_000).dt == 0.05


def test_out_of_order_observations_within_the_window_are_put_in_order_and_later_ones_counted():
    order = Reorder(window=100)
    for stamp in (10, 5, 60, 40, 150):  # 5 and 40 arrive late but within the window
        assert order.push(stamp, 1, stamp)
    assert order.ready() == [5, 10, 40]  # released: at least 100 ns older than the newest (150)
    assert not order.push(20, 1, 20)     # older than what was released: late, counted, skipped
    assert order.push(55, 1, 55) and order.push(300, 0, "control") and order.push(300, 1, 300)
    assert order.ready() == [55, 60, 150] and order.flush() == ["control", 300]
    assert order.late == 1


def test_one_csv_of_every_sensor_is_put_in_stamp_order_within_the_window_and_later_rows_skipped(robot, tmp_path):
    model = resolve(str(ROOT / MODEL))
    files = sources.observations_of(config_of(robot), model)
    lines = ["time,sensor,z0,z1,z2"]
    for stamp, sensor, z in zip(files.stamps, files.sensors, files.observations):
        values = [repr(float(v)) for v in z[:model.sensors[sensor]]]
        lines.append(",".join([f"{stamp // NS}.{stamp % NS:09d}", sensor, *values, *[""] * (3 - len(values))]))
    lines[4], lines[5] = lines[5], lines[4]   # 0.1 s apart: within the window of 0.1 s, put back in order
    lines.insert(12, lines.pop(3))            # 0.8 s late: beyond it, skipped and named
    shared = tmp_path / "all.csv"
    shared.write_text("\n".join(lines) + "\n")
    config = config_of(robot).model_copy(update={"sensor_files": None, "observations": str(shared)})
    data = sources.observations_of(config, model)
    kept = [i for i in range(len(files.sensors)) if i != 2]  # without the row that came late
    assert data.sensors == tuple(files.sensors[i] for i in kept)
    np.testing.assert_array_equal(data.stamps, files.stamps[kept])
    np.testing.assert_array_equal(data.observations, files.observations[kept])
    assert "1 row stamped before a row already put in order" in data.problem and "(line 13)" in data.problem


# --- files: in process and over Zenoh, the same numbers --------------------------------------------

def test_the_sensors_files_are_merged_in_stamp_order(robot):
    model = resolve(str(ROOT / MODEL))
    data = sources.observations_of(config_of(robot), model)
    assert len(data.sensors) == 22 and data.sensors.count("gps") == 2
    assert np.all(np.diff(data.stamps) >= 0) and data.stamps[0] == 50_000_000 * 2
    # at 1.000 s the GPS follows the beacons' observation at that stamp (the model's sensors in order: gps first)
    at_one = [s for s, t in zip(data.sensors, data.stamps) if t == NS]
    assert at_one == ["gps", "beacons"]
    assert data.drives[0] is None and data.drives[at_one and list(data.stamps).index(NS) + 1].dt == 0.0
    assert np.isnan(data.observations[list(data.sensors).index("gps"), 2])  # a GPS row has 2 values


def test_a_two_sensor_driven_model_launched_equals_dtpf_run_and_verifies(robot, tmp_path):
    from dtpf.scripts.launch import launch

    # the predictive policy and the likelihood weight rule: both other layers weigh each step by its own sensor
    config = config_of(robot, policy="predictive", weight_rule="likelihood")
    reference = inprocess.run(config)
    assert reference.rmse < 1.0  # GPS of 1.5 m and beacons of 0.3 m: the pose to well under a metre
    log = tmp_path / "robot.mcap"
    result = launch(config, log_path=log, timeout=10.0)
    assert result.exit_codes == {"recorder": 0, "system": 0, "information": 0, "entity": 0}
    estimates = sorted(result.estimates, key=lambda e: e.step)
    np.testing.assert_array_equal([e.mean for e in estimates], reference.means)  # number for number
    np.testing.assert_array_equal([e.ps for e in estimates], reference.ps)
    assert [e.sensor for e in estimates] == [s.sensor for s in reference.steps]
    data = sources.observations_of(config, resolve(config.model_ref))
    assert [e.stamp.to_ns() for e in estimates] == data.stamps.tolist()  # each at its observation's time
    done = dtpf("verify", str(log))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "22 propagated sets reproduced bit for bit" in done.stdout


def test_dtpf_sensor_stands_in_for_both_sensors_and_the_odometry_of_a_live_twin(robot, processes, router):
    # A window longer than the run holds every message until the end: arrival order cannot matter.
    run = ["--model", str(ROOT / MODEL), "--particles", "150", "--seed", "3", "--twin", "robot-live"]
    entity = processes.start("entity", service_args("dtpf.entity.service", router.endpoint, *run, "--observations",
                                                    "live", "--no-preprocess", "--reorder-window", "10"))
    files = ["--observations", f"gps={robot['gps']}", "--observations", f"beacons={robot['beacons']}",
             "--controls", str(robot["odometry"])]
    sensor = processes.start("sensor", ["-m", "dtpf.scripts.sensor", "--connect", router.endpoint, *run, *files,
                                        "--speed", "0"])
    assert entity.wait(timeout=120) == 0, processes.output(entity)
    assert sensor.wait(timeout=30) == 0, processes.output(sensor)

    def finished(messages):
        return [m for m in messages if isinstance(m, Status) and m.layer.value == "entity"
                and m.state == ServiceState.FINISHED]

    router.collect(lambda m: finished(m) and {e.step for e in m if isinstance(e, Estimate)} >= set(range(1, 23)),
                   timeout=30)
    estimates = sorted((m for m in router.messages if isinstance(m, Estimate)), key=lambda e: e.step)
    reference = inprocess.run(config_of(robot, twin="robot-live", preprocess=False))
    np.testing.assert_array_equal([e.mean for e in estimates], reference.means)
    final = finished(router.messages)[-1]
    assert final.observations.accepted == 22 and final.observations.controls == 40
    assert final.observations.late == 0


def test_the_live_intake_orders_counts_and_survives_bad_messages():
    from dtpf.entity.intake import DrivenIntake
    from dtpf.messages.models import Control, Observation, Time

    intake = DrivenIntake(ModelCalls(resolve(str(ROOT / MODEL))), state_dim=3, window=100_000_000)
    header = dict(run_id="r", twin_id="t")

    def observation(step, ms, sensor, values):
        return Observation(**header, step=step, stamp=Time.from_ns(ms * 1_000_000), sensor=sensor, values=values)

    def control(step, ms, values):
        return Control(**header, step=step, stamp=Time.from_ns(ms * 1_000_000), control=values)

    assert intake.control(control(1, 0, [1.0, 0.0])) is None
    assert intake.observation(observation(1, 100, "beacons", [1.0, 2.0, 3.0])) is None
    assert intake.observation(observation(1, 150, "gps", [0.0, 0.0])) is None
    assert intake.control(control(2, 120, [2.0, 0.5])) is None       # late, but within the window
    assert intake.observation(observation(2, 300, "beacons", [1.0, 2.0, 3.0])) is None
    bad = [intake.observation(observation(1, 310, "lidar", [1.0])),     # no such sensor
           intake.observation(observation(2, 320, "gps", [1.0])),       # gps has 2 values
           intake.control(control(3, 330, [1.0])),                      # the control has 2
           intake.observation(observation(3, 50, "beacons", [1.0, 2.0, 3.0]))]  # before a step filtered
    assert all(verdict is not None for verdict in bad)
    steps = [intake.take() for _ in range(2)]
    assert [(s.sensor, s.stamp) for s in steps] == [("beacons", 100_000_000), ("gps", 150_000_000)]
    assert steps[0].drive is None  # the first step starts from the prior
    np.testing.assert_allclose(steps[1].drive.pieces, [[0.02, 1.0, 0.0], [0.03, 2.0, 0.5]])  # split at 0.12 s
    assert intake.take() is None  # 0.3 s waits for a message 0.1 s later, or the end
    counts = intake.counts()
    assert (counts.unknown_sensor, counts.wrong_length, counts.controls_rejected, counts.late) == (1, 1, 1, 1)
    assert counts.accepted == 3 and counts.controls == 2
    # The observations end; what is held waits for the controls' end (the other key may still bring some).
    assert intake.observation(Observation(**header, step=4, sensor="beacons", values=[], end=True)) is None
    assert intake.take() is None
    assert intake.control(Control(**header, step=4, end=True)) is None
    assert intake.take().stamp == 300_000_000 and intake.take().end


# --- mistakes: one line each ------------------------------------------------------------------------

def test_bad_driven_inputs_are_named_in_one_line(robot, tmp_path):
    model = resolve(str(ROOT / MODEL))
    wrong = tmp_path / "wrong.csv"
    wrong.write_text("time,x\n0.1,1.0\n")
    cases = {
        "no sensor 'lidar'": dict(sensor_files={"lidar": str(robot["gps"])}),
        "1 observation column \\(x\\), the model observes 2": dict(sensor_files={"gps": str(wrong)}),
        "control has 2 \\(v, omega\\)": dict(controls=str(wrong)),
        "give them with --controls": dict(controls=None),
    }
    for message, change in cases.items():
        with pytest.raises(ObservationError, match=message):
            sources.observations_of(config_of(robot).model_copy(update=change), model)
    no_time = tmp_path / "no_time.csv"
    no_time.write_text("x,y\n1,2\n")
    with pytest.raises(ObservationError, match="no time column"):
        stamped.read_stamped(config_of(robot).model_copy(update={"sensor_files": {"gps": str(no_time)}}), model)
    np.save(tmp_path / "gps.npy", np.zeros((3, 2)))
    with pytest.raises(ObservationError, match="gps.npy: no times"):
        stamped.read_stamped(config_of(robot).model_copy(update={"sensor_files": {"gps": str(tmp_path / "gps.npy")}}),
                             model)
    with pytest.raises(ModelError, match="is driven"):
        sources.load_model(RunConfig(model=str(ROOT / MODEL), steps=5))
    done = dtpf("run", "--model", MODEL, "--observations", f"lidar={robot['gps']}", "--controls",
                str(robot["odometry"]))
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "no sensor 'lidar'" in done.stderr
