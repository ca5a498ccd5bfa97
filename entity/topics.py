"""A driven twin's sensors and control on ROS 2 topics: a rosbag2 bag's topics, or live ones.

Each sensor of a driven model (docs/guides/driven.md) may be a topic of a rosbag2 bag, ``BAG:/TOPIC``, and
the control too; the topics of one bag are merged by stamp as the files of :mod:`dtpf.entity.stamped`
are::

    dtpf run --model docs/examples/unicycle.py:Unicycle \\
        --observations gps=robot_bag:/gps --ros2-fields gps=point.x,point.y \\
        --observations beacons=robot_bag:/beacons --ros2-fields beacons=vector.x,vector.y,vector.z \\
        --controls robot_bag:/odom

Live, the same sensors are ``NAME=ros2:TOPIC`` and the control ``ros2:TOPIC`` (the bridge,
:mod:`dtpf.scripts.ros2.bridge`, subscribes to each).

A sensor's messages become its observations by its field paths (``--ros2-fields NAME=PATHS``,
:mod:`dtpf.entity.rosbag`), else by the model's ``observation_from_ros2(message)`` (given ``sensor=NAME``
when it takes it). A control's by ``--ros2-control-fields``, else by its type (:data:`CONTROL_FIELDS`: the
forward speed and yaw rate of a planar robot, REP 103's x forward and z up). Every stamp is the message's
``header.stamp`` in integer nanoseconds; a ``geometry_msgs/msg/Twist``, which has no header, is stamped
with the bag's record time (live: the time the bridge receives it). A damaged bag is refused with its
counts, or read in part with ``--partial``, as a single-topic bag is.
"""
from __future__ import annotations

import inspect
import os
from pathlib import Path

import numpy as np

from dtpf.entity.observations import ObservationError, ObservationTable

__all__ = ["CONTROL_FIELDS", "bag_topic", "control_fields", "read_control", "read_sensor", "sensor_mapper"]

#: The control's field paths by message type, when --ros2-control-fields does not give them.
CONTROL_FIELDS = {
    "geometry_msgs/msg/Twist": "linear.x,angular.z",
    "geometry_msgs/msg/TwistStamped": "twist.linear.x,twist.angular.z",
    "nav_msgs/msg/Odometry": "twist.twist.linear.x,twist.twist.angular.z",
    "sensor_msgs/msg/Imu": "linear_acceleration.x,angular_velocity.z",
}


def bag_topic(source) -> tuple[str, str] | None:
    """(bag, topic) of ``source`` written ``BAG:/TOPIC``, or None for anything else (a file that exists, a
    ``ros2:`` topic, a name without ':/')."""
    if source is None:
        return None
    text = os.fsdecode(source)
    if text.startswith("ros2:") or os.path.exists(text):
        return None
    bag, sep, topic = text.rpartition(":/")
    if not sep or len(bag) < 2 or not topic.strip("/"):  # 'C:/data/x.csv' is a drive, not a bag
        return None
    return bag, "/" + topic


def control_fields(msgtype: str | None, given: str | None, controls: tuple[str, ...], where: str) -> str:
    """The control's field paths: ``given``, else :data:`CONTROL_FIELDS` of ``msgtype`` when its width is the
    model's; ObservationError in one line otherwise."""
    if given:
        return given
    default = CONTROL_FIELDS.get(msgtype)
    if default is None:
        raise ObservationError(f"{where}: say how a {msgtype or 'message'} becomes the control "
                               f"({', '.join(controls)}) with --ros2-control-fields PATHS (defaults exist for "
                               f"{', '.join(name.rsplit('/', 1)[-1] for name in CONTROL_FIELDS)})")
    if len(default.split(",")) != len(controls):
        raise ObservationError(f"{where}: a {msgtype} gives {default} by default, the model's control has "
                               f"{len(controls)} ({', '.join(controls)}): give --ros2-control-fields PATHS")
    return default


class _SensorHook:
    """The model's ``observation_from_ros2`` for one sensor (given ``sensor=`` when it takes it)."""

    def __init__(self, model, sensor: str):
        hook = getattr(model, "observation_from_ros2", None)
        if hook is not None:
            try:
                takes = "sensor" in inspect.signature(hook).parameters
            except (TypeError, ValueError):
                takes = False
            self.observation_from_ros2 = (lambda message: hook(message, sensor=sensor)) if takes else hook


def sensor_mapper(model, sensor: str):
    """What :func:`dtpf.entity.rosbag.read_bag` takes as the model of one sensor's topic."""
    return _SensorHook(model, sensor)


def read_sensor(source: tuple[str, str], sensor: str, config, *, obs_dim: int | None, state_dim: int | None,
                model) -> ObservationTable:
    """The observations of ``sensor`` on a bag's topic (``source``: bag, topic), by its --ros2-fields."""
    from dtpf.entity import rosbag

    fields = (getattr(config, "sensor_fields", None) or {}).get(sensor)
    if fields is None and model is None:
        from dtpf.entity import model_ref
        model = model_ref.resolve(config.model_ref)
    try:
        return rosbag.read_bag(source[0], source[1], fields, obs_dim=obs_dim, state_dim=state_dim,
                               model=None if model is None else _SensorHook(model, sensor),
                               partial=bool(getattr(config, "partial", False)))
    except ObservationError as error:
        if fields is None and "say how a message becomes an observation" in str(error):
            raise ObservationError(f"sensor {sensor} ({source[0]}:{source[1]}): say how a message becomes its "
                                   f"observation: --ros2-fields {sensor}=PATHS (e.g. point.x,point.y), or a method "
                                   f"observation_from_ros2(message, sensor=...) in the model",
                                   source=source[0]) from None
        raise


def topic_type(bag, topic: str) -> str | None:
    """The message type of ``topic`` in the bag (None when the bag cannot tell: read_bag then says why)."""
    from dtpf.entity import rosbag

    rosbag.need_rosbags()
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        with AnyReader([Path(bag)], default_typestore=get_typestore(Stores.ROS2_KILTED)) as reader:
            found = {(c.topic, c.msgtype) for c in reader.connections}
    except Exception:  # a damaged bag: read_bag names the damage
        return None
    types = {msgtype for name, msgtype in found if name == topic}
    if not types:
        raise ObservationError(f"{bag}: no topic {topic!r} in the bag (it has: "
                               f"{', '.join(sorted(f'{t} ({m})' for t, m in found)) or 'no topics'})", source=bag)
    return types.pop() if len(types) == 1 else None


def read_control(source: tuple[str, str], controls: tuple[str, ...], fields: str | None = None,
                 partial: bool = False) -> tuple[np.ndarray, np.ndarray, str | None]:
    """The control's stamps (ns), values (C, c) and what was skipped of a damaged bag (None: nothing) from a
    bag's topic (``source``: bag, topic)."""
    from dtpf.entity import rosbag

    bag, topic = source
    where = f"--controls {bag}:{topic}"
    if not Path(bag).exists():
        raise ObservationError(f"{where}: no such file or folder", source=bag)
    paths = control_fields(None if fields else topic_type(bag, topic), fields, controls, where)
    table = rosbag.read_bag(bag, topic, paths, partial=partial)
    if table.observations.shape[1] != len(controls):
        width = table.observations.shape[1]
        raise ObservationError(f"{where}: {width} value{'' if width == 1 else 's'} per message ({paths}), the "
                               f"model's control has {len(controls)} ({', '.join(controls)})", source=bag)
    return table.stamps, np.ascontiguousarray(table.observations), table.problem
