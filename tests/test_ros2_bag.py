"""rosbag2 logs in and out: a bag written by rosbags (not by dtpf) drives dtpf run and dtpf launch to the
numbers of the CSV of the same observations; dtpf export --ros2 writes a bag rosbags reads back."""
from __future__ import annotations

import csv
import subprocess
import sys
from collections import OrderedDict

import numpy as np
import pytest

from dtpf.messages.config import RunConfig
from dtpf.scripts import inprocess
from dtpf.scripts.launch import launch
from dtpf.scripts.ros2 import convert

from conftest import ROOT

pytest.importorskip("rosbags", reason="rosbags is not installed (pip install 'dtpf[rosbag]')")

from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

EXAMPLE = "docs/examples/range_bearing.py:RangeBearingTarget"
EXAMPLE_NO_TRUTH = "docs/examples/range_bearing_no_truth.csv"
TYPESTORE = get_typestore(Stores.ROS2_KILTED)


def dtpf(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


#: 2026-12-01 as ns since the epoch: at such a time a float64 of seconds is off by up to 128 ns at 20 Hz stamps.
EPOCH = 1_796_160_000_000_000_000
#: How long after its header stamp each message of the example bag was received (its log time).
DELAY = 3_000_017


def write_bag(path, rows, *, nan_at: int | None = None, topic: str = "/target", start: int = 1_000_000_000_000,
              delay: int = 0) -> None:
    """The (range, bearing) rows as geometry_msgs/msg/PointStamped (point.x, point.y) on ``topic``, header
    stamps at 20 Hz from ``start`` ns (default t = 1000 s), each logged ``delay`` ns after its stamp, with a
    std_msgs/msg/String on another topic between them."""
    types = TYPESTORE.types
    point_stamped, header, time, point = (types["geometry_msgs/msg/PointStamped"], types["std_msgs/msg/Header"],
                                          types["builtin_interfaces/msg/Time"], types["geometry_msgs/msg/Point"])
    text = types["std_msgs/msg/String"]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        target = writer.add_connection(topic, point_stamped.__msgtype__, typestore=TYPESTORE)
        other = writer.add_connection("/chatter", text.__msgtype__, typestore=TYPESTORE)
        for i, (r, b) in enumerate(rows):
            ns = start + i * 50_000_000
            x = float("nan") if i == nan_at else r
            message = point_stamped(header=header(stamp=time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="radar"),
                                    point=point(x=x, y=b, z=0.0))
            writer.write(target, ns + delay, TYPESTORE.serialize_cdr(message, point_stamped.__msgtype__))
            writer.write(other, ns + delay + 1, TYPESTORE.serialize_cdr(text(data=f"row {i}"), text.__msgtype__))


def example_rows() -> list[tuple[float, float]]:
    with open(ROOT / EXAMPLE_NO_TRUTH) as file:
        return [(float(row["range"]), float(row["bearing"])) for row in csv.DictReader(file)]


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bag") / "radar"
    write_bag(path, example_rows(), start=EPOCH, delay=DELAY)
    return path


def test_a_bag_written_by_rosbags_drives_dtpf_run_to_the_csv_numbers(bag, monkeypatch):
    monkeypatch.chdir(ROOT)
    common = dict(model=EXAMPLE, particles=500, steps=40, seed=3, twin="rb-bag")
    reference = inprocess.run(RunConfig(observations=EXAMPLE_NO_TRUTH, **common))
    for source in (bag, bag / "radar.mcap"):  # the folder, or its .mcap file
        result = inprocess.run(RunConfig(observations=str(source), topic="/target", ros2_fields="point.x,point.y",
                                         **common))
        np.testing.assert_array_equal(result.means, reference.means)
        np.testing.assert_array_equal(result.log_predictive, reference.log_predictive)
    done = dtpf("run", "-q", "--model", EXAMPLE, "--observations", str(bag), "--topic", "/target",
                "--ros2-fields", "point.x,point.y", "-n", "500", "--seed", "3", "--twin", "rb-bag", "--policy", "fixed")
    csv_done = dtpf("run", "-q", "--model", EXAMPLE, "--observations", EXAMPLE_NO_TRUTH, "-n", "500", "--seed", "3",
                    "--twin", "rb-bag", "--policy", "fixed")
    assert done.returncode == 0, done.stderr
    line = [x for x in done.stdout.splitlines() if x.startswith("log predictive")]
    assert line and line == [x for x in csv_done.stdout.splitlines() if x.startswith("log predictive")]
    assert "T = 100" in done.stdout  # every message of the topic, one step each; the other topic is not read


@pytest.fixture(scope="module")
def bag_launch(bag, tmp_path_factory):
    """dtpf launch of 30 steps of the bag: its configuration, result and log."""
    config = RunConfig(model=EXAMPLE, observations=str(bag / "radar.mcap"), topic="/target",
                       ros2_fields="point.x,point.y", particles=500, steps=30, seed=3, twin="rb-bag")
    log = tmp_path_factory.mktemp("bag-launch") / "bag-launch.mcap"
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(ROOT)
        result = launch(config, log_path=log, timeout=5.0)
    return config, result, log


def test_a_bag_drives_dtpf_launch_to_the_csv_numbers_and_exports_back_to_rosbag2(bag_launch, tmp_path,
                                                                                 monkeypatch):
    monkeypatch.chdir(ROOT)
    config, result, log = bag_launch
    assert result.exit_codes == {"recorder": 0, "system": 0, "information": 0, "entity": 0}
    reference = inprocess.run(config.model_copy(update={"observations": EXAMPLE_NO_TRUTH, "topic": None,
                                                        "ros2_fields": None}))
    estimates = sorted(result.estimates, key=lambda e: e.step)
    np.testing.assert_array_equal(np.array([e.mean for e in estimates]), reference.means)

    # dtpf export --ros2: a rosbag2 folder that rosbags (not dtpf) reads back, every estimate equal.
    out = tmp_path / "exported"
    done = dtpf("export", "--ros2", str(log), str(out), "--ros2-pose", "x=0,y=1", "--ros2-frame", "world",
                "--ros2-child-frame", "{twin}_base")
    assert done.returncode == 0, done.stderr
    assert (out / "metadata.yaml").is_file()
    with Reader(out) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics["/dtpf/rb_bag/pose"] == "geometry_msgs/msg/PoseWithCovarianceStamped"
        assert topics["/dtpf/rb_bag/odom"] == "nav_msgs/msg/Odometry"
        assert topics["/tf"] == "tf2_msgs/msg/TFMessage"
        assert topics["/dtpf/rb_bag/particles"] == "geometry_msgs/msg/PoseArray"
        assert topics["/dtpf/rb_bag/observation"] == "std_msgs/msg/Float64MultiArray"
        assert topics["/dtpf/rb_bag/ess"] == "std_msgs/msg/Float64"
        poses, odoms, transforms, ess, clouds, observed = [], [], [], [], 0, []
        for connection, _, raw in reader.messages():
            message = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            if connection.topic.endswith("/pose"):
                poses.append(message)
            elif connection.topic.endswith("/odom"):
                odoms.append(message)
            elif connection.topic == "/tf":
                transforms.extend(message.transforms)
            elif connection.topic.endswith("/ess"):
                ess.append(message.data)
            elif connection.topic.endswith("/particles"):
                clouds += 1
                assert len(message.poses) == 500
            elif connection.topic.endswith("/observation"):
                observed.append(list(message.data))
    assert len(poses) == len(odoms) == len(transforms) == 30 and clouds == 30
    unknown = convert.UNKNOWN_VARIANCE
    for pose, odom, transform, estimate in zip(poses, odoms, transforms, estimates):
        stamp = EPOCH + (estimate.step - 1) * 50_000_000
        for header in (odom.header, transform.header):
            assert (header.frame_id, header.stamp.sec * 10**9 + header.stamp.nanosec) == ("world", stamp)
        assert odom.child_frame_id == transform.child_frame_id == "rb_bag_base"
        position = (estimate.mean[0], estimate.mean[1], 0.0)
        assert (odom.pose.pose.position.x, odom.pose.pose.position.y, odom.pose.pose.position.z) == position
        t = transform.transform
        assert (t.translation.x, t.translation.y, t.translation.z) == position
        assert (t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w) == (0.0, 0.0, 0.0, 1.0)
        np.testing.assert_array_equal(odom.pose.covariance, pose.pose.covariance)
        # z, roll, pitch and yaw are not in the state: unknown by a large variance, none between axes.
        covariance = pose.pose.covariance.reshape(6, 6)
        assert [covariance[i, i] for i in (2, 3, 4, 5)] == [unknown] * 4
        assert np.count_nonzero(covariance[2:, :]) == np.count_nonzero(covariance[:, 2:]) == 4
        assert (odom.twist.covariance.reshape(6, 6) == np.eye(6) * unknown).all()
        assert (odom.twist.twist.linear.x, odom.twist.twist.angular.z) == (0.0, 0.0)
    for pose, estimate in zip(poses, estimates):
        assert (pose.pose.pose.position.x, pose.pose.pose.position.y) == (estimate.mean[0], estimate.mean[1])
        covariance = pose.pose.covariance.reshape(6, 6)
        assert (covariance[0, 0], covariance[1, 1]) == (estimate.var[0], estimate.var[1])
        assert covariance[0, 1] == covariance[1, 0] == estimate.covariance[0] != 0.0  # the estimate's own
        assert pose.header.frame_id == "world"
        assert (pose.header.stamp.sec, pose.header.stamp.nanosec) == (estimate.stamp.sec, estimate.stamp.nsec)
        assert pose.header.stamp.sec * 10**9 + pose.header.stamp.nanosec == EPOCH + (estimate.step - 1) * 50_000_000
    assert ess == [e.ess for e in estimates]
    assert observed == [e.observation for e in estimates]


def test_the_header_stamp_of_each_message_is_the_stamp_of_its_estimate_to_the_nanosecond(bag_launch):
    """The message's header stamp becomes the step time, as on a live topic (not the bag's receive time, DELAY
    later): each estimate of a launch driven by a bag carries it to the nanosecond, at 20 Hz from EPOCH (where
    seconds as a float64 are off by up to 128 ns every other step)."""
    _, result, _ = bag_launch
    estimates = sorted(result.estimates, key=lambda e: e.step)
    assert [e.step for e in estimates] == list(range(1, 31))
    expected = [EPOCH + (k - 1) * 50_000_000 for k in range(1, 31)]
    assert sum(round(ns / 1e9, 9) * 10**9 != ns for ns in expected) > 0  # a float would not carry them
    assert [e.stamp.to_ns() for e in estimates] == expected


def test_a_message_without_a_header_stamp_takes_its_receive_time():
    from dtpf.entity.rosbag import stamp_ns

    types = TYPESTORE.types
    stamped = types["geometry_msgs/msg/PointStamped"](
        header=types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=7, nanosec=1_500_000_000),
                                            frame_id="radar"),
        point=types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0))
    assert stamp_ns(stamped) == 8_500_000_000  # nanosec carried into the seconds
    zero = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="")
    assert stamp_ns(types["geometry_msgs/msg/PointStamped"](header=zero, point=stamped.point)) is None
    assert stamp_ns(types["std_msgs/msg/Float64"](data=1.0)) is None


