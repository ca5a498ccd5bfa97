"""``dtpf export --ros2 LOG OUTDIR``: a dtpf log as a rosbag2 folder (MCAP storage, CDR messages).

For every twin of the log, one message per step on each of (namespace ``/dtpf/<twin>/`` unless
``--ros2-namespace``)::

    pose         geometry_msgs/msg/PoseWithCovarianceStamped   the estimate (dtpf.scripts.ros2.convert)
    odom         nav_msgs/msg/Odometry                         the same pose, child_frame_id the body frame
    particles    geometry_msgs/msg/PoseArray                   the step's particle cloud
    observation  std_msgs/msg/Float64MultiArray                the values filtered at the step
    ess, ps      std_msgs/msg/Float64
    degraded     std_msgs/msg/Bool

and on ``/tf`` (``tf2_msgs/msg/TFMessage``) the transform from ``--ros2-frame`` (default ``map``) to
``--ros2-child-frame`` (default ``base_link``; '{twin}' is the twin id) of each step's pose.

Each at the time the recorder received the estimate (the bag's time), its header stamp the stamp of the
observation the step filtered, to the nanosecond, as the live bridge publishes it. Written with rosbags
(pure Python, the ``[rosbag]`` or ``[ros2]`` extra), so ``ros2 bag play OUTDIR`` replays the run into a
ROS 2 system and Foxglove opens it as a ROS 2 bag. A log holds a twin's messages in step order; where a
step has competing estimates, the one :func:`in_step_order` chooses is exported.
"""
from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np

from dtpf.messages.codec import MessageError
from dtpf.messages.foxglove import PointCloud
from dtpf.messages.models import Estimate, Observation
from dtpf.recording.logfile import in_step_order, read_logs
from dtpf.scripts.ros2 import Ros2Error, params
from dtpf.scripts.ros2.convert import (
    TF_TOPIC,
    TF_TYPE,
    TOPICS,
    bool_cdr,
    cloud_points_of,
    float64_array_cdr,
    float64_cdr,
    odometry_cdr,
    parse_pose,
    pose_array_cdr,
    pose_cdr,
    pose_set,
    tf_cdr,
)

__all__ = ["DEFAULT_CHILD_FRAME", "DEFAULT_FRAME", "export_ros2", "frame_of", "register"]

#: The parent frame of the pose, the odometry and the transform, and the body frame they place in it.
DEFAULT_FRAME, DEFAULT_CHILD_FRAME = "map", "base_link"


def _rosbags():
    try:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise Ros2Error("dtpf export --ros2 needs the rosbags package: pip install 'dtpf[rosbag]' (pure Python) "
                        "or 'dtpf[ros2]'") from None
    return Writer, StoragePlugin, get_typestore(Stores.ROS2_KILTED)


def namespace_of(template: str | None, twin: str) -> str:
    """The ROS 2 namespace of ``twin``: ``template`` with '{twin}' filled in (default /dtpf/<twin>),
    absolute, without a trailing '/'. ROS 2 names allow letters, digits and '_': '-' and '.' become '_'."""
    text = (template or "/dtpf/{twin}").replace("{twin}", _ros_name(twin)).rstrip("/")
    return text if text.startswith("/") else "/" + text


def _ros_name(twin: str) -> str:
    return "".join(c if c.isalnum() or c == "_" else "_" for c in twin)


def frame_of(template: str, twin: str) -> str:
    """A frame id with '{twin}' filled in (the twin id as a ROS 2 name: '-' and '.' become '_')."""
    return template.replace("{twin}", _ros_name(twin))


