"""A twin inside a ROS 2 system: live topics in and out, rosbag2 logs out.

- :mod:`dtpf.scripts.ros2.bridge`: ``dtpf ros2``, a process of its own with a real rclpy node. It
  subscribes to a ROS 2 topic and publishes each message as one observation on the twin's live key
  (``dtpf/<twin>/sensor/observation``), and publishes the twin's estimate, particles, ESS, PS and
  degraded flag as ROS 2 messages under ``/dtpf/<twin>/``. ``dtpf launch --observations ros2:TOPIC``
  starts it as a child; a driven twin's sensors and control come from a topic each
  (:mod:`dtpf.scripts.ros2.feeds`).
- :mod:`dtpf.scripts.ros2.export`: ``dtpf export --ros2 LOG OUTDIR``, a dtpf log as a rosbag2 folder
  (MCAP storage, CDR messages), written with rosbags.
- :mod:`dtpf.scripts.ros2.convert`: estimates and particle clouds as ROS 2 message fields, for rclpy's
  classes and rosbags' alike.

Reading a rosbag2 log as observations is the entity's (:mod:`dtpf.entity.rosbag`). Nothing of dtpf
outside this package imports rclpy; the bridge needs the ``[ros2]`` extra (see :data:`ROS2_INSTALL`).
"""
from __future__ import annotations

import importlib.util

from dtpf.messages.errors import DtpfError

__all__ = ["ROS2_INSTALL", "Ros2Error", "have_rclpy", "require_rclpy"]

#: What to install for live ROS 2 topics; the wheels add a startup hook to the environment, so a separate one.
ROS2_INSTALL = ("live ROS 2 topics need rclpy: pip install 'dtpf[ros2]' (the ROS 2 Kilted wheels, about 150 MB; "
                "best in a virtual environment of its own, see docs/guides/ros2.md)")


class Ros2Error(DtpfError, ValueError):
    """A ROS 2 option or input that cannot be used: a missing package, a topic of another type, a field
    path the type does not have; one line."""


def have_rclpy() -> bool:
    """Whether rclpy can be imported here (without importing it)."""
    try:
        return importlib.util.find_spec("rclpy") is not None
    except (ImportError, ValueError):
        return False


def require_rclpy() -> None:
    """Ros2Error saying what to install when rclpy is missing."""
    if not have_rclpy():
        raise Ros2Error(ROS2_INSTALL)
