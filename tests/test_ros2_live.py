"""A twin inside a ROS 2 system, with real rclpy nodes: a publisher at 50 Hz drives dtpf launch
--observations ros2:TOPIC to the numbers of dtpf run on the same observations from a file, and a
subscriber receives and decodes every estimate and particle array the bridge publishes.

rclpy comes from the ROS 2 wheels, which add a startup hook to every Python process of their environment,
so they live in an environment of their own: ``.venv-ros2`` beside ``.venv`` (``.ci/run`` makes it), or the
Python that DTPF_ROS2_PYTHON names. Without one the tests skip and say so. Each test takes its own
ROS_DOMAIN_ID, discovery stays on localhost, Zenoh on 127.0.0.1."""
from __future__ import annotations

import csv
import json
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dtpf.messages.codec import MessageError, decode_for_key
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate, Observation, Status
from dtpf.recording.logfile import read_log
from dtpf.scripts import inprocess
from dtpf.shell.bus import free_port

from conftest import ROOT

EXAMPLE = "docs/examples/range_bearing.py:RangeBearingTarget"
EXAMPLE_NO_TRUTH = "docs/examples/range_bearing_no_truth.csv"


def ros2_python() -> str | None:
    """A Python with rclpy and dtpf, or None."""
    candidates = [os.environ.get("DTPF_ROS2_PYTHON"), str(ROOT / ".venv-ros2" / "bin" / "python")]
    for python in filter(None, candidates):
        if Path(python).exists():
            done = subprocess.run([python, "-c", "import rclpy, dtpf.scripts.ros2.bridge"], capture_output=True,
                                  timeout=120)
            if done.returncode == 0:
                return python
    return None


PYTHON = ros2_python()
needs_ros2 = pytest.mark.skipif(PYTHON is None, reason="no Python with rclpy and dtpf: make one with "
                                "python3 -m venv .venv-ros2 && .venv-ros2/bin/pip install -e '.[ros2]' "
                                "(.ci/run does), or name it in DTPF_ROS2_PYTHON")

PUBLISHER = r'''
import csv, math, os, sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
from geometry_msgs.msg import PointStamped
path, topic, rate, count, nan_after = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
reliability = ReliabilityPolicy.BEST_EFFORT if sys.argv[6:7] == ["best_effort"] else ReliabilityPolicy.RELIABLE
go = sys.argv[7] if len(sys.argv) > 7 else None  # a file: publish once it exists (the test's subscriber is ready)
rows = [(float(r["range"]), float(r["bearing"])) for r in csv.DictReader(open(path))][:count]
rclpy.init()
node = rclpy.create_node("test_publisher")
pub = node.create_publisher(PointStamped, topic, QoSProfile(depth=1000, reliability=reliability,
                                                            history=HistoryPolicy.KEEP_LAST))
deadline = time.monotonic() + 240
while pub.get_subscription_count() < 1 or (go is not None and not os.path.exists(go)):
    if time.monotonic() > deadline:
        sys.exit("no subscriber in 240 s")
    rclpy.spin_once(node, timeout_sec=0.05)
print("matched", flush=True)
messages = [(1_796_160_000 + i // 20, (i % 20) * 50_000_000 + 7, r, b) for i, (r, b) in enumerate(rows)]  # 20 Hz stamps
if nan_after:
    messages.insert(nan_after, (999, 0, math.nan, 0.5))  # not a measurement: the bridge counts it, sends nothing
t0 = time.monotonic()
for i, (sec, nsec, r, b) in enumerate(messages):
    m = PointStamped()
    m.header.frame_id = "radar"
    m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
    m.point.x, m.point.y = r, b
    pub.publish(m)
    time.sleep(max(0.0, t0 + (i + 1) / rate - time.monotonic()))
pub.wait_for_all_acked(rclpy.duration.Duration(seconds=30))
print("published", len(messages), flush=True)
'''