@pytest.mark.parametrize("case, extra, expected", [
    ("no such topic", ["--topic", "/nope", "--ros2-fields", "point.x,point.y"],
     r"no topic '/nope' in the bag \(it has: /chatter \(std_msgs/msg/String\), /target"),
    ("missing field", ["--topic", "/target", "--ros2-fields", "point.x,point.w"],
     r"has no field 'point.w' \('w' is not one of x, y, z\)"),
    ("not a number", ["--topic", "/target", "--ros2-fields", "point"], r"is a geometry_msgs/msg/Point, not a number"),
    ("wrong length", ["--topic", "/target", "--ros2-fields", "point.x"], r"1 value, the model observes 2"),
    ("no mapping", ["--topic", "/target"], r"--ros2-fields .* or a method observation_from_ros2"),
    ("no topic", ["--ros2-fields", "point.x,point.y"], r"name the topic to filter with --topic"),
    ("bad path", ["--topic", "/target", "--ros2-fields", "point..x"], r"is not a field path"),
])
def test_a_bad_bag_option_is_one_line_and_exit_2(bag, case, extra, expected):
    done = dtpf("run", "-q", "--model", EXAMPLE, "--observations", str(bag), *extra)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert __import__("re").search(expected, lines[0]), lines[0]


def test_a_nan_in_a_bag_is_one_line(tmp_path):
    nan_bag = tmp_path / "nan"
    write_bag(nan_bag, example_rows()[:10], nan_at=6)
    done = dtpf("run", "-q", "--model", EXAMPLE, "--observations", str(nan_bag), "--topic", "/target",
                "--ros2-fields", "point.x,point.y")
    assert done.returncode == 2 and "message 7 on /target: nan (observations must be finite)" in done.stderr, \
        done.stderr