def export_ros2(logs: list[Path], out: Path, *, pose: str | None = None, namespace: str | None = None,
                frame: str | None = None, child_frame: str | None = None,
                params_file: Path | None = None) -> dict[str, tuple[int, str]]:
    """Write the rosbag2 folder ``out`` from the dtpf log(s); the number of steps written and their
    namespace, by twin.
    ``params_file``: a ROS 2 parameters file (:mod:`dtpf.scripts.ros2.params`) whose ``pose``, ``namespace``,
    ``frame`` and ``child_frame`` of each twin's bridge node (dtpf_<twin>, or /**) serve where the arguments
    are None; its other parameters are the live bridge's."""
    Writer, StoragePlugin, store = _rosbags()
    if out.exists():
        raise Ros2Error(f"{out} exists; rosbag2 writes a new folder (remove it or name another)")
    log = read_logs(logs)
    estimates: dict[str, list] = defaultdict(list)
    clouds: dict[tuple[str, int], np.ndarray] = {}
    times: dict[int, int] = {}
    observed: dict[tuple, tuple[int, int]] = {}  # (twin, step) and (twin, values) -> the observation's stamp
    wanted = ("/entity/estimate", "/entity/cloud", "/sensor/observation")
    for item, message in log.decoded(lambda topic: topic.endswith(wanted)):
        if isinstance(message, MessageError):
            continue
        if isinstance(message, Estimate):
            estimates[message.twin_id].append(message)
            times[id(message)] = item.log_time
        elif isinstance(message, PointCloud):
            clouds.setdefault((message.twin_id, message.step), cloud_points_of(message))
        elif isinstance(message, Observation) and message.values:
            stamp = (message.stamp.sec, message.stamp.nsec)
            observed[(message.twin_id, message.step, tuple(message.values))] = stamp
            observed[(message.twin_id, tuple(message.values))] = stamp
    if not estimates:
        raise Ros2Error(f"{', '.join(str(p) for p in logs)}: no estimate in the log: nothing to export")
    written: dict[str, tuple[int, str]] = {}
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        tf = writer.add_connection(TF_TOPIC, TF_TYPE, typestore=store)
        for twin in sorted(estimates):
            given = params.load(params_file, params.node_name(twin)) if params_file is not None else {}
            twin_pose, twin_namespace = pose or given.get("pose"), namespace or given.get("namespace")
            parent = frame_of(frame or given.get("frame") or DEFAULT_FRAME, twin)
            child = frame_of(child_frame or given.get("child_frame") or DEFAULT_CHILD_FRAME, twin)
            chosen, _ = in_step_order(estimates[twin])
            dim = len(next(iter(chosen.values())).mean)
            try:
                mapping = parse_pose(twin_pose, dim)
            except ValueError as error:
                raise Ros2Error(str(error)) from None
            ns = namespace_of(twin_namespace, twin)
            connection = {name: writer.add_connection(f"{ns}/{name}", msgtype, typestore=store)
                          for name, msgtype in TOPICS.items()}

            for step, estimate in chosen.items():
                at = times[id(estimate)]
                sec, nsec = _stamp_of(estimate, observed)
                poses = pose_set(estimate, clouds.get((twin, step)), mapping)
                writer.write(connection["pose"], at, pose_cdr(sec, nsec, parent, poses))
                writer.write(connection["odom"], at, odometry_cdr(sec, nsec, parent, child, poses))
                writer.write(tf, at, tf_cdr(sec, nsec, parent, child, poses))
                if poses.particles is not None:
                    writer.write(connection["particles"], at, pose_array_cdr(sec, nsec, parent, poses.particles))
                if estimate.observation is not None:
                    writer.write(connection["observation"], at, float64_array_cdr(estimate.observation, "observation"))
                writer.write(connection["ess"], at, float64_cdr(estimate.ess))
                if estimate.ps is not None:
                    writer.write(connection["ps"], at, float64_cdr(estimate.ps))
                writer.write(connection["degraded"], at, bool_cdr(estimate.degraded))
            written[twin] = (len(chosen), ns)
    return written


def _stamp_of(estimate: Estimate, observed: dict) -> tuple[int, int]:
    """The stamp of the observation ``estimate`` filtered, as the live bridge publishes it: the logged
    observation of its step with its values (a live run), else the last one with its values (a run whose
    numbering skipped a late or duplicate observation), else the estimate's own stamp (a file or bag run: the
    observation's already)."""
    if estimate.observation:
        values = tuple(estimate.observation)
        stamp = observed.get((estimate.twin_id, estimate.step, values)) or observed.get((estimate.twin_id, values))
        if stamp is not None:
            return stamp
    return estimate.stamp.sec, estimate.stamp.nsec


def cmd_export(args: argparse.Namespace) -> int:
    if not args.ros2:
        raise Ros2Error("say what to export to: --ros2 LOG OUTDIR (a rosbag2 folder)")
    *logs, out = args.ros2
    if not logs:
        raise Ros2Error("--ros2 takes the log (one or more files of one run) and then the rosbag2 folder to write")
    written = export_ros2([Path(p) for p in logs], Path(out), pose=args.ros2_pose, namespace=args.ros2_namespace,
                          frame=args.ros2_frame, child_frame=args.ros2_child_frame,
                          params_file=None if args.ros2_params is None else Path(args.ros2_params))
    for twin, (steps, ns) in written.items():
        print(f"twin {twin}: {steps} steps as ROS 2 messages under {ns}/")
    print(f"wrote {out} (rosbag2, MCAP storage)")
    return 0


def register(subparsers) -> None:
    """Add the ``export`` command to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "export", help="export a recorded run to another format (--ros2: a rosbag2 folder)",
        description="Write a dtpf log as a rosbag2 folder (MCAP storage, CDR messages, metadata.yaml): each "
                    "twin's estimate (geometry_msgs/msg/PoseWithCovarianceStamped), particle cloud "
                    "(geometry_msgs/msg/PoseArray), observation (std_msgs/msg/Float64MultiArray), ESS, PS "
                    "(std_msgs/msg/Float64) and degraded flag (std_msgs/msg/Bool), one message per step, "
                    "so ros2 bag play replays the run and Foxglove opens it as a ROS 2 bag. Needs rosbags.")
    parser.add_argument("--ros2", nargs="+", metavar="LOG OUTDIR",
                        help="the log (one or more files of one run, e.g. a fleet's per-host logs), then the "
                             "rosbag2 folder to write (it must not exist)")
    parser.add_argument("--ros2-pose", default=None, metavar="MAP",
                        help="which state components a pose shows, e.g. 'x=0,y=1,yaw=3' (axes x, y, z, yaw; "
                             "default: x=0 and y=1 when the state has 2 or more)")
    parser.add_argument("--ros2-namespace", default=None, metavar="NS",
                        help="namespace of the topics; '{twin}' is the twin id (default: /dtpf/{twin})")
    parser.add_argument("--ros2-frame", default=None, metavar="FRAME",
                        help=f"frame_id of the headers, the parent of /tf (default: {DEFAULT_FRAME})")
    parser.add_argument("--ros2-child-frame", default=None, metavar="FRAME",
                        help="child_frame_id of the odometry and /tf, the twin's body; '{twin}' is the twin id "
                             f"(default: {DEFAULT_CHILD_FRAME})")
    parser.add_argument("--ros2-params", default=None, metavar="FILE",
                        help="the live bridge's ROS 2 parameters file: its pose, namespace, frame and child_frame "
                             "serve where these options are not given")
    parser.set_defaults(handler=cmd_export)