SUBSCRIBER = r'''
import json, sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from std_msgs.msg import Bool, Float64
ns, count, out = sys.argv[1], int(sys.argv[2]), open(sys.argv[3], "w")
rclpy.init()
node = rclpy.create_node("test_subscriber")
qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
got = {"pose": 0, "particles": 0, "ess": 0, "odom": 0}
def odom(m):
    got["odom"] += 1
    p = m.pose.pose.position
    out.write(json.dumps({"topic": "odom", "x": p.x, "y": p.y, "cov": list(m.pose.covariance),
                          "twist_cov": list(m.twist.covariance), "stamp": [m.header.stamp.sec, m.header.stamp.nanosec],
                          "frame": m.header.frame_id, "child": m.child_frame_id}) + "\n")
def pose(m):
    got["pose"] += 1
    p = m.pose.pose.position
    out.write(json.dumps({"topic": "pose", "x": p.x, "y": p.y, "cov": list(m.pose.covariance),
                          "stamp": [m.header.stamp.sec, m.header.stamp.nanosec], "frame": m.header.frame_id}) + "\n")
def particles(m):
    got["particles"] += 1
    out.write(json.dumps({"topic": "particles", "n": len(m.poses), "x0": m.poses[0].position.x}) + "\n")
def ess(m):
    got["ess"] += 1
subs = [node.create_subscription(PoseWithCovarianceStamped, ns + "/pose", pose, qos),
        node.create_subscription(PoseArray, ns + "/particles", particles, qos),
        node.create_subscription(Float64, ns + "/ess", ess, qos),
        node.create_subscription(Odometry, ns + "/odom", odom, qos)]
deadline = time.monotonic() + 300
while min(s.get_publisher_count() for s in subs) < 1:
    if time.monotonic() > deadline:
        sys.exit("no publisher in 300 s")
    rclpy.spin_once(node, timeout_sec=0.05)
print("ready", flush=True)
while min(got.values()) < count and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.1)
out.close()
print("received", json.dumps(got), flush=True)
'''