def test_a_cut_bag_is_read_up_to_the_cut_and_says_so(tmp_path):
    """A bag whose recording did not end (its MCAP file cut in the middle, no summary or footer) runs on the
    messages before the cut, the same numbers as the whole bag cut to that many steps, and says so."""
    whole = tmp_path / "whole"
    write_bag(whole, example_rows())
    data = (whole / "whole.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    common = ("--model", EXAMPLE, "--topic", "/target", "--ros2-fields", "point.x,point.y", "-n", "300", "--policy", "fixed")
    done = dtpf("run", "-q", "--observations", str(cut), *common)
    assert done.returncode == 0, done.stdout + done.stderr
    steps = int(done.stdout.split("T = ")[1].split(",")[0])
    assert f"was cut short: read up to the cut, where {steps} messages of /target end" in done.stderr, done.stderr
    assert 5 <= steps < len(example_rows()), done.stdout
    again = dtpf("run", "-q", "--observations", str(whole), "--steps", str(steps), *common)
    assert again.returncode == 0 and "cut short" not in again.stderr, again.stderr
    figures = [line for line in done.stdout.splitlines() if line.startswith(("log predictive", "mean ESS"))]
    assert len(figures) == 2 and figures == [line for line in again.stdout.splitlines()
                                             if line.startswith(("log predictive", "mean ESS"))]
    # Cut inside the header: nothing to read, one line.
    head = tmp_path / "head.mcap"
    head.write_bytes(data[:20])
    done = dtpf("run", "-q", "--observations", str(head), *common)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_the_model_may_map_a_message_itself(bag, tmp_path, monkeypatch):
    """Without --ros2-fields, the model's observation_from_ros2(message) makes the values."""
    monkeypatch.chdir(ROOT)
    model = tmp_path / "mapped.py"
    model.write_text("import sys\nsys.path.insert(0, 'docs/examples')\n"
                     "from range_bearing import RangeBearingTarget\n\n"
                     "class Mapped(RangeBearingTarget):\n"
                     "    def observation_from_ros2(self, message):\n"
                     "        return [message.point.x, message.point.y]\n")
    common = {"particles": 300, "steps": 20, "seed": 1, "twin": "rb-map"}
    mapped = inprocess.run(RunConfig(model=f"{model}:Mapped", observations=str(bag), topic="/target", **common))
    reference = inprocess.run(RunConfig(model=EXAMPLE, observations=EXAMPLE_NO_TRUTH, **common))
    np.testing.assert_array_equal(mapped.means, reference.means)


def test_the_ros2_messages_are_the_bytes_rosbags_serialises():
    """The bridge and dtpf export --ros2 make each message's CDR bytes themselves: the same bytes as rosbags'
    serialiser (frame names of every length modulo 8, so every padding is exercised)."""
    import math

    from dtpf.scripts.ros2 import convert

    types = TYPESTORE.types

    def serialised(msgtype, **fields):
        return TYPESTORE.serialize_cdr(types[msgtype](**fields), msgtype)

    def pose(x, y, z, yaw):
        return types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
            orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))

    rng = np.random.default_rng(0)
    for frame in ("m", "ma", "map", "odom", "frame", "radar1", "laser_2", "base_link"):
        header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=1000, nanosec=5),
                                              frame_id=frame)
        covariance = rng.normal(size=36)
        poses = convert.PoseSet([1.5, -2.0, 0.25], 0.7, covariance, None)
        assert convert.pose_cdr(1000, 5, frame, poses) == serialised(
            "geometry_msgs/msg/PoseWithCovarianceStamped", header=header,
            pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose(1.5, -2.0, 0.25, 0.7), covariance=covariance))
        particles = rng.normal(size=(7, 4))
        assert convert.pose_array_cdr(1000, 5, frame, particles) == serialised(
            "geometry_msgs/msg/PoseArray", header=header, poses=[pose(*p) for p in particles.tolist()])
        for child in ("b", "base_link", "rb_1_base"):
            twist = types["geometry_msgs/msg/TwistWithCovariance"](
                twist=types["geometry_msgs/msg/Twist"](linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                       angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=np.eye(6).reshape(36) * convert.UNKNOWN_VARIANCE)
            assert convert.odometry_cdr(1000, 5, frame, child, poses) == serialised(
                "nav_msgs/msg/Odometry", header=header, child_frame_id=child, twist=twist,
                pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose(1.5, -2.0, 0.25, 0.7),
                                                                   covariance=covariance))
            placed = pose(1.5, -2.0, 0.25, 0.7)
            transform = types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](x=1.5, y=-2.0, z=0.25), rotation=placed.orientation)
            assert convert.tf_cdr(1000, 5, frame, child, poses) == serialised(
                "tf2_msgs/msg/TFMessage", transforms=[types["geometry_msgs/msg/TransformStamped"](
                    header=header, child_frame_id=child, transform=transform)])
        values = rng.normal(size=3)
        layout = types["std_msgs/msg/MultiArrayLayout"](
            dim=[types["std_msgs/msg/MultiArrayDimension"](label=frame, size=3, stride=3)], data_offset=0)
        assert convert.float64_array_cdr(values, frame) == serialised("std_msgs/msg/Float64MultiArray",
                                                                      layout=layout, data=values)
    assert convert.float64_cdr(0.125) == serialised("std_msgs/msg/Float64", data=0.125)
    assert [convert.bool_cdr(v) for v in (True, False)] == [serialised("std_msgs/msg/Bool", data=v)
                                                            for v in (True, False)]


