"""Latency through the ROS 2 bridge, beside the native live path, measured in the same run.

Each run is a ``dtpf launch`` of its own (embedded router, recorder, system, information and entity,
lockstep with DT preprocessing) on the UNGM scenario's simulated observations, and this process plays
both ends:

- **ros2**: ``--observations ros2:/dtpf_bench/z`` (the bridge, ``dtpf ros2``, as a child of the launch);
  this process publishes z_k as a ``geometry_msgs/msg/PointStamped`` (``point.x``) with an rclpy node and
  takes the time until its rclpy subscriber receives the step's ``PoseWithCovarianceStamped`` from the
  bridge (``ros2``: the pose goes out with its estimate, and nobody reads the particles, so the bridge
  does not take the twin's cloud; ``ros2-particles``: this process also subscribes to the particles, as
  rviz drawing them does, so the bridge takes each step's cloud and publishes it as a PoseArray);
- **native**: ``--observations live``; this process puts z_k as a dtpf Observation on Zenoh and takes the
  time until its Zenoh subscriber receives the step's Estimate.

So both latencies run from the observation's publication to the estimate's arrival at a subscriber of
the same middleware, on one clock. The bridge's path is the native one (the same Zenoh hops, from the
bridge instead of the sensor) plus two ROS 2 hops: the observation in, the pose out. The floor of what
the bridge adds is those two hops with a relay process that does nothing but answer, measured in the same
run (**floor-ros2**: an rclpy node that republishes each PointStamped as a PoseWithCovarianceStamped);
**floor-zenoh**, two Zenoh hops with a relay that puts each payload back, is there for comparison. One
observation at a time: the next goes out ``--gap`` after the
estimate, so none queues behind another; the first ``--warm-up`` steps are left out. Runs alternate
(native, ros2, ros2-particles, floor-zenoh, floor-ros2, native, ...); the table gives the median over runs of each
run's p50 and p99, and the bridge's cost is the median over rounds of its p50 minus the native p50 of the
same round (so a load that drifts between rounds cancels). Needs rclpy (run it with the ROS 2
environment's Python)::

    .venv-ros2/bin/python -m dtpf.scripts.bench.ros2                 # N = 1e3, 2 runs each, about a minute
    .venv-ros2/bin/python -m dtpf.scripts.bench.ros2 --steps 500 --repeats 3

ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, a random ROS_DOMAIN_ID and RMW_FASTRTPS_PUBLICATION_MODE=SYNCHRONOUS
(the bridge's mode) are set unless given.
"""
from __future__ import annotations

import argparse
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from dtpf.entity import sources
from dtpf.messages import keys
from dtpf.messages.codec import MessageError, decode_for_key, encode
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate, Observation, ServiceState, Status, Time
from dtpf.scripts.bench.pipeline import fmt_n
from dtpf.shell.bus import BusError, Inbox, free_port, open_session, publisher, zenoh_config

#: The bridge may add at most this much to the p50 latency at N = 1e3 (ms).
TARGET_ADDED_P50_MS = 1.0
TOPIC = "/dtpf_bench/z"


def _launch(n: int, twin: str, seed: int, observations: list[str], log_dir: Path, port: int) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-P", "-m", "dtpf.scripts.cli", "launch", *observations, "--particles", str(n),
         "--seed", str(seed), "--twin", twin, "--port", str(port), "--quiet", "-o", str(log_dir / f"{twin}.mcap")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def _stop(launcher: subprocess.Popen) -> None:
    if launcher.poll() is None:
        os.killpg(launcher.pid, signal.SIGINT)
        try:
            launcher.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(launcher.pid, signal.SIGKILL)
            launcher.wait()


def _session(port: int, launcher: subprocess.Popen):
    deadline = time.monotonic() + 60
    while True:  # the launcher's router takes a moment to listen
        try:
            return open_session(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"],
                                             cfg=["connect/timeout_ms:1000", "connect/exit_on_failure:true"]))
        except BusError:
            if time.monotonic() > deadline or launcher.poll() is not None:
                raise RuntimeError("dtpf launch did not come up") from None
            time.sleep(0.2)


def _wait_running(inbox: Inbox) -> None:
    while True:  # until the entity is running (it has subscribed to the sensor key)
        item = inbox.get(timeout=60)
        if item is None:
            raise RuntimeError("the entity never said it was running")
        try:
            message = decode_for_key(item.key, item.payload)
        except MessageError:
            continue
        if isinstance(message, Status) and message.layer == "entity" and message.state == ServiceState.RUNNING:
            return


