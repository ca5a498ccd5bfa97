"""A twin's estimate and particles as ROS 2 messages (their CDR bytes), the same live and in a rosbag2 log.

Which state components a pose shows is a mapping (``--ros2-pose x=0,y=1,z=2,yaw=3``; default x = x[0]
and, for a state of 2 or more dimensions, y = x[1]). For each step:

- ``pose``: ``geometry_msgs/msg/PoseWithCovarianceStamped``; the position and yaw are the estimate's
  weighted means; the covariance (6 x 6, row-major, x y z roll pitch yaw) holds the estimate's weighted
  variances on the diagonal and the weighted covariances between the mapped components: the estimate's
  own (``Estimate.covariance``, a state of 2 to 8 components), else, between components the particle
  cloud carries (x[0], x[1], x[2]), those of the cloud's particles (every particle when N <= the
  entity's --cloud-points, 1000 by default). An axis the state does not have (roll and pitch always; z
  and yaw unless mapped) is marked unknown: :data:`UNKNOWN_VARIANCE` on its diagonal, 0 off it.
- ``odom``: ``nav_msgs/msg/Odometry``, the same pose and covariance, ``child_frame_id`` the twin's body
  frame; its twist is unknown (zero, :data:`UNKNOWN_VARIANCE` on the diagonal of its covariance).
- ``/tf``: ``tf2_msgs/msg/TFMessage``, one transform from the parent frame to the body frame, the pose.
- ``particles``: ``geometry_msgs/msg/PoseArray`` of the cloud's particles (components beyond x[2] are 0).
- ``ess``, ``ps``: ``std_msgs/msg/Float64``; ``degraded``: ``std_msgs/msg/Bool``; ``observation``:
  ``std_msgs/msg/Float64MultiArray`` (the values filtered at that step).

Each message is made as its CDR bytes (little endian, what rclpy publishes raw and rosbag2 stores), with
``struct`` and NumPy: the live bridge and ``dtpf export --ros2`` publish the same bytes, and a pose costs
microseconds instead of the tenths of a millisecond of rclpy's message objects and their conversion.
"""
from __future__ import annotations

import base64
import math
import struct

import numpy as np

from dtpf.messages.foxglove import PointCloud
from dtpf.messages.models import MAX_COVARIANCE_DIM, Estimate

__all__ = ["AXES", "TF_TOPIC", "TF_TYPE", "TOPICS", "UNKNOWN_VARIANCE", "PoseSet", "bool_cdr", "cloud_covariances",
           "cloud_points_of", "float64_array_cdr", "float64_cdr", "odometry_cdr", "parse_pose", "pose_array_cdr",
           "pose_cdr", "pose_set", "pose_set_particles", "tf_cdr"]

#: The pose axes a state component may be mapped to, and their rows in a ROS 2 6 x 6 covariance.
AXES = {"x": 0, "y": 1, "z": 2, "yaw": 5}
#: Topic (under the namespace) -> ROS 2 type.
TOPICS = {"pose": "geometry_msgs/msg/PoseWithCovarianceStamped", "particles": "geometry_msgs/msg/PoseArray",
          "ess": "std_msgs/msg/Float64", "ps": "std_msgs/msg/Float64", "degraded": "std_msgs/msg/Bool",
          "observation": "std_msgs/msg/Float64MultiArray", "odom": "nav_msgs/msg/Odometry"}
#: The transforms' topic (absolute: one tree for the whole system) and its type.
TF_TOPIC, TF_TYPE = "/tf", "tf2_msgs/msg/TFMessage"
#: The variance of a pose or twist axis the twin does not estimate. A PoseWithCovariance has no flag for
#: "unknown" (the -1 in element 0 is sensor_msgs/Imu's convention, per 3 x 3 block, and would void the
#: known axes too); a zero variance reads as perfectly known. A large variance, as odometry drivers give
#: their unused axes (REP 105 practice), makes a fusing filter (robot_localization, an EKF) weigh the
#: axis as no information.
UNKNOWN_VARIANCE = 1e6


def parse_pose(spec: str | None, dim: int) -> dict[str, int]:
    """The axis -> state component mapping of ``spec`` ('x=0,y=1,yaw=3'); ValueError in one line."""
    if spec is None or not spec.strip():
        return {"x": 0, "y": 1} if dim >= 2 else {"x": 0}
    mapping: dict[str, int] = {}
    for item in spec.split(","):
        axis, sep, component = item.strip().partition("=")
        axis = axis.strip()
        if not sep or axis not in AXES:
            raise ValueError(f"--ros2-pose: {item.strip()!r} is not AXIS=COMPONENT with AXIS one of "
                             f"{', '.join(AXES)} (e.g. 'x=0,y=1,yaw=3')")
        try:
            index = int(component)
        except ValueError:
            raise ValueError(f"--ros2-pose: {item.strip()!r}: the component must be an index of the state") from None
        if not 0 <= index < dim:
            raise ValueError(f"--ros2-pose: {item.strip()!r}: the state has components 0 .. {dim - 1}")
        if axis in mapping:
            raise ValueError(f"--ros2-pose: {axis} is given twice")
        mapping[axis] = index
    return mapping