def test_the_pose_waits_for_the_cloud_only_for_a_covariance_the_estimate_lacks_and_the_cloud_gives():
    """An estimate of 2 to 8 components carries its covariances; beyond, the cloud carries x[0], x[1], x[2]:
    a covariance between two distinct ones of those, and only that, needs it."""
    from dtpf.scripts.ros2.convert import cloud_covariances

    assert not cloud_covariances({"x": 0}, 1)
    assert not cloud_covariances({"x": 0, "y": 0}, 1)
    assert not cloud_covariances({"x": 0, "y": 1}, 4)
    assert not cloud_covariances({"x": 0, "y": 1}, 8)
    assert cloud_covariances({"x": 0, "y": 1}, 9)
    assert cloud_covariances({"x": 0, "y": 1, "yaw": 3}, 9)
    assert not cloud_covariances({"x": 0, "yaw": 3}, 9)
    assert not cloud_covariances({"x": 1, "y": 1}, 9)


def test_the_pose_covariance_is_the_estimates_own_between_any_two_mapped_components():
    """Pose rows x, y, z, yaw of state components 3, 0, 2, 3: each pair's covariance from the estimate's
    row-by-row pairs, one component twice its variance, nothing off the diagonal with --ros2-covariance
    diagonal; the weighted covariances are those of the particles (the filter's covariances())."""
    from dtpf.entity.filter import covariances, moments, moments_and_covariances
    from dtpf.messages.models import Estimate, Layer, Time
    from dtpf.scripts.ros2 import convert

    rng = np.random.default_rng(5)
    d = 4
    particles = rng.normal(size=(400, d)) @ rng.normal(size=(d, d))
    weights = rng.random(400)
    weights /= weights.sum()
    mean = weights @ particles
    full = np.cov(particles, rowvar=False, aweights=weights, bias=True)
    pairs = covariances(particles, weights, mean)
    np.testing.assert_allclose(pairs, [full[i, j] for i in range(d) for j in range(i + 1, d)], rtol=1e-12)
    assert covariances(particles[:, :1], weights, mean[:1]) is None
    assert covariances(np.zeros((5, 9)), np.full(5, 0.2), np.zeros(9)) is None
    # What the filter computes, in one pass: the same numbers, and moments() itself outside 2 <= d <= 8.
    fused_mean, fused_var, fused_pairs = moments_and_covariances(particles, weights)
    np.testing.assert_allclose(fused_mean, mean, rtol=1e-14)
    np.testing.assert_allclose(fused_var, np.diag(full), rtol=1e-12)
    np.testing.assert_allclose(fused_pairs, pairs, rtol=1e-12)
    for wide in (particles[:, :1], np.hstack([particles, particles, particles[:, :1]])):
        expected_mean, expected_var = moments(wide, weights)
        got = moments_and_covariances(wide, weights)
        assert got[2] is None and (got[0] == expected_mean).all() and (got[1] == expected_var).all()

    var = np.diag(full)
    estimate = Estimate(run_id="r", twin_id="t", step=1, stamp=Time(sec=1, nsec=0), layer=Layer.ENTITY,
                        mean=mean.tolist(), var=var.tolist(), lower=(mean - 1).tolist(), upper=(mean + 1).tolist(),
                        ess=10.0, ess_ratio=0.1, resampled=True, degraded=False, covariance=pairs.tolist())
    mapping = {"x": 3, "y": 0, "z": 2, "yaw": 3}
    rows = {"x": 0, "y": 1, "z": 2, "yaw": 5}
    covariance = convert.pose_set(estimate, None, mapping).covariance.reshape(6, 6)
    for a, i in mapping.items():
        for b, j in mapping.items():
            assert covariance[rows[a], rows[b]] == pytest.approx(full[i, j], rel=1e-12), (a, b)
    diagonal = convert.pose_set(estimate, None, mapping, covariances=False).covariance.reshape(6, 6)
    assert np.count_nonzero(diagonal - np.diag(np.diag(diagonal))) == 0
    assert [diagonal[rows[a], rows[a]] for a in mapping] == [var[i] for i in mapping.values()]

    with pytest.raises(ValueError, match=r"covariance must hold d\(d-1\)/2 = 6 values"):
        Estimate(**{**estimate.model_dump(), "covariance": pairs.tolist()[:5]})


