"""``--ros2-params FILE``: the bridge's options from a ROS 2 parameters file.

The file has the layout ``ros2 run ... --params-file`` reads: node names (or the wildcard ``/**``) at the
top, each with ``ros__parameters``::

    dtpf_rb_ros:                  # the bridge's node: dtpf_<twin> ('-' and '.' as '_'); or /**
      ros__parameters:
        topic: /target
        fields: point.x,point.y
        frame: map
        child_frame: base_link
        best_effort: true

A driven twin's topics (several sensors and a control; docs/guides/ros2.md) are nested parameters, as ROS 2
writes them (``sensors.gps.topic`` is the same as the nested form)::

    dtpf_unicycle_1:
      ros__parameters:
        sensors:
          gps: {topic: /gps, fields: "point.x,point.y"}
          beacons: {topic: /beacons, type: geometry_msgs/msg/Vector3Stamped}
        control: {topic: /odom, fields: "twist.twist.linear.x,twist.twist.angular.z"}

each with ``topic``, ``type`` and ``fields`` (:data:`TOPIC_PARAMETERS`; :func:`topics_of` gives them).

Each parameter means what its option means on the command line (:data:`PARAMETERS`); an option given on the
command line wins over the file. Entries of other nodes are left alone (one file may configure a whole
stack); a parameter the bridge does not know, a value of the wrong type, or a file with no entry for the
bridge's node is one line naming it (:class:`~dtpf.scripts.ros2.Ros2Error`, exit 2).

    from dtpf.scripts.ros2 import params
    values = params.load("bridge.yaml", "dtpf_rb_ros")   # {"topic": "/target", "fields": ..., ...}
"""
from __future__ import annotations

import fnmatch
from pathlib import Path

from dtpf.scripts.ros2 import Ros2Error

__all__ = ["PARAMETERS", "TOPIC_PARAMETERS", "load", "node_name", "topics_of"]

#: Parameter -> (the option's argparse destination, its type, the option).
PARAMETERS: dict[str, tuple[str, type, str]] = {
    "topic": ("topic", str, "--topic (dtpf ros2) or --observations ros2:TOPIC"),
    "type": ("ros2_type", str, "--ros2-type"),
    "fields": ("ros2_fields", str, "--ros2-fields"),
    "pose": ("ros2_pose", str, "--ros2-pose"),
    "namespace": ("ros2_namespace", str, "--ros2-namespace"),
    "frame": ("ros2_frame", str, "--ros2-frame"),
    "child_frame": ("ros2_child_frame", str, "--ros2-child-frame"),
    "depth": ("ros2_depth", int, "--ros2-depth"),
    "covariance": ("ros2_covariance", str, "--ros2-covariance"),
    "best_effort": ("ros2_best_effort", bool, "--ros2-best-effort"),
}
#: A driven twin's topic parameters, ``sensors.NAME.KEY`` and ``control.KEY``: KEY -> its option.
TOPIC_PARAMETERS = {"topic": "NAME=ros2:TOPIC (--observations) or ros2:TOPIC (--controls)",
                    "type": "--ros2-type NAME=TYPE or --ros2-control-type", "fields": "--ros2-fields NAME=PATHS "
                    "or --ros2-control-fields"}
#: The closed choices of a parameter.
CHOICES = {"covariance": ("full", "diagonal")}


def node_name(twin: str) -> str:
    """The bridge's ROS 2 node name for ``twin``: dtpf_<twin>, '-' and '.' as '_'."""
    return "dtpf_" + "".join(c if c.isalnum() or c == "_" else "_" for c in twin)


def _matches(key: str, node: str) -> bool:
    """Whether a top-level key of a parameters file names ``node``: '/**' or '**', the node's name with or
    without a namespace, or a pattern with '*' of its last part."""
    text = str(key).strip()
    if text.strip("/") == "**":
        return True
    last = text.rstrip("/").rsplit("/", 1)[-1]
    return fnmatch.fnmatchcase(node, last)


