"""``dtpf ros2``: a twin inside a ROS 2 system, a bridge process with a real rclpy node.

In: it subscribes to a ROS 2 topic and publishes each message as one
:class:`~dtpf.messages.models.Observation` on the twin's live key ``dtpf/<twin>/sensor/observation``,
numbered 1, 2, ... (after the last the twin's entity accepted), so the entity's intake handles
duplicates, late, malformed and wrong-length observations as for any sensor. The message's
``header.stamp`` (its receive time when it has no header) is the observation's stamp, recorded with it.
Field paths (``--ros2-fields``, :mod:`dtpf.entity.rosbag`) or the model's
``observation_from_ros2(message)`` make the values; a message they do not fit, or with a NaN or an
infinity, is counted and skipped (the bridge's status, role sensor), never sent.

A driven twin (docs/guides/driven.md) is fed by a topic per sensor (``--observations NAME=ros2:TOPIC``,
each message sent named by its ``sensor`` and numbered per sensor) and a control topic
(``--controls ros2:TOPIC``, each message a :class:`~dtpf.messages.models.Control` on
``dtpf/<twin>/sensor/control``): :mod:`dtpf.scripts.ros2.feeds`.

Out: the twin's estimate, particles, ESS, PS and degraded flag as ROS 2 messages under
``/dtpf/<twin>/`` (:mod:`dtpf.scripts.ros2.convert`), QoS reliable, volatile, keep last 100 by default.

``dtpf launch --observations ros2:TOPIC`` starts it beside the layers; alone, it joins a twin running
elsewhere::

    dtpf ros2 --model m.py:M --twin t --topic /range --ros2-fields range --connect tcp/127.0.0.1:7447

With ``--secure DIR`` it publishes observations in the sensor role and reads the twin in the viewer
role (two Zenoh sessions). It needs rclpy (the ``[ros2]`` extra); nothing else in dtpf imports it.
"""
from __future__ import annotations

import argparse
import importlib
import json
import logging
import math
import os
import sys
import threading
import time
from collections import OrderedDict

from dtpf.entity import model_ref, rosbag
from dtpf.messages import keys
from dtpf.messages.codec import MessageError, decode
from dtpf.messages.config import RunConfig, add_run_arguments, config_from_args
from dtpf.messages.foxglove import PointCloud
from dtpf.messages.models import MAX_OBSERVATION_VALUES, Control, Estimate, Layer, Observation
from dtpf.scripts.console import run_command
from dtpf.scripts.ros2 import Ros2Error, params, require_rclpy
from dtpf.scripts.ros2.convert import (
    TF_TOPIC,
    TF_TYPE,
    TOPICS,
    bool_cdr,
    cloud_covariances,
    cloud_points_of,
    float64_cdr,
    odometry_cdr,
    parse_pose,
    pose_array_cdr,
    pose_cdr,
    pose_set,
    pose_set_particles,
    tf_cdr,
)
from dtpf.scripts.ros2.export import DEFAULT_CHILD_FRAME, DEFAULT_FRAME, frame_of, namespace_of
from dtpf.shell.bus import BusError, add_zenoh_arguments, open_session, publisher, zenoh_config, zenoh_config_from_args
from dtpf.shell.service import ServiceShell

__all__ = ["bridge_arguments", "bridge_words", "command_line", "main", "register", "resolve_options"]

log = logging.getLogger("dtpf.ros2")

#: How long an estimate waits for its step's particle cloud before its pose goes out without the cloud.
CLOUD_WAIT = 0.5
#: The bridge's options when neither the command line nor --ros2-params gives them.
DEFAULTS = {"ros2_frame": DEFAULT_FRAME, "ros2_child_frame": DEFAULT_CHILD_FRAME, "ros2_depth": 100,
            "ros2_best_effort": False}
#: The options dtpf launch passes on to its bridge (their argparse destinations).
BRIDGE_OPTIONS = ("ros2_type", "ros2_pose", "ros2_namespace", "ros2_frame", "ros2_child_frame", "ros2_depth",
                  "ros2_covariance", "ros2_params")