def test_the_bridge_formats_an_observation_that_decodes_as_the_one_pydantic_builds(monkeypatch):
    """The bridge writes each observation's JSON itself (pydantic's build and dump were a third of its time per
    message): it decodes, strictly, to the message pydantic would have sent, for extreme floats too."""
    from dtpf.messages.codec import decode
    from dtpf.messages.models import Layer, Observation, Time
    from dtpf.scripts.ros2 import bridge

    class Shell:
        config = RunConfig(twin="twin_1.a-b", run_id="run-7")
        session = None

        def header(self, step):
            return {"run_id": self.config.run_id, "twin_id": self.config.twin, "step": step}

    monkeypatch.setattr(bridge, "publisher", lambda session, key: key)
    inbound = bridge.Inbound(Shell(), mapper=None, start=1, stamps={})
    assert inbound.publisher == inbound.key == "dtpf/twin_1.a-b/sensor/observation"
    rng = np.random.default_rng(3)
    cases = [[0.1], [-0.0, 5e-324, 1.7976931348623157e308], rng.normal(size=8).tolist(),
             (rng.normal(size=16) * 10.0 ** rng.integers(-300, 300, size=16)).tolist()]
    for step, values in enumerate(cases, start=1):
        payload = inbound.payload(step, (1_700_000_000 + step, 999_999_999), values)
        expected = Observation(run_id="run-7", twin_id=Shell.config.twin, step=step, layer=Layer.SENSOR,
                               stamp=Time(sec=1_700_000_000 + step, nsec=999_999_999), values=values)
        assert decode(payload, Observation) == expected