def native_run(n, z, warm_up, gap, seed, log_dir) -> np.ndarray:
    twin = f"bench-native-{n}"
    port = free_port()
    launcher = _launch(n, twin, seed, ["--observations", "live"], log_dir, port)
    session = None
    try:
        session = _session(port, launcher)
        inbox = Inbox(session, keys.key(twin, "entity", "estimate"), keys.key(twin, "entity", "status"))
        out = publisher(session, keys.key(twin, "sensor", "observation"))
        _wait_running(inbox)
        latencies = []
        for k in range(1, len(z) + 1):
            message = Observation(run_id="run", twin_id=twin, step=k, values=[float(z[k - 1])], stamp=Time.now())
            payload = encode(message)
            sent = time.perf_counter_ns()
            out.put(payload)
            while True:
                item = inbox.get(timeout=30)
                got = time.perf_counter_ns()
                if item is None:
                    raise RuntimeError(f"no estimate of step {k}")
                try:
                    estimate = decode_for_key(item.key, item.payload)
                except MessageError:
                    continue
                if isinstance(estimate, Estimate) and estimate.step == k:
                    break
            if k > warm_up:
                latencies.append((got - sent) / 1e6)
            time.sleep(gap)
        return np.array(latencies)
    finally:
        if session is not None:
            session.close()
        _stop(launcher)


def _pose_latencies(process: subprocess.Popen, answers: str, z, warm_up: int, gap: float, who: str,
                    probe: bool = False, particles: str | None = None) -> np.ndarray:
    """With an rclpy node of this process: publish z_k on TOPIC as a PointStamped stamped k, wait for the
    PoseWithCovarianceStamped stamped k on ``answers`` (from ``process``: the launch's bridge, or the floor's
    relay, named ``who``, stopped at the end), and return the milliseconds in between after the warm-up.
    ``probe``: first publish messages stamped 0 until one is answered (a relay answers anything; matched
    both ways in this process, its publisher may not yet have matched this subscriber). ``particles``: also
    subscribe to that PoseArray topic, and fail unless the particles of every measured step came."""
    import rclpy
    from geometry_msgs.msg import PointStamped, PoseArray, PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node = rclpy.create_node(f"dtpf_bench_{os.getpid()}")
    arrived: dict[int, int] = {}
    event = threading.Event()

    def on_pose(message) -> None:
        arrived[message.header.stamp.sec] = time.perf_counter_ns()
        event.set()

    clouds: set[int] = set()
    pub = node.create_publisher(PointStamped, TOPIC, qos)
    sub = node.create_subscription(PoseWithCovarianceStamped, answers, on_pose, qos)
    cloud_sub = None
    if particles is not None:
        cloud_sub = node.create_subscription(PoseArray, particles, lambda message: clouds.add(message.header.stamp.sec),
                                             qos)
    executor = SingleThreadedExecutor()  # spinning on a thread of its own (EventsExecutor's spin there holds the GIL)
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    try:
        deadline = time.monotonic() + 120
        while pub.get_subscription_count() < 1 or sub.get_publisher_count() < 1 or (
                cloud_sub is not None and cloud_sub.get_publisher_count() < 1):
            if time.monotonic() > deadline or process.poll() is not None:
                raise RuntimeError(f"{who} did not come up")
            time.sleep(0.05)
        while probe and 0 not in arrived:
            if time.monotonic() > deadline or process.poll() is not None:
                raise RuntimeError(f"{who} did not answer")
            pub.publish(PointStamped())
            event.wait(timeout=0.1)
        # The answers to the probes still on their way; the bridge takes the twin's cloud within 0.1 s of a
        # subscriber of the particles.
        time.sleep(0.5 if particles is not None else 0.2)
        latencies = []
        for k in range(1, len(z) + 1):
            message = PointStamped()
            message.header.stamp.sec = k  # the answer carries the observation's stamp
            message.point.x = float(z[k - 1])
            event.clear()
            sent = time.perf_counter_ns()
            pub.publish(message)
            while k not in arrived:
                if not event.wait(timeout=30):
                    raise RuntimeError(f"{who} did not answer {k}")
                event.clear()
            if k > warm_up:
                latencies.append((arrived[k] - sent) / 1e6)
            time.sleep(gap)
        if particles is not None:
            time.sleep(0.5)
            missing = set(range(warm_up + 1, len(z) + 1)) - clouds
            if missing:
                raise RuntimeError(f"{who} sent no particles of {len(missing)} measured steps ({sorted(missing)[:5]} ...)")
        return np.array(latencies)
    finally:
        executor.shutdown()
        node.destroy_node()
        _stop(process)


