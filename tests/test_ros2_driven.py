"""A driven, two-sensor twin fed through ROS 2: the unicycle of docs/examples/unicycle.py from its CSV files,
from a rosbag2 bag of the same data (docs/examples/make_unicycle_bag.py) and live from real rclpy nodes
(a test node plays the bag's /gps, /beacons and /odom topics): the same estimates, number for number.

The live test needs the ROS 2 environment of tests/test_ros2_live.py (its helpers are used here); it skips
without one."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from test_ros2_live import needs_ros2, ros_env, start, wait_for_line

from dtpf.entity import sources
from dtpf.entity.model_ref import resolve
from dtpf.entity.observations import ObservationError
from dtpf.messages.codec import MessageError, decode_for_key
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Control, Estimate, Observation
from dtpf.recording.logfile import read_log
from dtpf.scripts import inprocess
from dtpf.shell.bus import free_port

from conftest import ROOT, example_module

MODEL = "docs/examples/unicycle.py:Unicycle"
FIELDS = {"gps": "point.x,point.y", "beacons": "vector.x,vector.y,vector.z"}
RUN = {"particles": 150, "seed": 3, "twin": "robot-1"}


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """3 s of the robot as CSV files and as a bag (33 steps: 30 beacon rows, 3 GPS rows; 60 odometry rows)."""
    folder = tmp_path_factory.mktemp("robot")
    files = example_module("make_unicycle_csv").main(folder, duration=3.0, seed=5)
    files["bag"] = example_module("make_unicycle_bag").main(folder / "bag", duration=3.0, seed=5)
    return files


def files_config(robot) -> RunConfig:
    return RunConfig(model=str(ROOT / MODEL), sensor_files={"gps": str(robot["gps"]), "beacons": str(robot["beacons"])},
                     controls=str(robot["odometry"]), **RUN)


def bag_config(robot, **change) -> RunConfig:
    bag = robot["bag"]
    values = dict(model=str(ROOT / MODEL), sensor_files={name: f"{bag}:/{name}" for name in FIELDS},
                  sensor_fields=FIELDS, controls=f"{bag}:/odom", **RUN)
    return RunConfig(**{**values, **change})


@pytest.fixture(scope="module")
def reference(robot):
    """dtpf run of the CSV files."""
    return inprocess.run(files_config(robot))


def test_the_bag_gives_the_files_estimates_and_stamps(robot, reference):
    run = inprocess.run(bag_config(robot))
    np.testing.assert_array_equal(run.means, reference.means)  # number for number
    assert [s.sensor for s in run.steps] == [s.sensor for s in reference.steps]
    model = resolve(str(ROOT / MODEL))
    data = sources.observations_of(bag_config(robot), model)
    assert data.stamps.dtype == np.int64 and data.stamps[:3].tolist() == [100_000_000, 200_000_000, 300_000_000]
    assert data.stamps.tolist() == sources.observations_of(files_config(robot), model).stamps.tolist()


def test_bag_mistakes_are_one_line(robot, tmp_path):
    model = resolve(str(ROOT / MODEL))
    bag = robot["bag"]
    cases = {
        "no topic '/gpx' in the bag": dict(sensor_files={"gps": f"{bag}:/gpx", "beacons": f"{bag}:/beacons"}),
        "PointStamped has no field 'point.q'": dict(sensor_fields={**FIELDS, "gps": "point.x,point.q"}),
        "say how a geometry_msgs/msg/PointStamped becomes the control": dict(controls=f"{bag}:/gps"),
        "2 values, the model observes 3": dict(sensor_fields={**FIELDS, "beacons": "vector.x,vector.y"}),
        "--ros2-fields gps=PATHS": dict(sensor_fields={"beacons": FIELDS["beacons"]}),
    }
    for message, change in cases.items():
        with pytest.raises(ObservationError, match=message):
            sources.observations_of(bag_config(robot, **change), model)
    with pytest.raises(ValueError, match="no sensor lidar is given"):
        bag_config(robot, sensor_fields={"lidar": "point.x"})
    # a damaged bag (the record of the 23rd odometry message broken): refused with its counts, read in part
    # with --partial
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        raw = [bytes(r) for c, _, r in reader.messages() if c.topic == "/odom"][22]
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    for path in bag.iterdir():
        data = bytearray(path.read_bytes())
        if path.suffix == ".mcap":
            start = data.find(raw) - 31  # the Message record: opcode, length, channel, sequence, two times
            assert start > 0 and data.count(raw) == 1
            data[start:start + 16] = b"\xff" * 16
        (damaged / path.name).write_bytes(bytes(data))
    change = dict(sensor_files={name: f"{damaged}:/{name}" for name in FIELDS}, controls=f"{damaged}:/odom")
    with pytest.raises(ObservationError, match="declares 60 messages on /odom, 59 can be read: missing message 23 "
                                               r"\(log time 1.150 s") as refused:
        sources.observations_of(bag_config(robot, **change), model)
    assert "--partial reads the" in str(refused.value) and "\n" not in str(refused.value)
    data = sources.observations_of(bag_config(robot, **change, partial=True), model)
    assert len(data.sensors) == 33 and "read 59 of the 60 messages on /odom the bag declares (--partial)" in \
        data.problem


def decoded(item):
    """The message of a log's item, or None (a payload dtpf does not decode)."""
    try:
        return decode_for_key(item.topic, item.data)
    except MessageError:
        return None