class _FakePublisher:
    def __init__(self, cls=None):
        self.sent, self.subscribers, self.cls = [], 0, cls

    def get_subscription_count(self):
        return self.subscribers

    def publish(self, data):
        self.sent.append(data)


class _FakeNode:
    def __init__(self):
        self.publishers = {}

    def create_publisher(self, cls, topic, profile):
        return self.publishers.setdefault(topic.rsplit("/", 1)[1], _FakePublisher(cls))


class _FakeSubscriber:
    def __init__(self, declared, key):
        self.declared, self.key = declared, key

    def undeclare(self):
        del self.declared[self.key]


class _FakeSession:
    def __init__(self):
        self.declared = {}  # key -> callback

    def declare_subscriber(self, key, callback):
        assert key not in self.declared, f"{key} declared twice"
        self.declared[key] = callback
        return _FakeSubscriber(self.declared, key)

    def deliver(self, key, payload: bytes) -> bool:
        """A sample on ``key`` to its subscriber; False when nothing subscribes to it."""
        if key not in self.declared:
            return False
        self.declared[key](type("Sample", (), {"payload": type("Payload", (), {"to_bytes": lambda _: payload})()})())
        return True


def _outbound(monkeypatch, dim: int, pose: str | None = None, classes=lambda msgtype: msgtype):
    from types import SimpleNamespace

    from dtpf.scripts.ros2 import bridge

    monkeypatch.setattr(bridge, "message_class", classes)
    monkeypatch.setattr(bridge, "qos", lambda args: None)
    node, session = _FakeNode(), _FakeSession()
    args = SimpleNamespace(ros2_pose=pose, ros2_namespace=None, ros2_frame="map", ros2_child_frame="base_{twin}",
                           ros2_covariance=None, ros2_depth=100, ros2_best_effort=False)
    outbound = bridge.Outbound(node, session, RunConfig(twin="fake"), dim, args, OrderedDict())
    return outbound, node.publishers, session