def ros2_run(n, z, warm_up, gap, seed, log_dir, particles: bool = False) -> np.ndarray:
    twin = f"bench_ros2_{n}"
    launcher = _launch(n, twin, seed, ["--observations", f"ros2:{TOPIC}", "--ros2-fields", "point.x",
                                       "--ros2-type", "geometry_msgs/msg/PointStamped"], log_dir, free_port())
    return _pose_latencies(launcher, f"/dtpf/{twin}/pose", z, warm_up, gap, "the bridge",
                           particles=f"/dtpf/{twin}/particles" if particles else None)


_ECHO = "/dtpf_bench/echo"


def _relay(kind: str, where: str) -> None:
    """The floor's relay process: answer each message at once, nothing else (``where``: the Zenoh endpoint)."""
    if kind == "zenoh":
        session = open_session(zenoh_config(mode="client", connect=[where]))
        back = publisher(session, "dtpf_bench/echo")
        inbox = Inbox(session, "dtpf_bench/z")
        while (item := inbox.get(timeout=60)) is not None:
            back.put(item.payload)
        return
    import rclpy
    from geometry_msgs.msg import PointStamped, PoseArray, PoseWithCovarianceStamped
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    rclpy.init()
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node = rclpy.create_node(f"dtpf_bench_relay_{os.getpid()}")
    back = node.create_publisher(PoseWithCovarianceStamped, _ECHO, qos)

    def answer(message) -> None:
        pose = PoseWithCovarianceStamped()
        pose.header.stamp = message.header.stamp
        pose.pose.pose.position.x = message.point.x
        back.publish(pose)

    node.create_subscription(PointStamped, TOPIC, answer, qos)
    from dtpf.scripts.ros2.bridge import ros2_executor  # the bridge's own, so that the floor is its floor

    executor = ros2_executor()
    executor.add_node(node)
    while True:  # as the bridge serves its input
        executor.spin_once(timeout_sec=0.1)


def _relay_process(kind: str, where: str = "") -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-P", "-m", "dtpf.scripts.bench.ros2", "--relay", kind, where],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def floor_zenoh_run(n, z, warm_up, gap, seed, log_dir) -> np.ndarray:
    port = free_port()
    session = open_session(zenoh_config(mode="router", listen=[f"tcp/127.0.0.1:{port}"]))
    relay = _relay_process("zenoh", f"tcp/127.0.0.1:{port}")
    try:
        inbox = Inbox(session, "dtpf_bench/echo")
        out = publisher(session, "dtpf_bench/z")
        latencies, deadline = [], time.monotonic() + 60
        while inbox.get(timeout=0.05) is None:  # until the relay answers
            assert time.monotonic() < deadline and relay.poll() is None, "the Zenoh relay did not come up"
            out.put(b"ping")
        while inbox.get(timeout=0.2) is not None:
            pass
        for k in range(1, len(z) + 1):
            payload = encode(Observation(run_id="run", twin_id="floor", step=k, values=[float(z[k - 1])],
                                         stamp=Time.now()))
            sent = time.perf_counter_ns()
            out.put(payload)
            if inbox.get(timeout=30) is None:
                raise RuntimeError(f"the Zenoh relay did not answer {k}")
            if k > warm_up:
                latencies.append((time.perf_counter_ns() - sent) / 1e6)
            time.sleep(gap)
        return np.array(latencies)
    finally:
        _stop(relay)
        session.close()


def floor_ros2_run(n, z, warm_up, gap, seed, log_dir) -> np.ndarray:
    return _pose_latencies(_relay_process("ros2"), _ECHO, z, warm_up, gap, "the rclpy relay", probe=True)


#: The paths measured, in the order of each round, and their rows in the table.
PATHS = (("native", native_run), ("ros2", ros2_run),
         ("ros2-particles", lambda *a: ros2_run(*a, particles=True)),
         ("floor-zenoh", floor_zenoh_run), ("floor-ros2", floor_ros2_run))
