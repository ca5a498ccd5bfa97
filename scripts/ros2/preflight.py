"""What ``dtpf launch --observations ros2:TOPIC`` checks before it starts anything.

The launcher reads ``--ros2-params``, learns the topic's message type (``--ros2-type``, the file's
``type``, else from the topic's publishers, waiting for one as the bridge would) and checks every
``--ros2-fields`` path and the ``--ros2-pose`` mapping against it: a misspelt path, an unknown parameter, a
type whose package is missing is one line and exit 2 before a layer starts. The bridge it then starts is
given the learnt type, so it does not wait for it again.
"""
from __future__ import annotations

import argparse
import sys
from types import SimpleNamespace

from dtpf.entity import rosbag
from dtpf.messages.config import RunConfig
from dtpf.scripts.ros2 import Ros2Error, params, require_rclpy
from dtpf.scripts.ros2.bridge import _mapper, bridge_words, discover_type, message_class
from dtpf.scripts.ros2.convert import parse_pose

__all__ = ["TYPE_WAIT", "check_before_start", "learn_type", "with_param_topics"]

#: How long the launcher waits for a publisher of the topic to learn its type (the bridge's --type-wait).
TYPE_WAIT = 30.0


def learn_type(topic: str, wait: float = TYPE_WAIT) -> str:
    """The message type the publishers of ``topic`` announce, with an rclpy node of the launcher's that
    lives only for this; Ros2Error when none is seen in ``wait`` seconds."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node("dtpf_launch")
        try:
            return discover_type(node, topic, None, wait, lambda: False,
                                 say=lambda text: print(f"dtpf: {text} (--ros2-type skips this)", file=sys.stderr,
                                                        flush=True))
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()


def check_before_start(config: RunConfig, args: argparse.Namespace, model) -> list[str]:
    """The bridge's command-line words for this launch, once its options are checked (see the module);
    Ros2Error, FieldPathError or ValueError in one line otherwise."""
    require_rclpy()
    values = params.load(args.ros2_params, params.node_name(config.twin)) if args.ros2_params else {}
    if config.ros2_sensors or config.ros2_control is not None:
        return _check_feeds(config, args, model, values)
    fields = config.ros2_fields or values.get("fields")
    if fields:
        rosbag.parse_fields(fields)  # its syntax, before any wait for a publisher
    parse_pose(args.ros2_pose or values.get("pose"), model.dim)
    msgtype = args.ros2_type or values.get("type")
    words = bridge_words(args)
    if msgtype is None:
        msgtype = learn_type(config.ros2_topic)
        words += ["--ros2-type", msgtype]
    _mapper(SimpleNamespace(ros2_fields=fields), config, model, message_class(msgtype))
    return words


def _check_feeds(config: RunConfig, args: argparse.Namespace, model, values: dict) -> list[str]:
    """:func:`check_before_start` for a driven twin's topics (:mod:`~dtpf.scripts.ros2.feeds`): each topic's
    paths parsed, its type learnt, its paths checked; the learnt types go to the bridge."""
    from dtpf.entity.calls import ModelCalls
    from dtpf.scripts.ros2.feeds import feed_mapper, feeds_of

    calls = ModelCalls(model)
    feeds = feeds_of(args, config, values)
    unknown = [feed.sensor for feed in feeds if feed.sensor is not None and feed.sensor not in calls.sensors]
    if unknown:
        raise Ros2Error(f"--observations {unknown[0]}=ros2:...: the model has no sensor {unknown[0]!r}; its sensors "
                        f"are {', '.join(str(name) for name in calls.sensors)}")
    missing = [name for name in calls.sensors if name is not None and name not in
               {feed.sensor for feed in feeds}]
    if missing and calls.named_sensors:
        raise Ros2Error(f"the model's sensor {missing[0]} has no topic: give --observations {missing[0]}=ros2:TOPIC")
    if calls.controls and not any(feed.control for feed in feeds):
        raise Ros2Error(f"the model is driven by controls ({', '.join(calls.controls)}): give their topic with "
                        f"--controls ros2:TOPIC")
    for feed in feeds:
        if feed.fields:
            rosbag.parse_fields(feed.fields)  # its syntax, before any wait for a publisher
    parse_pose(args.ros2_pose or values.get("pose"), model.dim)
    words = bridge_words(args)
    for feed in feeds:
        msgtype = feed.msgtype or learn_type(feed.topic)
        feed_mapper(feed, model, message_class(msgtype), tuple(calls.controls))
        if feed.msgtype is None:
            words += ["--ros2-control-type", msgtype] if feed.control else ["--ros2-type", f"{feed.sensor}={msgtype}"]
    return words


def with_param_topics(config: RunConfig, path, steps: int | None = None) -> RunConfig:
    """``config`` with a driven twin's sensor and control topics from the parameters file ``path``
    (``sensors.NAME.topic``, ``control.topic``) when the command line gives no observations; else as it is.
    ``steps``: the command line's --steps (None: until the stream ends)."""
    sensors, control = params.topics_of(params.load(path, params.node_name(config.twin)))
    files = {name: "ros2:" + entry["topic"] for name, entry in sensors.items() if "topic" in entry}
    if not files:
        return config
    update = {"sensor_files": files, "steps": steps}
    if "topic" in control and config.controls is None:
        update["controls"] = "ros2:" + control["topic"]
    return RunConfig(**{**config.model_dump(exclude_defaults=True), **update})