def _estimate_and_cloud(step: int, dim: int, rng):
    import base64

    from dtpf.entity.cloud import FIELDS, POINT_STRIDE, cloud_points
    from dtpf.entity.filter import covariances, moments
    from dtpf.messages.codec import encode
    from dtpf.messages.foxglove import PackedElementField, PointCloud
    from dtpf.messages.models import Estimate, Layer, Time

    particles = rng.normal(size=(200, dim))
    weights = np.full(200, 1 / 200)
    mean, var = moments(particles, weights)
    pairs = covariances(particles, weights, mean)
    header = dict(run_id="run", twin_id="fake", step=step, layer=Layer.ENTITY)
    estimate = Estimate(**header, stamp=Time(sec=1000 + step, nsec=5), mean=mean.tolist(), var=var.tolist(),
                        lower=(mean - 1).tolist(), upper=(mean + 1).tolist(), ess=200.0, ess_ratio=1.0,
                        resampled=True, degraded=False, covariance=None if pairs is None else pairs.tolist())
    points = cloud_points(particles, weights, 1000)
    cloud = PointCloud(**header, stamp=Time(sec=7, nsec=0), timestamp=Time(sec=7, nsec=0), frame_id="state",
                       point_stride=POINT_STRIDE,
                       fields=[PackedElementField(name=name, offset=offset, type=8) for name, offset in FIELDS],
                       data=base64.b64encode(points.tobytes()).decode("ascii"))
    return estimate, encode(estimate), encode(cloud)


def _pose_stamps(publisher) -> list[int]:
    """The header stamps (seconds) of the PoseWithCovarianceStamped / PoseArray CDR bytes ``publisher`` sent."""
    return [int.from_bytes(data[4:8], "little", signed=True) for data in publisher.sent]


def test_the_bridge_takes_the_twins_cloud_only_while_the_particles_have_a_subscriber(monkeypatch):
    """A pose of two of four components goes out with its estimate, its covariance the estimate's; the cloud is
    taken only while someone reads the particles, which then carry their estimate's stamp, the cloud served
    before or after its estimate; an estimate of another dimension is left alone."""
    rng = np.random.default_rng(8)
    outbound, published, session = _outbound(monkeypatch, dim=4)
    estimate_key, cloud_key = "dtpf/fake/entity/estimate", "dtpf/fake/entity/cloud"
    assert list(session.declared) == [estimate_key]

    estimate, first, cloud = _estimate_and_cloud(1, 4, rng)
    assert session.deliver(estimate_key, first) and not session.deliver(cloud_key, cloud)
    assert _pose_stamps(published["pose"]) == [1001] and published["particles"].sent == []
    covariance = TYPESTORE.deserialize_cdr(published["pose"].sent[0],
                                           "geometry_msgs/msg/PoseWithCovarianceStamped").pose.covariance
    assert covariance[1] == covariance[6] == estimate.covariance[0]

    published["particles"].subscribers = 1
    outbound.tick()
    assert cloud_key in session.declared
    _, second, cloud = _estimate_and_cloud(2, 4, rng)
    session.deliver(estimate_key, second)
    session.deliver(cloud_key, cloud)             # after its estimate: out at once
    _, third, cloud = _estimate_and_cloud(3, 4, rng)
    session.deliver(cloud_key, cloud)             # before its estimate: out with it
    assert _pose_stamps(published["particles"]) == [1002]
    session.deliver(estimate_key, third)
    assert _pose_stamps(published["pose"]) == [1001, 1002, 1003]
    assert _pose_stamps(published["particles"]) == [1002, 1003]

    _, other, _ = _estimate_and_cloud(4, 3, rng)  # three components: not the model's four
    session.deliver(estimate_key, other)
    assert len(published["pose"].sent) == 3

    published["particles"].subscribers = 0
    outbound.tick()
    assert list(session.declared) == [estimate_key]