def cloud_points_of(cloud: PointCloud) -> np.ndarray:
    """(K, 4) float64 points (x, y, z, weight) of an entity's cloud message."""
    raw = base64.b64decode(cloud.data)
    return np.frombuffer(raw, dtype=np.float64).reshape(-1, cloud.point_stride // 8)[:, :4]


def _cloud_column(component: int, dim: int) -> int | None:
    """The cloud column that holds state component ``component`` (entity/cloud.py), or None."""
    if dim == 1:
        return 0 if component == 0 else None
    return component if component < 3 else None


def cloud_covariances(mapping: dict[str, int], dim: int) -> bool:
    """Whether the pose's covariances come from the particle cloud: the estimate carries none (a state of
    more than MAX_COVARIANCE_DIM components) and two distinct mapped components are in the cloud."""
    if 2 <= dim <= MAX_COVARIANCE_DIM:
        return False
    return len({component for component in mapping.values() if _cloud_column(component, dim) is not None}) >= 2


def pair_index(i: int, j: int, dim: int) -> int:
    """Where the covariance of components i < j sits in ``Estimate.covariance`` (pairs row by row)."""
    return i * (2 * dim - i - 1) // 2 + (j - i - 1)


class PoseSet:
    """One step's pose: ``position`` (x, y, z), ``yaw``, ``covariance`` (36,) and the particles' poses."""

    __slots__ = ("covariance", "particles", "position", "yaw")

    def __init__(self, position, yaw, covariance, particles):
        self.position, self.yaw, self.covariance, self.particles = position, yaw, covariance, particles


def pose_set(estimate: Estimate, points: np.ndarray | None, mapping: dict[str, int],
             covariances: bool = True) -> PoseSet:
    """The pose of ``estimate`` with its covariance, and (``points``: the step's cloud) the particles' poses.
    ``covariances`` False: the variances alone (``--ros2-covariance diagonal``)."""
    dim = len(estimate.mean)
    position = [0.0, 0.0, 0.0]
    for axis, row in (("x", 0), ("y", 1), ("z", 2)):
        if axis in mapping:
            position[row] = float(estimate.mean[mapping[axis]])
    yaw = float(estimate.mean[mapping["yaw"]]) if "yaw" in mapping else 0.0
    covariance = np.zeros((6, 6), dtype=np.float64)
    for row in set(range(6)) - {AXES[axis] for axis in mapping}:
        covariance[row, row] = UNKNOWN_VARIANCE
    columns = {axis: _cloud_column(component, dim) for axis, component in mapping.items()}
    weighted = None
    pairs = estimate.covariance if covariances else None
    if covariances and pairs is None and points is not None and len(points):
        w = points[:, 3]
        total = w.sum()
        if total > 0 and np.isfinite(total):
            w = w / total
            centred = points[:, :3] - w @ points[:, :3]
            weighted = (centred * w[:, None]).T @ centred
    axes = list(mapping)
    for i, a in enumerate(axes):
        covariance[AXES[a], AXES[a]] = float(estimate.var[mapping[a]])
        for b in axes[i + 1:]:
            ia, ib = mapping[a], mapping[b]
            if ia == ib or pairs is not None:  # one component twice: its variance; else the estimate's
                value = float(estimate.var[ia]) if ia == ib else pairs[pair_index(min(ia, ib), max(ia, ib), dim)]
                if covariances:
                    covariance[AXES[a], AXES[b]] = covariance[AXES[b], AXES[a]] = value
                continue
            if weighted is None or columns[a] is None or columns[b] is None:
                continue
            ca, cb = columns[a], columns[b]
            sa, sb = math.sqrt(weighted[ca, ca]), math.sqrt(weighted[cb, cb])
            if sa > 0 and sb > 0:  # the cloud's correlation, at the estimate's variances
                value = weighted[ca, cb] / (sa * sb) * math.sqrt(estimate.var[mapping[a]] * estimate.var[mapping[b]])
                covariance[AXES[a], AXES[b]] = covariance[AXES[b], AXES[a]] = value
    particles = None if points is None else pose_set_particles(points, mapping, dim)
    return PoseSet(position, yaw, covariance.reshape(36), particles)


def pose_set_particles(points: np.ndarray, mapping: dict[str, int], dim: int) -> np.ndarray:
    """(K, 4) x, y, z, yaw of the cloud's particles by ``mapping`` (0 where the cloud lacks a component)."""
    particles = np.zeros((len(points), 4), dtype=np.float64)
    for axis, slot in (("x", 0), ("y", 1), ("z", 2), ("yaw", 3)):
        column = _cloud_column(mapping[axis], dim) if axis in mapping else None
        if column is not None:
            particles[:, slot] = points[:, column]
    return particles


#: CDR's encapsulation header: plain CDR, little endian.
_CDR = b"\x00\x01\x00\x00"


def _header_cdr(sec: int, nsec: int, frame: str) -> bytes:
    """A ``std_msgs/msg/Header``'s CDR bytes after the encapsulation header, padded to 4."""
    name = frame.encode("utf-8") + b"\0"
    head = struct.pack("<iII", sec, nsec, len(name)) + name
    return head + b"\0" * (-len(head) % 4)


def pose_cdr(sec: int, nsec: int, frame: str, poses: PoseSet) -> bytes:
    """The ``geometry_msgs/msg/PoseWithCovarianceStamped`` of ``poses`` as CDR bytes."""
    head = _header_cdr(sec, nsec, frame)
    head += b"\0" * (-len(head) % 8)
    return _CDR + head + _pose_cdr(poses)


def _pose_cdr(poses: PoseSet) -> bytes:
    """A ``geometry_msgs/msg/PoseWithCovariance`` (8-aligned doubles only)."""
    x, y, z = poses.position
    return (struct.pack("<7d", x, y, z, 0.0, 0.0, math.sin(poses.yaw / 2.0), math.cos(poses.yaw / 2.0))
            + np.asarray(poses.covariance, dtype="<f8").tobytes())


def _string_cdr(text: str) -> bytes:
    """A string's CDR bytes (length with its NUL, then the bytes), starting 4-aligned."""
    name = text.encode("utf-8") + b"\0"
    return struct.pack("<I", len(name)) + name


#: An unknown twist: zero, with UNKNOWN_VARIANCE on its covariance's diagonal.
_UNKNOWN_TWIST = struct.pack("<6d", *[0.0] * 6) + (np.eye(6) * UNKNOWN_VARIANCE).astype("<f8").tobytes()


def odometry_cdr(sec: int, nsec: int, frame: str, child: str, poses: PoseSet) -> bytes:
    """The ``nav_msgs/msg/Odometry`` of ``poses`` in ``frame``, its body ``child``, as CDR bytes (its twist
    unknown)."""
    head = _header_cdr(sec, nsec, frame)
    head += _string_cdr(child)
    head += b"\0" * (-len(head) % 8)
    return _CDR + head + _pose_cdr(poses) + _UNKNOWN_TWIST


def tf_cdr(sec: int, nsec: int, frame: str, child: str, poses: PoseSet) -> bytes:
    """A ``tf2_msgs/msg/TFMessage`` of one transform, ``frame`` -> ``child``, the pose (no covariance), as
    CDR bytes."""
    head = struct.pack("<I", 1) + _header_cdr(sec, nsec, frame) + _string_cdr(child)
    head += b"\0" * (-len(head) % 8)
    x, y, z = poses.position
    return _CDR + head + struct.pack("<7d", x, y, z, 0.0, 0.0, math.sin(poses.yaw / 2.0), math.cos(poses.yaw / 2.0))


def pose_array_cdr(sec: int, nsec: int, frame: str, particles: np.ndarray) -> bytes:
    """A ``geometry_msgs/msg/PoseArray`` of ``particles`` ((K, 4): x, y, z, yaw) as CDR bytes, made with
    NumPy: a thousand poses as message objects take milliseconds of Python, their bytes microseconds."""
    head = _header_cdr(sec, nsec, frame) + struct.pack("<I", len(particles))
    head += b"\0" * (-len(head) % 8)
    poses = np.zeros((len(particles), 7), dtype="<f8")
    poses[:, 0:3] = particles[:, 0:3]
    poses[:, 5] = np.sin(particles[:, 3] / 2.0)
    poses[:, 6] = np.cos(particles[:, 3] / 2.0)
    return _CDR + head + poses.tobytes()


def float64_cdr(value: float) -> bytes:
    """A ``std_msgs/msg/Float64`` as CDR bytes."""
    return _CDR + struct.pack("<d", value)


def bool_cdr(value: bool) -> bytes:
    """A ``std_msgs/msg/Bool`` as CDR bytes."""
    return _CDR + (b"\x01" if value else b"\x00")


def float64_array_cdr(values, label: str) -> bytes:
    """A ``std_msgs/msg/Float64MultiArray`` of ``values`` (one dimension named ``label``) as CDR bytes."""
    name = label.encode("utf-8") + b"\0"
    head = struct.pack("<II", 1, len(name)) + name
    head += b"\0" * (-len(head) % 4) + struct.pack("<IIII", len(values), len(values), 0, len(values))
    head += b"\0" * (-len(head) % 8)
    return _CDR + head + np.asarray(values, dtype="<f8").tobytes()
