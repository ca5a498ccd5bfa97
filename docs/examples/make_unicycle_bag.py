"""Simulate the unicycle robot of unicycle.py into a rosbag2 bag: wheel odometry, GPS and beacons.

The same simulation as make_unicycle_csv.py (imported from it, same seed, same numbers), written as ROS 2
messages with rosbags (MCAP storage, CDR), each stamped in ``header.stamp`` with its CSV row's time to the
nanosecond (plus ``--epoch`` seconds) and recorded at that time:

- ``/odom``, ``nav_msgs/msg/Odometry`` at 20 Hz: the odometry's speed and turn rate in
  ``twist.twist.linear.x`` and ``twist.twist.angular.z`` (the control, v and omega);
- ``/gps``, ``geometry_msgs/msg/PointStamped`` at 1 Hz: the GPS position in ``point.x``, ``point.y``;
- ``/beacons``, ``geometry_msgs/msg/Vector3Stamped`` at 10 Hz: the three ranges in ``vector.x``,
  ``vector.y``, ``vector.z``;
- ``/truth``, ``geometry_msgs/msg/Vector3Stamped`` at 10 Hz: the true pose (x, y, theta), for reference.

Every value is a float64, as in the CSV files: the bag and the files give the same estimates::

    python docs/examples/make_unicycle_bag.py --out /tmp/robot_bag --duration 60
    dtpf run --model docs/examples/unicycle.py:Unicycle \\
        --observations gps=/tmp/robot_bag:/gps --ros2-fields gps=point.x,point.y \\
        --observations beacons=/tmp/robot_bag:/beacons --ros2-fields beacons=vector.x,vector.y,vector.z \\
        --controls /tmp/robot_bag:/odom
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from make_unicycle_csv import simulate  # noqa: E402

#: Topic -> message type.
TOPICS = {"/odom": "nav_msgs/msg/Odometry", "/gps": "geometry_msgs/msg/PointStamped",
          "/beacons": "geometry_msgs/msg/Vector3Stamped", "/truth": "geometry_msgs/msg/Vector3Stamped"}
#: The field paths of each sensor, as --ros2-fields takes them.
FIELDS = {"gps": "point.x,point.y", "beacons": "vector.x,vector.y,vector.z"}


def stamp_ns(text: str) -> int:
    """Nanoseconds of a CSV time written as seconds with three decimals ('1.050' -> 1_050_000_000)."""
    seconds, _, millis = text.partition(".")
    return int(seconds) * 1_000_000_000 + int(millis.ljust(3, "0")) * 1_000_000


def messages(duration: float, seed: int, epoch: int = 0):
    """(stamp ns, topic, fields) of every message, in stamp order (odometry first at a shared stamp)."""
    odometry, gps, beacons = simulate(duration, seed)
    offset = int(epoch) * 1_000_000_000
    out = []
    for text, v, omega in odometry:
        out.append((stamp_ns(text) + offset, 0, "/odom", (v, omega)))
    for text, x, y, *_ in gps:
        out.append((stamp_ns(text) + offset, 1, "/gps", (x, y)))
    for text, r1, r2, r3, *truth in beacons:
        out.append((stamp_ns(text) + offset, 2, "/beacons", (r1, r2, r3)))
        out.append((stamp_ns(text) + offset, 3, "/truth", tuple(truth)))
    out.sort(key=lambda item: (item[0], item[1]))
    return [(stamp, topic, values) for stamp, _, topic, values in out]


def _message(types, topic: str, stamp: int, values):
    """The rosbags message of ``topic`` with ``values``, stamped ``stamp`` ns."""
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](
        sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000), frame_id="odom" if topic == "/odom" else "map")
    vector = types["geometry_msgs/msg/Vector3"]
    if topic == "/odom":
        import numpy as np

        pose = types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                                 orientation=types["geometry_msgs/msg/Quaternion"](
                                                     x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=np.zeros(36))
        twist = types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=vector(x=float(values[0]), y=0.0, z=0.0),
                                                   angular=vector(x=0.0, y=0.0, z=float(values[1]))),
            covariance=np.zeros(36))
        return types["nav_msgs/msg/Odometry"](header=header, child_frame_id="base_link", pose=pose, twist=twist)
    if topic == "/gps":
        return types["geometry_msgs/msg/PointStamped"](
            header=header, point=types["geometry_msgs/msg/Point"](x=float(values[0]), y=float(values[1]), z=0.0))
    return types["geometry_msgs/msg/Vector3Stamped"](header=header, vector=vector(*map(float, values)))


def main(out: Path, duration: float = 60.0, seed: int = 2026, epoch: int = 0) -> Path:
    """Write the bag folder ``out`` (replacing one that is there); return its path."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {topic: writer.add_connection(topic, msgtype, typestore=store)
                       for topic, msgtype in TOPICS.items()}
        for stamp, topic, values in messages(duration, seed, epoch):
            message = _message(store.types, topic, stamp, values)
            writer.write(connections[topic], stamp, store.serialize_cdr(message, TOPICS[topic]))
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE / "unicycle_bag",
                        help="the bag folder to write (default: unicycle_bag beside this)")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of driving (default: 60)")
    parser.add_argument("--seed", type=int, default=2026, help="seed of the noise (default: 2026)")
    parser.add_argument("--epoch", type=int, default=0,
                        help="seconds added to every stamp, e.g. 1796160000 for December 2026 (default: 0, the "
                             "CSV files' times)")
    args = parser.parse_args()
    print(main(args.out, args.duration, args.seed, args.epoch))