LABELS = {"native": "native live (Zenoh)", "ros2": "ROS 2 bridge (default)",
          "ros2-particles": "ROS 2 bridge, the particles read too (as rviz drawing them)",
          "floor-zenoh": "floor: Zenoh there and back, a relay that does nothing",
          "floor-ros2": "floor: rclpy there and back, a relay that does nothing"}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.ros2", description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", "-n", default="1e3", help="N (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=300, help="observations per run (default: %(default)s)")
    parser.add_argument("--warm-up", type=int, default=20, help="first steps left out (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each path, alternating (default: %(default)s)")
    parser.add_argument("--gap", type=float, default=0.005, metavar="SECONDS",
                        help="pause between an estimate and the next observation (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--relay", nargs="+", metavar=("KIND", "ENDPOINT"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.relay:  # a floor's relay process
        _relay(args.relay[0], args.relay[1] if len(args.relay) > 1 else "")
        return 0
    try:
        import rclpy
    except ImportError:
        sys.exit("this benchmark needs rclpy: run it with the Python of the ROS 2 environment "
                 "(pip install 'dtpf[ros2]')")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    # This process's publisher writes in its own thread, as the bridge's do (Fast DDS's default hands the
    # sample to a thread of its own, which would count against the bridge).
    os.environ.setdefault("RMW_FASTRTPS_PUBLICATION_MODE", "SYNCHRONOUS")
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
    n = int(float(args.particles))
    config = RunConfig(particles=n, steps=args.steps, seed=args.seed)
    z = sources.observations_of(config, sources.load_model(config)).observations[:, 0]
    load = os.getloadavg()[0]
    print(f"observation publication -> estimate received by a subscriber (ROS 2: rclpy, Fast DDS; native: "
          f"Zenoh); N = {fmt_n(n)}, {os.cpu_count()} cores, load {load:.2f}; {args.steps} observations per run "
          f"({args.warm_up} warm-up), {args.repeats} runs of each, lockstep with DT preprocessing and the recorder",
          flush=True)
    rclpy.init()
    runs: dict[str, list[np.ndarray]] = {path: [] for path, _ in PATHS}
    start = time.monotonic()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(args.repeats):
                for path, run in PATHS:
                    latencies = run(n, z, args.warm_up, args.gap, args.seed, Path(tmp))
                    runs[path].append(latencies)
                    print(f"  run {i + 1}/{args.repeats} {path:6}: p50 {np.percentile(latencies, 50):.3f} ms, "
                          f"p99 {np.percentile(latencies, 99):.3f} ms", flush=True)
    finally:
        rclpy.try_shutdown()
    print(f"\n{time.monotonic() - start:.0f} s")
    print("\n| path | N | p50 ms | p99 ms | max ms | p50 range over runs |")
    print("|---|---|---|---|---|---|")
    p50s = {}
    for path, label in LABELS.items():
        p50 = [float(np.percentile(r, 50)) for r in runs[path]]
        p99 = [float(np.percentile(r, 99)) for r in runs[path]]
        p50s[path] = statistics.median(p50)
        print(f"| {label} | {fmt_n(n)} | {p50s[path]:.3f} | {statistics.median(p99):.3f} | "
              f"{max(float(r.max()) for r in runs[path]):.2f} | {min(p50):.3f}-{max(p50):.3f} |")
    # The bridge's path is the native path (the same Zenoh hops, from the bridge instead of the sensor) plus two
    # ROS 2 hops, the observation in and the pose out: what those cost with a relay that does nothing is the
    # least a bridge can add.
    floor = [float(np.percentile(r, 50)) for r in runs["floor-ros2"]]
    floor_p50 = statistics.median(floor)
    print(f"\nfloor of what the bridge adds: ROS 2 there and back, a relay that does nothing: "
          f"{floor_p50:.3f} ms at p50 ({min(floor):.3f}-{max(floor):.3f} over rounds)")
    ok = True
    for path in ("ros2", "ros2-particles"):
        added, low, high = _paired(runs, path, "native")
        ok = ok and added <= TARGET_ADDED_P50_MS if path == "ros2" else ok
        print(f"{LABELS[path]} adds {added:.3f} ms at p50 ({low:.3f}-{high:.3f} over rounds), "
              f"{added / floor_p50:.2f} x the floor; target <= {TARGET_ADDED_P50_MS} ms: {verdict(added, floor_p50)}")
    return 0 if ok else 1


def verdict(added: float, floor: float, target: float = TARGET_ADDED_P50_MS) -> str:
    """PASS or FAIL against ``target``, and whether the target lies below the ``floor`` measured in the same run
    (no bridge could meet it on this machine)."""
    if added <= target:
        return "PASS"
    return f"FAIL, below its floor ({floor:.3f} ms) on this machine" if floor > target else "FAIL"


def _paired(runs: dict[str, list[np.ndarray]], path: str, base: str) -> tuple[float, float, float]:
    """The median over rounds of ``path``'s p50 minus ``base``'s p50 of the same round (a load that drifts
    between rounds cancels), and the least and greatest of those differences."""
    added = [float(np.percentile(a, 50) - np.percentile(b, 50)) for a, b in zip(runs[path], runs[base])]
    return statistics.median(added), min(added), max(added)


if __name__ == "__main__":
    sys.exit(main())