@needs_ros2
def test_live_ros2_topics_drive_the_twin_to_the_files_numbers_and_the_log_verifies(processes, robot, reference,
                                                                                   tmp_path):
    """Two sensor topics and an Odometry control, played by an rclpy node from the bag
    (docs/examples/play_bag.py): dtpf launch (a bridge of three topics; the sensors' field paths from a ROS 2
    parameters file, the control's by its type) gives dtpf run's estimates on the CSV files, each step
    stamped with its message's header stamp. The twin stops at 22 steps: the last second of the bag releases
    them from the reorder window."""
    env = ros_env()
    (tmp_path / "robot.yaml").write_text(
        "dtpf_robot_1:\n  ros__parameters:\n    sensors:\n"
        f"      gps: {{fields: '{FIELDS['gps']}', type: geometry_msgs/msg/PointStamped}}\n"
        f"      beacons: {{fields: '{FIELDS['beacons']}'}}\n")
    player = start(processes, "player", [str(ROOT / "docs/examples/play_bag.py"), str(robot["bag"]), "--topics",
                                         "/gps,/beacons,/odom", "--wait", "240"], env)
    log = tmp_path / "robot.mcap"
    launcher = start(processes, "launch", [
        "-m", "dtpf.scripts.cli", "launch", "-q", "--policy", "fixed", "--model", MODEL, "-n", str(RUN["particles"]), "--seed",
        str(RUN["seed"]), "--twin", RUN["twin"], "--steps", "22", "--reorder-window", "1.0",
        "--observations", "gps=ros2:/gps", "--observations", "beacons=ros2:/beacons", "--controls", "ros2:/odom",
        "--ros2-params", str(tmp_path / "robot.yaml"), "--port", str(free_port()), "-o", str(log)], env)
    wait_for_line(processes, player, "played 93 messages", 240, watch=launcher)
    assert launcher.wait(timeout=240) == 0, processes.output(launcher)

    logged = [message for message in map(decoded, read_log(log).messages) if message is not None]
    estimates = {m.step: m for m in logged if isinstance(m, Estimate)}
    observations = [m for m in logged if isinstance(m, Observation)]
    controls = [m for m in logged if isinstance(m, Control)]
    assert sorted(estimates) == list(range(1, 23))
    np.testing.assert_array_equal([estimates[k].mean for k in range(1, 23)], reference.means[:22])
    assert [estimates[k].sensor for k in range(1, 23)] == [s.sensor for s in reference.steps[:22]]
    data = sources.observations_of(bag_config(robot), resolve(str(ROOT / MODEL)))
    assert [estimates[k].stamp.to_ns() for k in range(1, 23)] == data.stamps[:22].tolist()  # the header stamps
    assert {o.sensor for o in observations} == {"gps", "beacons"} and len(controls) >= 40
    assert [c.stamp.to_ns() for c in controls[:3]] == [50_000_000, 100_000_000, 150_000_000]
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "verify", str(log)], cwd=ROOT,
                          capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "22 propagated sets reproduced bit for bit" in done.stdout