def published_stamp(k: int) -> list[int]:
    """The header stamp [sec, nanosec] of PUBLISHER's k-th message (1, 2, ...): 20 Hz from 2026-12-01, + 7 ns."""
    return [1_796_160_000 + (k - 1) // 20, (k - 1) % 20 * 50_000_000 + 7]


def ros_env() -> dict:
    """Discovery on localhost only, a domain of this test's own."""
    return dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(random.randint(1, 100)),
                PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")


def start(processes, name: str, args: list[str], env: dict):
    """A process of the ROS 2 Python, stopped by the ``processes`` fixture (pass or fail)."""
    log = open(processes.log_dir / f"{name}-{len(processes.started)}.log", "wb")
    process = subprocess.Popen([PYTHON, *args], stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=env,
                               start_new_session=True)
    process.name, process.log_path = name, log.name
    processes.started.append(process)
    return process


def wait_for_line(processes, process, text: str, timeout: float, watch=None) -> None:
    """Until ``process`` says ``text``; fails when it (or ``watch``) ends first, or after ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if text in processes.output(process):
            return
        if process.poll() is not None:
            break
        if watch is not None and watch.poll() is not None:
            pytest.fail(f"{watch.name} ended (code {watch.returncode}):\n{processes.output(watch)}")
        time.sleep(0.05)
    assert text in processes.output(process), f"{process.name} did not say {text!r}:\n{processes.output(process)}"


@needs_ros2
@pytest.mark.parametrize("secure", [False, True], ids=["plain", "secured"])
def test_a_ros2_publisher_drives_the_twin_to_dtpf_run_numbers_and_a_subscriber_gets_every_estimate(
        processes, tmp_path, secure):
    """Plain: the publisher offers best effort only (as sensor drivers do), the frames come from a ROS 2
    parameters file; secured: a reliable publisher, the default frames. A subscriber of the twin's pose and
    odometry gets every estimate, its stamp the observation's to the nanosecond, the axes the state lacks
    marked unknown."""
    steps, n = (20, 300) if secure else (60, 500)
    env = ros_env()
    extra = []
    if secure:  # the bridge publishes in the sensor role, reads the twin in the viewer role
        done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "secure", "init", str(tmp_path / "sec")],
                              cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        extra = ["--secure", str(tmp_path / "sec" / "tls")]
        frame, child, reliability = "map", "base_link", "reliable"
    else:
        (tmp_path / "bridge.yaml").write_text("dtpf_rb_ros:\n  ros__parameters:\n    frame: world\n"
                                              "    child_frame: '{twin}_base'\n")
        extra = ["--ros2-params", str(tmp_path / "bridge.yaml")]
        frame, child, reliability = "world", "rb_ros_base", "best_effort"
    (tmp_path / "pub.py").write_text(PUBLISHER)
    (tmp_path / "sub.py").write_text(SUBSCRIBER)
    received = tmp_path / "received.jsonl"
    subscriber = start(processes, "subscriber", [str(tmp_path / "sub.py"), "/dtpf/rb_ros", str(steps),
                                                 str(received)], env)
    # The launcher learns the topic's type from its publisher before it starts anything; the publisher sends
    # once the bridge has subscribed and the subscriber has the bridge's topics (the file ``go``).
    go = tmp_path / "go"
    publisher = start(processes, "publisher", [str(tmp_path / "pub.py"), EXAMPLE_NO_TRUTH, "/target", "50",
                                               str(steps), "10", reliability, str(go)], env)
    log = tmp_path / "ros2.mcap"
    launcher = start(processes, "launch", ["-m", "dtpf.scripts.cli", "launch", "-q", "--policy", "fixed", "--model", EXAMPLE,
                                           "--observations", "ros2:/target", "--ros2-fields", "point.x,point.y",
                                           "-n", str(n), "--steps", str(steps), "--twin", "rb-ros",
                                           "--port", str(free_port()), "-o", str(log), *extra], env)
    wait_for_line(processes, subscriber, "ready", 240, watch=launcher)  # the bridge's publishers are matched
    go.touch()
    wait_for_line(processes, publisher, f"published {steps + 1}", 240, watch=launcher)
    assert launcher.wait(timeout=240) == 0, processes.output(launcher)
    assert subscriber.wait(timeout=120) == 0, processes.output(subscriber)
    assert f'received {{"pose": {steps}, "particles": {steps}, "ess": {steps}, "odom": {steps}}}' in \
        processes.output(subscriber)
    said = processes.output(launcher)
    assert ("offers best-effort QoS only: the bridge subscribes best effort" in said) == (not secure), said
    assert "/tf not published: tf2_msgs cannot be imported here: it has no wheel on PyPI" in said, said

    # The twin's estimates equal dtpf run on the same observations from the file, number for number.
    estimates, observations, statuses = {}, [], []
    for item in read_log(log).messages:
        try:
            message = decode_for_key(item.topic, item.data)
        except MessageError:
            continue
        if isinstance(message, Estimate):
            estimates[message.step] = message
        elif isinstance(message, Observation):
            observations.append(message)
        elif isinstance(message, Status) and message.layer == "sensor":
            statuses.append(message)
    reference = inprocess.run(RunConfig(model=EXAMPLE, observations=EXAMPLE_NO_TRUTH, particles=n, steps=steps,
                                        twin="rb-ros"))
    means = np.array([estimates[k].mean for k in range(1, steps + 1)])
    np.testing.assert_array_equal(means, reference.means)
    # The header stamps travelled with the observations and are in the log, to the nanosecond.
    assert [(o.step, [o.stamp.sec, o.stamp.nsec]) for o in observations] == \
        [(k, published_stamp(k)) for k in range(1, steps + 1)]
    # The NaN message was counted by the bridge, never sent.
    assert any(r.name.startswith("a ROS message with a NaN") and r.count == 1
               for s in statuses for r in s.rejections), [s.rejections for s in statuses]

    # The subscriber decoded every estimate: the pose is the estimate's mean, its covariance the variances.
    lines = [json.loads(line) for line in received.read_text().splitlines()]
    poses = [x for x in lines if x["topic"] == "pose"]
    odoms = [x for x in lines if x["topic"] == "odom"]
    assert [(p["x"], p["y"]) for p in poses] == [(e.mean[0], e.mean[1]) for e in (estimates[k] for k in
                                                                                  range(1, steps + 1))]
    assert [(p["cov"][0], p["cov"][7]) for p in poses] == [(estimates[k].var[0], estimates[k].var[1])
                                                            for k in range(1, steps + 1)]
    # The x-y covariance is the estimate's own (the pose went out with its estimate).
    assert [(p["cov"][1], p["cov"][6]) for p in poses] == [(estimates[k].covariance[0],) * 2
                                                            for k in range(1, steps + 1)]
    # The odometry is the same pose, in the configured frames; every stamp is the observation's.
    assert [(o["x"], o["y"], o["cov"]) for o in odoms] == [(p["x"], p["y"], p["cov"]) for p in poses]
    assert [p["stamp"] for p in poses] == [o["stamp"] for o in odoms] == [published_stamp(k)
                                                                          for k in range(1, steps + 1)]
    assert {p["frame"] for p in poses} == {o["frame"] for o in odoms} == {frame}
    assert {o["child"] for o in odoms} == {child}
    # z, roll, pitch and yaw are not in the state: unknown (a large variance), not known perfectly (0).
    unknown = 1e6
    for message in poses + odoms:
        covariance = np.array(message["cov"]).reshape(6, 6)
        assert [covariance[i, i] for i in (2, 3, 4, 5)] == [unknown] * 4
        assert np.count_nonzero(covariance[2:, :]) == 4
    assert all(o["twist_cov"] == np.diag([unknown] * 6).reshape(36).tolist() for o in odoms)
    assert all(x["n"] == n for x in lines if x["topic"] == "particles")
    if secure:
        return
    # dtpf export --ros2 of the run's log stamps each pose, odometry and transform as the bridge did.
    out = tmp_path / "exported"
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "export", "--ros2", str(log), str(out),
                           "--ros2-params", str(tmp_path / "bridge.yaml")], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([out], default_typestore=get_typestore(Stores.ROS2_KILTED)) as reader:
        headers = {"/dtpf/rb_ros/pose": [], "/dtpf/rb_ros/odom": [], "/tf": []}
        for connection, _, raw in reader.messages([c for c in reader.connections if c.topic in headers]):
            message = reader.deserialize(raw, connection.msgtype)
            for header in [t.header for t in message.transforms] if connection.topic == "/tf" else [message.header]:
                headers[connection.topic].append([header.frame_id, header.stamp.sec, header.stamp.nanosec])
    assert all(found == [[frame, *published_stamp(k)] for k in range(1, steps + 1)] for found in headers.values()), \
        headers


@needs_ros2
def test_a_field_path_the_type_does_not_have_is_one_line_at_start(processes, router, tmp_path):
    bridge = start(processes, "bridge", ["-m", "dtpf.scripts.cli", "ros2", "--model", EXAMPLE, "--topic", "/r",
                                         "--ros2-type", "sensor_msgs/msg/Range", "--ros2-fields", "rnge",
                                         "--connect", router.endpoint], ros_env())
    assert bridge.wait(timeout=120) == 2
    lines = processes.output(bridge).strip().splitlines()
    assert len(lines) == 1 and "sensor_msgs/msg/Range has no field 'rnge'" in lines[0], lines
    bridge = start(processes, "bridge", ["-m", "dtpf.scripts.cli", "ros2", "--model", EXAMPLE, "--topic", "/r",
                                         "--ros2-type", "sensor_msgs/msg/Nope", "--connect", router.endpoint],
                   ros_env())
    assert bridge.wait(timeout=120) == 2
    assert "sensor_msgs.msg has no Nope" in processes.output(bridge)


@needs_ros2
def test_dtpf_launch_checks_every_field_path_and_parameter_before_anything_starts(processes, tmp_path):
    """A misspelt --ros2-fields path (the type given on the command line or in --ros2-params) or an unknown
    parameter is one line and exit 2 from the launcher, before a layer or the bridge starts (no log)."""
    (tmp_path / "typed.yaml").write_text("/**:\n  ros__parameters:\n    type: sensor_msgs/msg/Range\n")
    (tmp_path / "misspelt.yaml").write_text("dtpf_rb:\n  ros__parameters:\n    fields: range\n    frme: odom\n")
    cases = [(["--ros2-type", "sensor_msgs/msg/Range", "--ros2-fields", "rnge"],
              "--ros2-fields: sensor_msgs/msg/Range has no field 'rnge'"),
             (["--ros2-params", str(tmp_path / "typed.yaml"), "--ros2-fields", "range,rnge"],
              "--ros2-fields: sensor_msgs/msg/Range has no field 'rnge'"),
             (["--ros2-params", str(tmp_path / "misspelt.yaml")],
              f"--ros2-params {tmp_path / 'misspelt.yaml'}: unknown parameter 'frme' (known: topic, type, fields")]
    for i, (options, expected) in enumerate(cases):
        log = tmp_path / f"never-{i}.mcap"
        launcher = start(processes, "launch", ["-m", "dtpf.scripts.cli", "launch", "-q", "--model", EXAMPLE,
                                               "--observations", "ros2:/r", "--twin", "rb", "-o", str(log),
                                               *options], ros_env())
        assert launcher.wait(timeout=120) == 2, processes.output(launcher)
        lines = processes.output(launcher).strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"dtpf launch: error: {expected}"), lines
        assert not log.exists()


def test_without_rclpy_a_ros2_option_says_what_to_install():
    from dtpf.scripts.ros2 import have_rclpy
    if have_rclpy():
        pytest.skip("this Python has rclpy")
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "launch", "--observations", "ros2:/range"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == ["dtpf launch: error: live ROS 2 topics need rclpy: pip install "
                                                "'dtpf[ros2]' (the ROS 2 Kilted wheels, about 150 MB; best in a "
                                                "virtual environment of its own, see docs/guides/ros2.md)"]


@needs_ros2
def test_a_publisher_of_another_type_on_the_topic_is_named_and_counted(processes, router, tmp_path):
    env = ros_env()
    bridge = start(processes, "bridge", ["-m", "dtpf.scripts.cli", "ros2", "--model", EXAMPLE, "--topic", "/target",
                                         "--ros2-type", "sensor_msgs/msg/Range", "--ros2-fields", "range",
                                         "--wait-for-entity", "0", "--resume-wait", "0", "--no-out",
                                         "--connect", router.endpoint], env)
    wait_for_line(processes, bridge, "bridging /target (sensor_msgs/msg/Range)", 120)
    (tmp_path / "pub.py").write_text(PUBLISHER)  # geometry_msgs/msg/PointStamped, waiting for a subscriber
    start(processes, "publisher", [str(tmp_path / "pub.py"), EXAMPLE_NO_TRUTH, "/target", "50", "5", "0"], env)
    wait_for_line(processes, bridge, "/target has a publisher of geometry_msgs/msg/PointStamped; the bridge takes "
                                     "sensor_msgs/msg/Range", 120)
    assert bridge.poll() is None  # counted, not a crash