def message_class(msgtype: str):
    """The rclpy class of 'pkg/msg/Name'; Ros2Error when it is not a message type or not installed."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise Ros2Error(f"--ros2-type {msgtype!r}: expected a message type such as sensor_msgs/msg/Range")
    package, _, name = parts
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError:
        raise Ros2Error(f"message type {msgtype}: its Python package {package} is not installed "
                        f"(pip install ros-{package.replace('_', '-')})") from None
    cls = getattr(module, name, None)
    if cls is None:
        raise Ros2Error(f"message type {msgtype}: {package}.msg has no {name}")
    return cls


def _types_of(node, topic: str) -> list[str]:
    return next((types for name, types in node.get_topic_names_and_types() if name == topic), [])


def discover_type(node, topic: str, given: str | None, wait: float, stopping, say=None) -> str:
    """The message type of ``topic``: ``given`` (checked against the publishers seen), or the one its
    publishers announce, waiting up to ``wait`` seconds for one (``say``: told once that it waits);
    Ros2Error otherwise."""
    import rclpy

    deadline = time.monotonic() + wait
    said = False
    while True:
        types = _types_of(node, topic)
        if given is not None:
            if types and given not in types:
                raise Ros2Error(f"topic {topic} carries {', '.join(types)}, not {given} (--ros2-type)")
            return given
        if len(types) > 1:
            raise Ros2Error(f"topic {topic} carries several types ({', '.join(types)}): give one with --ros2-type")
        if types:
            return types[0]
        if time.monotonic() > deadline or stopping():
            raise Ros2Error(f"no publisher of {topic} seen in {wait:.0f} s: start it, or give its type with "
                            f"--ros2-type (e.g. sensor_msgs/msg/Range)")
        if not said:
            (say or log.info)(f"waiting for a publisher of {topic} to learn its type")
            said = True
        rclpy.spin_once(node, timeout_sec=0.1)


def ros2_executor():
    """rclpy's EventsExecutor (its event queue in C++: a callback costs a fraction of the wait-set executor's),
    else the SingleThreadedExecutor; DTPF_ROS2_EXECUTOR=single chooses the latter."""
    from rclpy.executors import SingleThreadedExecutor

    if os.environ.get("DTPF_ROS2_EXECUTOR", "events") != "single":
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor()
        except ImportError:
            pass
    return SingleThreadedExecutor()


def qos(args, best_effort: bool | None = None):
    """The QoS profile of ``args`` (``best_effort`` None: --ros2-best-effort's choice)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    best_effort = args.ros2_best_effort if best_effort is None else best_effort
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.ros2_depth,
                      reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def resolve_options(args: argparse.Namespace, config: RunConfig) -> argparse.Namespace:
    """``args`` with what ``--ros2-params`` gives where the command line gave nothing (the topic only when
    neither --topic nor --observations ros2:TOPIC names one), then :data:`DEFAULTS`."""
    if getattr(args, "ros2_params", None):
        for parameter, value in params.load(args.ros2_params, params.node_name(config.twin)).items():
            if parameter not in params.PARAMETERS:  # a driven twin's topic (sensors.NAME.KEY, control.KEY): feeds
                continue
            dest = params.PARAMETERS[parameter][0]
            if parameter == "topic":
                if getattr(args, "topic", None) is None and config.ros2_topic is None:
                    args.topic = value
            elif getattr(args, dest, None) is None:
                setattr(args, dest, value)
    for dest, value in DEFAULTS.items():
        if getattr(args, dest, None) is None:
            setattr(args, dest, value)
    return args


def bridge_words(args: argparse.Namespace) -> list[str]:
    """The bridge's options given on a command line (dtpf launch's), as the bridge's command-line words."""
    words = []
    for dest in BRIDGE_OPTIONS:
        value = getattr(args, dest, None)
        if value is not None:
            words += ["--" + dest.replace("_", "-"), str(value)]
    if getattr(args, "ros2_best_effort", None):
        words.append("--ros2-best-effort")
    for sensor, msgtype in (getattr(args, "ros2_types", None) or {}).items():
        words += ["--ros2-type", f"{sensor}={msgtype}"]
    if getattr(args, "ros2_control_type", None):
        words += ["--ros2-control-type", args.ros2_control_type]
    return words


#: Why /tf is not published where tf2_msgs cannot be imported.
NO_TF2 = ("tf2_msgs cannot be imported here: it has no wheel on PyPI; a ROS 2 installation provides it "
          "(docs/guides/ros2.md, 'A ROS 2 installation')")


def optional_publisher(node, msgtype: str, topic: str, profile):
    """A publisher of ``msgtype`` on ``topic``, or None (said once in the log) when its Python package is not
    installed here: nav_msgs comes with the [ros2] extra; tf2_msgs has no wheel, a ROS 2 installation
    provides it (:data:`NO_TF2`)."""
    try:
        cls = message_class(msgtype)
    except Ros2Error as error:
        log.warning("%s not published: %s", topic, NO_TF2 if msgtype == TF_TYPE else error)
        return None
    return node.create_publisher(cls, topic, profile)


class Outbound:
    """The twin's estimates and clouds (Zenoh) to ROS 2 publishers.

    Zenoh's callbacks publish, one at a time (a lock); the executor's thread serves the input, and looks
    for estimates that waited too long. The pose goes out with its estimate, which carries the covariances
    between components for a state of 2 to 8; the particles go out with their cloud, which is taken from
    the twin only while the particles have a subscriber. Beyond 8 components, when the cloud gives the
    pose a covariance between two components (:func:`~dtpf.scripts.ros2.convert.cloud_covariances`), a
    step's pose goes out when its estimate and its cloud are both in (in either order), CLOUD_WAIT after
    the estimate without the cloud, or at once while the entity publishes no clouds, its particles right
    after it. Every message is published as its CDR bytes (:mod:`dtpf.scripts.ros2.convert`), the pose
    first."""

    def __init__(self, node, session, config: RunConfig, dim: int, args, stamps):
        self.mapping = parse_pose(args.ros2_pose, dim)
        self.dim = dim
        self.cloud_stamps: OrderedDict = OrderedDict()
        self.frame = frame_of(args.ros2_frame, config.twin)
        self.child_frame = frame_of(args.ros2_child_frame, config.twin)
        self.stamps = stamps
        ns = namespace_of(args.ros2_namespace, config.twin)
        self.namespace = ns
        profile = qos(args)
        self.pub = {name: node.create_publisher(message_class(msgtype), f"{ns}/{name}", profile)
                    for name, msgtype in TOPICS.items() if name not in ("observation", "odom")}
        #: nav_msgs/Odometry and /tf, each where its package can be imported (else None, said in the log).
        self.odom = optional_publisher(node, TOPICS["odom"], f"{ns}/odom", profile)
        self.tf = optional_publisher(node, TF_TYPE, TF_TOPIC, profile)
        self.pending: dict[int, tuple[Estimate, float]] = {}
        self.clouds: OrderedDict = OrderedDict()  # a step's cloud that came before its estimate
        #: True once an estimate waited CLOUD_WAIT for its cloud in vain (an entity with --cloud-points 0).
        self.no_clouds = False
        #: False (--ros2-covariance diagonal): the pose's covariance is the estimate's variances alone.
        self.covariances = args.ros2_covariance != "diagonal"
        #: False (covariances the estimate carries, or none the cloud could give): the pose goes out with its
        #: estimate, the particles with their cloud.
        self.wait_for_cloud = self.covariances and cloud_covariances(self.mapping, dim)
        self.published = 0
        self.samples = 0
        #: The latest step of the twin's estimates taken (published or waiting for its cloud).
        self.last_step = 0
        self.closed = False
        self.lock = threading.Lock()
        self.twin = config.twin
        self.session = session
        self.subscribers = [self._subscribe("estimate", Estimate)]
        #: The twin's cloud (43 kB a step at N = 1e3) is taken only while it is used: a pose that waits for it,
        #: or a subscriber of the particles (:meth:`tick` looks).
        self.cloud_subscriber = self._subscribe("cloud", PointCloud) if self.wait_for_cloud else None

    def _subscribe(self, topic: str, cls):
        return self.session.declare_subscriber(keys.key(self.twin, "entity", topic),
                                               lambda sample: self._on_sample(sample, cls))

    def _on_sample(self, sample, cls) -> None:  # a Zenoh thread
        self.samples += 1
        with self.lock:
            if not self.closed:
                self.handle(sample.payload.to_bytes(), cls)

    def handle(self, payload: bytes, cls) -> None:
        """One sample that arrived on the twin's key of ``cls`` (the checks of decode_for_key, without
        parsing the key again)."""
        try:
            message = decode(payload, cls)
        except MessageError as error:
            log.debug("not a message of the twin: %s", error)
            return
        if message.twin_id != self.twin or message.layer != Layer.ENTITY:
            log.debug("not a message of the twin: %s of twin %r, layer %s", cls.__name__, message.twin_id,
                      message.layer.value)
            return
        if isinstance(message, Estimate) and len(message.mean) != self.dim:
            log.debug("an estimate of %d components, not the model's %d", len(message.mean), self.dim)
            return
        if isinstance(message, Estimate):
            self.last_step = max(self.last_step, message.step)
            cloud = self.clouds.pop(message.step, None)
            if cloud is not None or self.no_clouds or not self.wait_for_cloud:
                self._publish(message, cloud)
            else:
                self.pending[message.step] = (message, time.monotonic())
        elif isinstance(message, PointCloud):
            self.no_clouds = False
            waiting = self.pending.pop(message.step, None)
            if waiting is not None:
                self._publish(waiting[0], cloud_points_of(message))
            elif not self.wait_for_cloud and message.step in self.cloud_stamps:  # the pose went out already
                stamp = self.cloud_stamps.pop(message.step)
                points = cloud_points_of(message)
                self.pub["particles"].publish(pose_array_cdr(*stamp, self.frame,
                                                             pose_set_particles(points, self.mapping, self.dim)))
            else:  # before its estimate (a Zenoh thread of its own may serve it first): out with the estimate
                self.clouds[message.step] = cloud_points_of(message)
                while len(self.clouds) > 100:
                    self.clouds.popitem(last=False)
        self._expire()

    def tick(self) -> None:
        """The executor's thread, at least every 0.1 s: estimates that waited too long for their cloud go out;
        the cloud is taken from the twin while the particles have a subscriber, and left when none has."""
        with self.lock:
            self._expire()
        if self.wait_for_cloud or self.closed:
            return
        wanted = self.pub["particles"].get_subscription_count() > 0
        if wanted and self.cloud_subscriber is None:
            self.cloud_subscriber = self._subscribe("cloud", PointCloud)
        elif not wanted and self.cloud_subscriber is not None:
            subscriber, self.cloud_subscriber = self.cloud_subscriber, None
            subscriber.undeclare()
            with self.lock:
                self.cloud_stamps.clear()

    def _expire(self) -> None:
        now = time.monotonic()
        for step in [s for s, (_, at) in self.pending.items() if now - at > CLOUD_WAIT]:
            self.no_clouds = True
            self._publish(self.pending.pop(step)[0], None)

    def _publish(self, estimate: Estimate, points) -> None:
        poses = pose_set(estimate, points, self.mapping, self.covariances)
        stamp = self.stamps.get(tuple(estimate.observation or ()))
        sec, nsec = stamp if stamp is not None else (estimate.stamp.sec, estimate.stamp.nsec)
        self.pub["pose"].publish(pose_cdr(sec, nsec, self.frame, poses))
        if self.odom is not None:
            self.odom.publish(odometry_cdr(sec, nsec, self.frame, self.child_frame, poses))
        if self.tf is not None:
            self.tf.publish(tf_cdr(sec, nsec, self.frame, self.child_frame, poses))
        self.pub["ess"].publish(float64_cdr(estimate.ess))
        if estimate.ps is not None:
            self.pub["ps"].publish(float64_cdr(estimate.ps))
        self.pub["degraded"].publish(bool_cdr(estimate.degraded))
        if poses.particles is not None:
            self.pub["particles"].publish(pose_array_cdr(sec, nsec, self.frame, poses.particles))
        elif not self.wait_for_cloud:
            self.cloud_stamps[estimate.step] = (sec, nsec)
            while len(self.cloud_stamps) > 100:
                self.cloud_stamps.popitem(last=False)
        self.published += 1
        log.debug("published step %d (%s)", estimate.step, "with its cloud" if points is not None else "no cloud")

    def close(self, progress, quiet: float = 0.3, acked: float = 10.0, last_step: int | None = None,
              patience: float = 5.0) -> None:
        """Take what the twin still sends until ``quiet`` seconds pass without a sample (and, if the run's
        ``last_step`` is known, until its estimate is in or ``patience`` seconds pass: on a loaded machine it
        can come later than ``quiet``), publish what waits, then wait (at most ``acked`` s) until reliable
        subscribers have acknowledged everything; ``progress()`` is called while this moves (the shell's exit
        watchdog)."""
        from rclpy.duration import Duration

        deadline = time.monotonic() + patience
        while True:
            seen = self.samples
            time.sleep(quiet)
            behind = last_step is not None and self.last_step < last_step and time.monotonic() < deadline
            if self.samples == seen and not behind:
                break
            progress()
        with self.lock:
            self.closed = True
            for step in sorted(self.pending):
                self._publish(self.pending[step][0], None)
            self.pending.clear()
        for subscriber in self.subscribers + [self.cloud_subscriber]:
            if subscriber is not None:
                subscriber.undeclare()
        deadline = time.monotonic() + acked
        for publisher in [*self.pub.values(), *filter(None, (self.odom, self.tf))]:
            while not publisher.wait_for_all_acked(Duration(seconds=0.5)) and time.monotonic() < deadline:
                progress()


class Input:
    """The input topic's subscription, its reliability matched to its publishers'. Reliable (each message
    retransmitted until received) unless --ros2-best-effort or a publisher offers best effort only (as most
    sensor drivers do): a reliable subscriber never matches such a publisher, so the subscription is then
    made best effort, which receives from reliable and best-effort publishers alike, and the log says so in
    one line naming --ros2-best-effort. A publisher that appears later is looked at by :meth:`tick`."""

    def __init__(self, node, cls, topic: str, callback, args, say):
        self.node, self.cls, self.topic, self.callback, self.args, self.say = node, cls, topic, callback, args, say
        self.best_effort = bool(args.ros2_best_effort)
        self.offered = False  # an incompatible publisher was reported (an rclpy thread)
        if not self.best_effort and self._best_effort_publisher():
            self._switch()
        self.subscription = self._create()

    def _best_effort_publisher(self) -> bool:
        from rclpy.qos import ReliabilityPolicy

        return any(info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                   for info in self.node.get_publishers_info_by_topic(self.topic))

    def _create(self):
        from rclpy.event_handler import SubscriptionEventCallbacks

        events = SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible)
        return self.node.create_subscription(self.cls, self.topic, self.callback, qos(self.args, self.best_effort),
                                             event_callbacks=events)

    def _on_incompatible(self, info) -> None:
        self.offered = True

    def _switch(self) -> None:
        self.best_effort = True
        self.say(f"a publisher of {self.topic} offers best-effort QoS only: the bridge subscribes best effort, "
                 f"which hears it (--ros2-best-effort does so from the start)")

    def tick(self) -> None:
        """The executor's thread, about once a second: a best-effort publisher met while subscribed reliable
        makes the subscription best effort."""
        if self.best_effort or not (self.offered or self._best_effort_publisher()):
            return
        self.offered = False
        if self._best_effort_publisher():
            self.node.destroy_subscription(self.subscription)
            self._switch()
            self.subscription = self._create()