def test_beyond_eight_components_the_pose_waits_for_its_cloud(monkeypatch):
    """An estimate of 9 components carries no covariances: a pose of x[0] and x[1] waits for the step's cloud,
    whose weighted covariance it then carries."""
    rng = np.random.default_rng(9)
    outbound, published, session = _outbound(monkeypatch, dim=9)
    estimate_key, cloud_key = "dtpf/fake/entity/estimate", "dtpf/fake/entity/cloud"
    assert set(session.declared) == {estimate_key, cloud_key}
    estimate, payload, cloud = _estimate_and_cloud(1, 9, rng)
    assert estimate.covariance is None
    session.deliver(estimate_key, payload)
    assert published["pose"].sent == []
    session.deliver(cloud_key, cloud)
    assert _pose_stamps(published["pose"]) == [1001]
    covariance = TYPESTORE.deserialize_cdr(published["pose"].sent[0],
                                           "geometry_msgs/msg/PoseWithCovarianceStamped").pose.covariance
    assert covariance[1] == covariance[6] != 0.0


def test_the_latency_benchmark_says_when_its_target_lies_below_the_floor_of_the_same_run():
    from dtpf.scripts.bench.ros2 import verdict

    assert verdict(0.95, 0.49) == "PASS"
    assert verdict(1.04, 0.49) == "FAIL"
    assert verdict(2.09, 1.116) == "FAIL, below its floor (1.116 ms) on this machine"


def test_the_bridge_publishes_odometry_and_tf_where_their_packages_import(monkeypatch, caplog):
    """Each pose goes out as nav_msgs/Odometry and on /tf too, the bytes dtpf export --ros2 writes. tf2_msgs has
    no wheel (a system ROS 2 installation provides it): a stand-in module takes its place here; without one,
    /tf is left out and the log says why, once."""
    import sys
    import types

    from dtpf.scripts.ros2 import bridge

    real = bridge.message_class
    package, module = types.ModuleType("tf2_msgs"), types.ModuleType("tf2_msgs.msg")
    module.TFMessage = type("TFMessage", (), {})
    package.msg = module
    monkeypatch.setitem(sys.modules, "tf2_msgs", package)
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", module)
    only_tf = lambda msgtype: real(msgtype) if msgtype.startswith("tf2_msgs/") else msgtype  # noqa: E731
    rng = np.random.default_rng(4)
    _, published, session = _outbound(monkeypatch, dim=4, classes=only_tf)
    assert published["tf"].cls is module.TFMessage
    estimate, payload, _ = _estimate_and_cloud(1, 4, rng)
    session.deliver("dtpf/fake/entity/estimate", payload)
    poses = convert.pose_set(estimate, None, {"x": 0, "y": 1})
    assert published["tf"].sent == [convert.tf_cdr(1001, 5, "map", "base_fake", poses)]
    assert published["odom"].sent == [convert.odometry_cdr(1001, 5, "map", "base_fake", poses)]
    odom = TYPESTORE.deserialize_cdr(published["odom"].sent[0], "nav_msgs/msg/Odometry")
    assert (odom.header.frame_id, odom.child_frame_id) == ("map", "base_fake")

    monkeypatch.setitem(sys.modules, "tf2_msgs", None)  # cannot be imported, installed or not
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", None)
    with caplog.at_level("WARNING", logger="dtpf.ros2"):
        _, published, session = _outbound(monkeypatch, dim=4, classes=only_tf)
    assert "tf" not in published and "odom" in published
    lines = [r.getMessage() for r in caplog.records if r.name == "dtpf.ros2"]
    assert lines == ["/tf not published: tf2_msgs cannot be imported here: it has no wheel on PyPI; a ROS 2 "
                     "installation provides it (docs/guides/ros2.md, 'A ROS 2 installation')"], lines
    session.deliver("dtpf/fake/entity/estimate", payload)
    assert len(published["odom"].sent) == 1
