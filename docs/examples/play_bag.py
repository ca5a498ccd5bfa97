"""Play a rosbag2 bag's topics on ROS 2 at the pace they were recorded (``ros2 bag play`` has no wheel).

Each message goes out as the CDR bytes the bag holds, by a real rclpy node, once every topic played has a
subscriber (QoS reliable, keep last 1000; ``--best-effort`` as most sensor drivers publish). It needs the
ROS 2 environment (rclpy and the message packages of the bag's types) and rosbags::

    .venv-ros2/bin/python docs/examples/play_bag.py robot/bag --topics /gps,/beacons,/odom
"""
from __future__ import annotations

import argparse
import importlib
import sys
import time


def message_class(msgtype: str):
    """The rclpy class of 'pkg/msg/Name'."""
    package, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


def main(bag: str, topics: list[str] | None, speed: float = 1.0, wait: float = 60.0,
         best_effort: bool = False) -> int:
    """Play ``topics`` of ``bag`` (all when None); the number of messages played."""
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        connections = [c for c in reader.connections if topics is None or c.topic in topics]
        messages = [(stamp, c.topic, bytes(raw)) for c, stamp, raw in reader.messages(connections=connections)]
    missing = sorted(set(topics or ()) - {c.topic for c in connections})
    if missing:
        raise SystemExit(f"play_bag: {bag} has no topic {missing[0]}")
    rclpy.init()
    node = rclpy.create_node("dtpf_play_bag")
    qos = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE)
    publishers = {c.topic: node.create_publisher(message_class(c.msgtype), c.topic, qos) for c in connections}
    deadline = time.monotonic() + wait
    while min(p.get_subscription_count() for p in publishers.values()) < 1:
        if time.monotonic() > deadline:
            raise SystemExit(f"play_bag: no subscriber of every topic in {wait:g} s")
        rclpy.spin_once(node, timeout_sec=0.05)
    print(f"playing {len(messages)} messages of {', '.join(publishers)}", flush=True)
    start, first = time.monotonic(), messages[0][0] if messages else 0
    for stamp, topic, raw in messages:
        if speed:
            time.sleep(max(0.0, start + (stamp - first) / 1e9 / speed - time.monotonic()))
        publishers[topic].publish(raw)
    if not best_effort:
        for publisher in publishers.values():
            publisher.wait_for_all_acked(Duration(seconds=30))
    print(f"played {len(messages)} messages", flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return len(messages)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", help="the bag (a folder with metadata.yaml, or an .mcap file)")
    parser.add_argument("--topics", default=None, help="the topics to play, comma-separated (default: all)")
    parser.add_argument("--speed", type=float, default=1.0, help="times real time; 0: at once (default: 1)")
    parser.add_argument("--wait", type=float, default=60.0,
                        help="seconds to wait for a subscriber of every topic (default: 60)")
    parser.add_argument("--best-effort", action="store_true", help="publish best effort, as sensor drivers do")
    args = parser.parse_args()
    main(args.bag, args.topics.split(",") if args.topics else None, args.speed, args.wait, args.best_effort)
    sys.exit(0)