class Inbound:
    """ROS 2 messages to the twin's live observations (of ``sensor``, a driven twin's), or with ``control`` to
    its controls (dtpf/<twin>/sensor/control): mapped, checked, numbered, stamped."""

    def __init__(self, shell: ServiceShell, mapper, start: int, stamps, *, sensor: str | None = None,
                 control: bool = False):
        self.shell = shell
        self.mapper = mapper
        self.sequence = start - 1
        self.stamps = stamps
        self.sent = 0
        self.control = control
        #: The name of the values' field: a Control carries them in 'control'.
        self.field = b"control" if control else b"values"
        head = (Control.model_construct(**shell.header(0), layer=Layer.SENSOR, control=[]) if control else
                Observation.model_construct(**shell.header(0), layer=Layer.SENSOR, values=[]))
        self.key = keys.key_for(head)
        self.publisher = publisher(shell.session, self.key)
        #: The run's fields as pydantic writes them ('{"run_id":...,"twin_id":...,"layer":"sensor"'): a message
        #: is this and its step, stamp and values (json.dumps writes each float as repr: the same number).
        self.head = head.model_dump_json(include={"run_id", "twin_id", "layer"}).encode()[:-1]
        if sensor is not None:
            self.head += b',"sensor":' + json.dumps(sensor).encode()

    def __call__(self, message) -> None:
        shell = self.shell
        shell.received += 1
        try:
            values = self.mapper(message)
        except (rosbag.FieldPathError, Ros2Error) as error:
            shell.reject("a ROS message the field paths do not fit", str(error))
            return
        except Exception as error:  # the model's observation_from_ros2
            shell.reject(f"{rosbag.MODEL_HOOK} raised an error", f"{rosbag.MODEL_HOOK}: {type(error).__name__}: {error}")
            return
        if not all(math.isfinite(v) for v in values):
            shell.reject("a ROS message with a NaN or infinite value", f"values {values[:8]} are not all finite")
            return
        if not 0 < len(values) <= MAX_OBSERVATION_VALUES:
            shell.reject("a ROS message with no values or too many",
                         f"{len(values)} values (an observation holds 1 to {MAX_OBSERVATION_VALUES})")
            return
        stamp = normalized_stamp(rosbag.stamp_of(message))
        if stamp is None or stamp == (0, 0) or stamp[0] < 0:
            now = time.time_ns()
            stamp = (now // 10**9, now % 10**9)
        self.sequence += 1
        if not self.control:
            self.stamps[tuple(values)] = stamp
            if len(self.stamps) > 10_000:
                self.stamps.popitem(last=False)
        self.publisher.put(self.payload(self.sequence, stamp, values))
        self.sent += 1

    def payload(self, sequence: int, stamp: tuple[int, int], values: list[float]) -> bytes:
        """The Observation's JSON, formatted here: every field is checked above or comes from the shell, and
        the entity that receives it validates it. Building and serialising the message with pydantic was a
        third of the bridge's time per observation; this is a fraction of that."""
        values_json = json.dumps([float(v) for v in values], separators=(",", ":")).encode()
        return b'%s,"step":%d,"stamp":{"sec":%d,"nsec":%d},"%s":%s}' % (
            self.head, sequence, stamp[0], stamp[1], self.field, values_json)


def normalized_stamp(stamp: tuple[int, int] | None) -> tuple[int, int] | None:
    """A ROS 2 stamp with ``nanosec`` carried into ``sec``: (1, 1_500_000_000) is (2, 500_000_000), the same
    instant, as rclpy's Time reads it (a stamp's nanosec should stay below 1e9; publishers do not all
    normalise it, and the observation on the bus must)."""
    if stamp is None:
        return None
    sec, nanosec = int(stamp[0]), int(stamp[1])
    return sec + nanosec // 10**9, nanosec % 10**9


def _mapper(args, config: RunConfig, model, cls):
    if args.ros2_fields or config.ros2_fields:
        paths = rosbag.parse_fields(args.ros2_fields or config.ros2_fields)
        rosbag.check_fields(cls(), paths)
        from dtpf.scripts.ros2.feeds import checked_values
        return checked_values(paths)
    hook = getattr(model, rosbag.MODEL_HOOK, None)
    if hook is None:
        raise Ros2Error(f"say how a {rosbag.type_name(cls())} becomes an observation: --ros2-fields (e.g. 'range', "
                        f"'point.x,point.y', 'ranges[0:8]'), or a method {rosbag.MODEL_HOOK}(message) in the model")
    return lambda message: [float(v) for v in hook(message)]


def main(config: RunConfig, zconf, args: argparse.Namespace) -> int:
    """Bridge ``args.topic`` (or ``ros2:TOPIC``; a driven twin's sensor and control topics,
    :mod:`~dtpf.scripts.ros2.feeds`) into the twin, and the twin out to ROS 2, until stopped."""
    from dtpf.entity.calls import ModelCalls
    from dtpf.scripts.ros2.feeds import feeds_of
    from dtpf.scripts.sensor import resume_point

    require_rclpy()
    values = params.load(args.ros2_params, params.node_name(config.twin)) if getattr(args, "ros2_params", None) else {}
    resolve_options(args, config)
    feeds = feeds_of(args, config, values)
    if not feeds and args.no_out:
        raise Ros2Error("nothing to bridge: give --topic (in) or leave the outputs on")
    model = model_ref.resolve(config.model_ref)
    controls = tuple(ModelCalls(model).controls)
    if any(feed.control for feed in feeds) and not controls:
        raise Ros2Error("--controls ros2:TOPIC: the model takes no control input (its controls are empty)")
    mappers: dict[int, object] = {}
    classes: dict[int, object] = {}
    for i, feed in enumerate(feeds):
        if feed.msgtype is not None:  # a type given: its field paths checked first
            classes[i] = message_class(feed.msgtype)
            mappers[i] = _feed_mapper(feed, args, config, model, classes[i], controls)
        elif feed.fields:  # a path that does not parse: one line now
            rosbag.parse_fields(feed.fields)
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    # Fast DDS writes a sample in the publishing thread (not a thread of its own): less latency, and what
    # wait_for_all_acked waits for is on its way when the bridge stops.
    os.environ.setdefault("RMW_FASTRTPS_PUBLICATION_MODE", "SYNCHRONOUS")
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    viewer = outbound = None
    try:
        node = rclpy.create_node(params.node_name(config.twin))
        with ServiceShell("sensor", config, zconf) as shell:
            stamps: OrderedDict = OrderedDict()
            if not args.no_out:  # the twin's topics exist before the input's publisher is awaited
                if args.secure:  # the viewer role reads the twin; the sensor role only publishes
                    viewer = open_session(zenoh_config(mode=args.mode, connect=args.connect, listen=args.listen,
                                                       config_file=args.zenoh_config, cfg=args.cfg,
                                                       secure=args.secure, role="viewer"))
                outbound = Outbound(node, viewer or shell.session, config, model.dim, args, stamps)
            msgtypes = {}
            for i, feed in enumerate(feeds):
                msgtypes[i] = discover_type(node, feed.topic, feed.msgtype, args.type_wait, lambda: shell.stopping)
                if i not in classes:
                    classes[i] = message_class(msgtypes[i])
                    mappers[i] = _feed_mapper(feed, args, config, model, classes[i], controls)
            shell.running()
            inputs = []
            if feeds:
                if args.wait_for_entity:
                    missing = shell.presence.wait_for(["entity"], args.wait_for_entity)
                    if missing:
                        shell.log.warning("no entity of twin %s after %.1f s: bridging anyway", config.twin,
                                          args.wait_for_entity)
                start = resume_point(shell, args.resume_wait) + 1
                for i, feed in enumerate(feeds):
                    inbound = Inbound(shell, mappers[i], start, stamps, sensor=feed.sensor, control=feed.control)
                    inputs.append((feed, msgtypes[i], inbound,
                                   Input(node, classes[i], feed.topic, inbound, args, shell.log.warning)))
                    shell.log.info("bridging %s (%s) to %s%s from sequence %d%s", feed.topic, msgtypes[i],
                                   inbound.key if feed.control else config.observation_key() or inbound.key,
                                   f" as {feed.label}" if feed.sensor or feed.control else "", start,
                                   f"; the twin out under {outbound.namespace}/" if outbound else "")
            elif outbound is not None:
                shell.log.info("publishing twin %s under %s/", config.twin, outbound.namespace)
            executor = ros2_executor()
            executor.add_node(node)
            next_look, foreign = time.monotonic() + 1.0, set()
            while not shell.stopping:
                executor.spin_once(timeout_sec=0.1)
                if outbound is not None:
                    outbound.tick()
                if inputs and time.monotonic() > next_look:  # a publisher of another type never matches
                    next_look = time.monotonic() + 1.0
                    for feed, msgtype, _, subscription in inputs:
                        subscription.tick()
                        for other in set(_types_of(node, feed.topic)) - {msgtype} - foreign:
                            foreign.add(other)
                            shell.reject("a publisher of another message type on the topic",
                                         f"{feed.topic} has a publisher of {other}; the bridge takes {msgtype}: its "
                                         f"messages are not received")
            if outbound is not None:
                shell.watchdog.step = "publishing the twin's last messages on ROS 2"
                outbound.close(shell.watchdog.progress, last_step=config.steps)
            sent = sum(inbound.sent for _, _, inbound, _ in inputs if not inbound.control)
            shell.log.info("stopped: %s%s", f"{sent} observations sent" if inputs else "",
                           f", {outbound.published} estimates published" if outbound is not None else "")
    finally:
        if viewer is not None:
            viewer.close()
        rclpy.try_shutdown()
    return 130


def _feed_mapper(feed, args, config: RunConfig, model, cls, controls):
    """The mapper of one input: a driven twin's through :func:`~dtpf.scripts.ros2.feeds.feed_mapper`, the one
    topic's as before."""
    if feed.sensor is None and not feed.control:
        return _mapper(args, config, model, cls)
    from dtpf.scripts.ros2.feeds import feed_mapper

    return feed_mapper(feed, model, cls, controls)


class _TypeAction(argparse.Action):
    """``--ros2-type TYPE``, or ``--ros2-type NAME=TYPE`` once per sensor (into ``ros2_types``)."""

    def __call__(self, parser, namespace, value, option_string=None):
        name, sep, msgtype = value.partition("=")
        if sep:
            types = dict(getattr(namespace, "ros2_types", None) or {})
            types[name.strip()] = msgtype.strip()
            namespace.ros2_types = types
            return
        setattr(namespace, self.dest, value)


def bridge_arguments(parser: argparse.ArgumentParser, defaults: bool = True) -> None:
    """The bridge's own options (also those ``dtpf launch`` passes on for ``--observations ros2:TOPIC``,
    ``defaults`` False). Every option defaults to None (not given): :func:`resolve_options` fills in what
    --ros2-params gives, then :data:`DEFAULTS`."""
    group = parser.add_argument_group("ROS 2 (with --observations ros2:TOPIC)" if not defaults else "ROS 2")
    group.add_argument("--ros2-params", default=None, metavar="FILE",
                       help="a ROS 2 parameters file (node: ros__parameters: ...; the node is dtpf_<twin> or /**) "
                            "giving any of these options by their names without 'ros2-' (topic, type, fields, "
                            "pose, namespace, frame, child_frame, depth, covariance, best_effort); the command "
                            "line wins")
    group.add_argument("--ros2-type", default=None, metavar="TYPE", action=_TypeAction,
                       help="the topic's message type, e.g. sensor_msgs/msg/Range (default: learnt from its "
                            "publishers); a driven twin's sensor on a topic: NAME=TYPE, once per sensor")
    group.add_argument("--ros2-control-type", default=None, metavar="TYPE",
                       help="the control topic's message type (geometry_msgs/msg/Twist, TwistStamped, "
                            "nav_msgs/msg/Odometry, sensor_msgs/msg/Imu, ...; default: learnt from its publishers)")
    group.add_argument("--ros2-pose", default=None, metavar="MAP",
                       help="which state components the published pose shows, e.g. 'x=0,y=1,yaw=3' (axes x, y, z, "
                            "yaw; default: x=0, and y=1 for a state of 2 or more)")
    group.add_argument("--ros2-namespace", default=None, metavar="NS",
                       help="namespace of the published topics; '{twin}' is the twin id (default: /dtpf/{twin})")
    group.add_argument("--ros2-frame", default=None, metavar="FRAME",
                       help=f"frame_id of the published headers, the parent of /tf (default: {DEFAULT_FRAME})")
    group.add_argument("--ros2-child-frame", default=None, metavar="FRAME",
                       help="child_frame_id of the odometry and /tf, the twin's body; '{twin}' is the twin id "
                            f"(default: {DEFAULT_CHILD_FRAME})")
    group.add_argument("--ros2-depth", type=int, default=None, metavar="N",
                       help=f"QoS history depth, in and out (default: {DEFAULTS['ros2_depth']})")
    group.add_argument("--ros2-covariance", choices=("full", "diagonal"), default=None,
                       help="the pose's covariance: 'full', the weighted covariances between the mapped components "
                            "(the estimate's for a state of 2 to 8 components; beyond, the step's particle cloud's, "
                            "which the pose then waits for); 'diagonal', the variances only (default: full)")
    group.add_argument("--ros2-best-effort", action="store_true", default=None,
                       help="QoS best effort instead of reliable, in and out (a publisher that offers best effort "
                            "only is heard without it: the input then subscribes best effort)")


def register(subparsers) -> None:
    """Add the ``ros2`` command (the bridge) to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "ros2", help="bridge a twin and ROS 2: a topic in as observations, the estimate out (needs rclpy)",
        description="A bridge with an rclpy node: each message of --topic becomes one observation of the twin "
                    "(dtpf/<twin>/sensor/observation) by --ros2-fields or the model's observation_from_ros2 (a "
                    "driven twin: --observations NAME=ros2:TOPIC per sensor, --controls ros2:TOPIC); "
                    "the twin's estimate (PoseWithCovarianceStamped), particles (PoseArray), ESS, PS and "
                    "degraded flag are published under /dtpf/<twin>/. Needs the [ros2] extra; see "
                    "docs/guides/ros2.md.")
    add_run_arguments(parser)
    group = parser.add_argument_group("bridge")
    group.add_argument("--no-out", action="store_true", help="do not publish the twin on ROS 2 (in only)")
    group.add_argument("--type-wait", type=float, default=30.0, metavar="SECONDS",
                       help="how long to wait for a publisher of the topic to learn its type (default: %(default)s)")
    group.add_argument("--resume-wait", type=float, default=1.5, metavar="SECONDS",
                       help="how long to listen for the entity's status to continue its numbering (default: "
                            "%(default)s)")
    group.add_argument("--wait-for-entity", type=float, default=30.0, metavar="SECONDS",
                       help="wait at most this long for the twin's entity before subscribing (default: %(default)s)")
    group.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                       help="logging level on stderr (default: %(default)s)")
    group.add_argument("--exit-with-parent", action="store_true", help=argparse.SUPPRESS)
    bridge_arguments(parser)
    add_zenoh_arguments(parser)
    parser.set_defaults(handler=cmd_ros2)


def cmd_ros2(args: argparse.Namespace) -> int:
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s ros2        %(levelname)s %(message)s")
    require_rclpy()
    config = config_from_args(args)
    if config.observation_file is not None or (config.sensor_files and not config.ros2_sensors):
        raise Ros2Error("the bridge takes a live topic (--topic or --observations ros2:TOPIC), not a file")
    if args.exit_with_parent:
        from dtpf.shell.service import _watch_parent
        _watch_parent()
    try:
        code = main(config, zenoh_config_from_args(args, role="sensor"), args)
    except BusError as error:
        print(f"dtpf ros2: error: {error}", file=sys.stderr)
        return 2
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)  # past rclpy's and Zenoh's threads


def command_line(argv: list[str] | None = None) -> int:
    """``python -m dtpf.scripts.ros2``: the same as ``dtpf ros2``."""
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.ros2")
    commands = parser.add_subparsers(dest="command", required=True)
    register(commands)
    return run_command(parser, parser.parse_args(["ros2", *(sys.argv[1:] if argv is None else argv)]))