def load(path, node: str) -> dict[str, object]:
    """The parameters of ``node`` in the ROS 2 parameters file ``path`` (the entries that name it merged in
    file order, later ones winning, as ROS 2 does), checked against :data:`PARAMETERS`; Ros2Error in one
    line."""
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise Ros2Error(f"--ros2-params {name}: cannot read it ({error.strerror or error})") from None
    try:
        from ruamel.yaml import YAML
        from ruamel.yaml.error import YAMLError
    except ImportError:
        raise Ros2Error("--ros2-params needs ruamel.yaml: pip install 'dtpf[ros2]'") from None
    try:
        document = YAML(typ="safe", pure=True).load(text)
    except YAMLError as error:
        where = getattr(error, "problem_mark", None)
        at = f" at line {where.line + 1}" if where is not None else ""
        raise Ros2Error(f"--ros2-params {name}: not YAML{at} ({getattr(error, 'problem', None) or error})") from None
    if not isinstance(document, dict):
        raise Ros2Error(f"--ros2-params {name}: expected node names at the top ('{node}:' or '/**:', each with "
                        f"'ros__parameters:'), not {type(document).__name__}")
    found: dict[str, object] = {}
    named = False
    for key, entry in document.items():
        if not _matches(key, node):
            continue
        named = True
        values = entry.get("ros__parameters") if isinstance(entry, dict) else None
        if not isinstance(values, dict):
            raise Ros2Error(f"--ros2-params {name}: '{key}' has no 'ros__parameters:' mapping")
        for parameter, value in _flat(values).items():
            found[parameter] = _checked(name, parameter, value)
    if not named:
        nodes = ", ".join(str(k) for k in document) or "none"
        raise Ros2Error(f"--ros2-params {name}: no entry for the bridge's node {node} (the file has: {nodes}); "
                        f"name it '{node}:' or '/**:'")
    return found


def _flat(values: dict, prefix: str = "") -> dict[str, object]:
    """Nested parameters as ROS 2 names them: {'sensors': {'gps': {'topic': ...}}} -> {'sensors.gps.topic': ...}."""
    out: dict[str, object] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and name.split(".")[0] in ("sensors", "control"):
            out.update(_flat(value, name + "."))
        else:
            out[name] = value
    return out


def topics_of(values: dict[str, object]) -> tuple[dict[str, dict[str, str]], dict[str, str]]:
    """The sensors' (name -> {topic, type, fields}) and the control's ({topic, type, fields}) parameters of
    :func:`load`'s answer."""
    sensors: dict[str, dict[str, str]] = {}
    control: dict[str, str] = {}
    for parameter, value in values.items():
        parts = parameter.split(".")
        if parts[0] == "sensors":
            sensors.setdefault(parts[1], {})[parts[2]] = value
        elif parts[0] == "control":
            control[parts[1]] = value
    return sensors, control


def _checked_topic(name: str, parameter: str, value) -> object:
    """A ``sensors.NAME.KEY`` or ``control.KEY`` parameter, checked."""
    import re

    parts = parameter.split(".")
    shape = (len(parts) == 3 and parts[0] == "sensors" and re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]{0,63}", parts[1])
             or len(parts) == 2 and parts[0] == "control")
    if not shape or parts[-1] not in TOPIC_PARAMETERS:
        raise Ros2Error(f"--ros2-params {name}: unknown parameter {parameter!r} (a driven twin's topics are "
                        f"sensors.NAME.KEY and control.KEY, KEY one of {', '.join(TOPIC_PARAMETERS)})")
    if not isinstance(value, str) or not value.strip():
        raise Ros2Error(f"--ros2-params {name}: {parameter} must be a non-empty string (as "
                        f"{TOPIC_PARAMETERS[parts[-1]]}), not {value!r}")
    return value


def _checked(name: str, parameter: str, value) -> object:
    if parameter.split(".")[0] in ("sensors", "control"):
        return _checked_topic(name, parameter, value)
    if parameter not in PARAMETERS:
        raise Ros2Error(f"--ros2-params {name}: unknown parameter {parameter!r} (known: {', '.join(PARAMETERS)})")
    _, kind, option = PARAMETERS[parameter]
    if kind is bool:
        ok = isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, str) and value.strip() != ""
    if not ok:
        what = {bool: "true or false", int: "an integer", str: "a non-empty string"}[kind]
        raise Ros2Error(f"--ros2-params {name}: {parameter} must be {what} (as {option}), not {value!r}")
    if parameter in CHOICES and value not in CHOICES[parameter]:
        raise Ros2Error(f"--ros2-params {name}: {parameter} must be one of {', '.join(CHOICES[parameter])}, "
                        f"not {value!r}")
    if kind is int and value < 1:
        raise Ros2Error(f"--ros2-params {name}: {parameter} must be at least 1, not {value}")
    return value