@needs_ros2
def test_dtpf_launch_checks_each_topic_before_anything_starts(processes, tmp_path):
    """A misspelt field path of one sensor (its type in the parameters file) and a control type without a
    default for a two-control model: one line, exit 2, no log."""
    (tmp_path / "typed.yaml").write_text(
        "/**:\n  ros__parameters:\n    sensors:\n      gps: {type: geometry_msgs/msg/PointStamped}\n"
        "      beacons: {type: geometry_msgs/msg/Vector3Stamped}\n"
        "    control: {type: sensor_msgs/msg/Range}\n")
    base = ["-m", "dtpf.scripts.cli", "launch", "-q", "--model", MODEL, "--twin", "robot-1",
            "--observations", "gps=ros2:/gps", "--observations", "beacons=ros2:/beacons", "--controls", "ros2:/odom",
            "--ros2-params", str(tmp_path / "typed.yaml")]
    cases = [(["--ros2-fields", "gps=point.x,point.q", "--ros2-fields", f"beacons={FIELDS['beacons']}"],
              "--ros2-fields: geometry_msgs/msg/PointStamped has no field 'point.q'"),
             (["--ros2-fields", f"gps={FIELDS['gps']}", "--ros2-fields", f"beacons={FIELDS['beacons']}"],
              "--controls ros2:/odom: say how a sensor_msgs/msg/Range becomes the control (v, omega)")]
    # the topics too from the file (no --observations): its misspelt path is found the same way
    (tmp_path / "topics.yaml").write_text(
        "dtpf_robot_1:\n  ros__parameters:\n    sensors:\n"
        "      gps: {topic: /gps, type: geometry_msgs/msg/PointStamped, fields: 'point.x,point.q'}\n"
        f"      beacons: {{topic: /beacons, type: geometry_msgs/msg/Vector3Stamped, fields: '{FIELDS['beacons']}'}}\n"
        "    control: {topic: /odom, type: nav_msgs/msg/Odometry}\n")
    cases.append((["--ros2-params", str(tmp_path / "topics.yaml")],
                  "--ros2-fields: geometry_msgs/msg/PointStamped has no field 'point.q'"))
    cases.append((["--observations", "lidar=ros2:/scan", "--ros2-fields", f"gps={FIELDS['gps']}"],
                  "--observations lidar=ros2:...: the model has no sensor 'lidar'"))
    for i, (options, expected) in enumerate(cases):
        log = tmp_path / f"never-{i}.mcap"
        command = base[:base.index("--observations")] if i == 2 else base
        launcher = start(processes, "launch", [*command, *options, "-o", str(log)], ros_env())
        assert launcher.wait(timeout=120) == 2, processes.output(launcher)
        lines = processes.output(launcher).strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"dtpf launch: error: {expected}"), lines
        assert not log.exists()


def test_dtpf_sensor_replays_a_bag_with_its_own_stamps(robot, processes, router):
    """A bag's topic (one sensor) and the unicycle's sensors and odometry: every observation and control
    goes out with its message's header stamp, not the time it is sent."""
    bag = robot["bag"]
    common = ["-m", "dtpf.scripts.sensor", "--connect", router.endpoint, "--wait-for-entity", "0",
              "--resume-wait", "0", "--log-level", "WARNING"]
    one = processes.start("sensor", [*common, "--model", "docs/examples/range_bearing.py:RangeBearingTarget",
                                     "--twin", "one", "--observations", str(bag), "--topic", "/gps",
                                     "--ros2-fields", "point.x,point.y", "--rate", "0"])
    driven = processes.start("sensor", [*common, "--model", MODEL, "--twin", "robot-1", "--speed", "0",
                                        *[f"--observations={name}={bag}:/{name}" for name in FIELDS],
                                        *[f"--ros2-fields={name}={paths}" for name, paths in FIELDS.items()],
                                        "--controls", f"{bag}:/odom",
                                        "--ros2-control-fields", "twist.twist.linear.x,twist.twist.angular.z"])
    assert one.wait(timeout=120) == 0, processes.output(one)
    assert driven.wait(timeout=120) == 0, processes.output(driven)

    def sent(messages, twin, cls):
        return [m for m in messages if isinstance(m, cls) and m.twin_id == twin and not m.end]

    router.collect(lambda m: len(sent(m, "one", Observation)) >= 3 and len(sent(m, "robot-1", Observation)) >= 33
                   and len(sent(m, "robot-1", Control)) >= 60, timeout=60)
    assert [o.stamp.to_ns() for o in sent(router.messages, "one", Observation)] == [10**9, 2 * 10**9, 3 * 10**9]
    data = sources.observations_of(bag_config(robot), resolve(str(ROOT / MODEL)))
    observations = sent(router.messages, "robot-1", Observation)
    assert [(o.sensor, o.stamp.to_ns()) for o in observations] == list(zip(data.sensors, data.stamps.tolist()))
    assert [c.stamp.to_ns() for c in sent(router.messages, "robot-1", Control)] == \
        [k * 50_000_000 for k in range(1, 61)]
