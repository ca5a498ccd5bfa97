"""The ROS 2 topics a bridge feeds into its twin, and how each message becomes an observation or a control.

One topic (``--observations ros2:TOPIC`` or ``--topic``) feeds a twin of one sensor. A driven twin
(docs/guides/driven.md) is fed by a topic per sensor and one for its control::

    dtpf launch --model docs/examples/unicycle.py:Unicycle \\
        --observations gps=ros2:/gps --ros2-fields gps=point.x,point.y \\
        --observations beacons=ros2:/beacons --ros2-fields beacons=vector.x,vector.y,vector.z \\
        --controls ros2:/odom

or the same topics, types and fields from ``--ros2-params`` (``sensors.NAME.topic|type|fields``,
``control.topic|type|fields``; :mod:`dtpf.scripts.ros2.params`); the command line wins. Each sensor's
messages go to the twin's observation key named by ``sensor``, numbered per sensor; the control's to
``dtpf/<twin>/sensor/control``. A control's fields default by its type
(:data:`dtpf.entity.topics.CONTROL_FIELDS`).
"""
from __future__ import annotations

from dataclasses import dataclass

from dtpf.entity import rosbag, topics
from dtpf.entity.observations import ObservationError
from dtpf.scripts.ros2 import Ros2Error, params

__all__ = ["Feed", "feeds_of", "feed_mapper", "checked_values"]


@dataclass
class Feed:
    """One input topic of the bridge."""

    topic: str
    #: The model's sensor it feeds (None: the model's one sensor, or the control).
    sensor: str | None = None
    #: Whether it carries the control.
    control: bool = False
    #: Its message type, when given (else learnt from its publishers).
    msgtype: str | None = None
    #: Its field paths, when given.
    fields: str | None = None

    @property
    def label(self) -> str:
        """How messages name it: 'control', 'sensor gps' or the topic."""
        return "control" if self.control else f"sensor {self.sensor}" if self.sensor else self.topic


def checked_values(paths: list[rosbag.FieldPath]):
    """:func:`~dtpf.entity.rosbag.values_of` for messages of the type ``paths`` were checked against
    (:func:`~dtpf.entity.rosbag.check_fields`): the names are looked up without being checked again; a
    path that ends on anything but one float (an array, an integer), or that a message does not fit (an
    index past the end of its array), goes through values_of, which says why."""
    steps = [path.steps for path in paths]

    def values(message) -> list[float]:
        out = []
        try:
            for path in steps:
                value = message
                for name, selector in path:
                    value = getattr(value, name)
                    if selector is not None:
                        value = value[selector]
                if type(value) is not float:
                    return rosbag.values_of(message, paths)
                out.append(value)
        except (AttributeError, IndexError, TypeError):
            return rosbag.values_of(message, paths)
        return out
    return values


def _absolute(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic


def feeds_of(args, config, values: dict | None = None) -> list[Feed]:
    """The bridge's input topics: ``args`` (after :func:`~dtpf.scripts.ros2.bridge.resolve_options`), the run's
    ``config`` and the parameters file's ``values`` (:func:`~dtpf.scripts.ros2.params.load`)."""
    sensors, control = params.topics_of(values or {})
    given_types = getattr(args, "ros2_types", None) or {}
    fields = config.sensor_fields or {}
    named = config.ros2_sensors or {name: entry["topic"] for name, entry in sensors.items()
                                    if "topic" in entry and not config.sensor_files}
    out = [Feed(_absolute(topic), name, False, given_types.get(name) or sensors.get(name, {}).get("type"),
                fields.get(name) or sensors.get(name, {}).get("fields"))
           for name, topic in named.items()]
    unknown = [name for name in given_types if name not in named]
    if unknown:
        raise Ros2Error(f"--ros2-type {unknown[0]}=...: no sensor {unknown[0]} on a topic (give it with "
                        f"--observations {unknown[0]}=ros2:TOPIC)")
    control_topic = config.ros2_control or (control.get("topic") if not config.controls else None)
    if control_topic is not None:
        out.append(Feed(_absolute(control_topic), None, True,
                        getattr(args, "ros2_control_type", None) or control.get("type"),
                        config.control_fields or control.get("fields")))
    if not out:
        topic = getattr(args, "topic", None) or config.ros2_topic
        if topic is not None:
            out.append(Feed(_absolute(topic), None, False, getattr(args, "ros2_type", None),
                            getattr(args, "ros2_fields", None) or config.ros2_fields))
    return out


def feed_mapper(feed: Feed, model, cls, controls: tuple[str, ...] = ()):
    """message -> values of ``feed``, checked against its type's class ``cls``; Ros2Error or FieldPathError in
    one line when its paths do not fit the type."""

    msgtype = rosbag.type_name(cls())
    spec = feed.fields
    if feed.control:
        try:
            spec = topics.control_fields(msgtype, feed.fields, controls, f"--controls ros2:{feed.topic}")
        except ObservationError as error:
            raise Ros2Error(str(error)) from None
    if spec:
        paths = rosbag.parse_fields(spec)
        rosbag.check_fields(cls(), paths)
        if feed.control:
            width = _width(cls(), paths)
            if width is not None and width != len(controls):
                raise Ros2Error(f"--controls ros2:{feed.topic}: {spec} gives {width} values of a {msgtype}, the "
                                f"model's control has {len(controls)} ({', '.join(controls)})")
        return checked_values(paths)
    hook = getattr(topics.sensor_mapper(model, feed.sensor), rosbag.MODEL_HOOK, None) if feed.sensor else \
        getattr(model, rosbag.MODEL_HOOK, None)
    if hook is None:
        option = f"--ros2-fields {feed.sensor}=PATHS" if feed.sensor else "--ros2-fields"
        raise Ros2Error(f"say how a {msgtype} on {feed.topic} becomes an observation: {option} (e.g. "
                        f"'point.x,point.y'), or a method {rosbag.MODEL_HOOK}(message) in the model")
    return lambda message: [float(v) for v in hook(message)]


def _width(message, paths) -> int | None:
    """The number of values ``paths`` give of a default ``message`` (None when an array makes it vary)."""
    try:
        width = len(rosbag.values_of(message, paths))
    except Exception:
        return None
    return width or None
