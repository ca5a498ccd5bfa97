"""ROS 2 messages as observations: field paths, and rosbag2 logs read as an observation file.

A ROS 2 message becomes one observation vector by **field paths**, comma-separated, each
a chain of field names with an optional index or slice per name (Python's, half-open)::

    range                 sensor_msgs/msg/Range -> [range]
    point.x,point.y       geometry_msgs/msg/PointStamped -> [x, y]
    ranges[0:8]           sensor_msgs/msg/LaserScan -> its first 8 ranges
    pose.pose.position.x,pose.pose.position.y

A path that ends on an array gives all its values, in order. Or the model file gives a
method ``observation_from_ros2(message)`` that returns the values; it is used when no
field paths are given. The same paths serve a live topic (``dtpf.scripts.ros2``, on
rclpy's message objects) and a rosbag2 log (here, on the messages ``rosbags`` decodes)::

    from dtpf.entity import rosbag
    paths = rosbag.parse_fields("point.x,point.y")
    rosbag.values_of(message, paths)         # [x, y], floats; FieldPathError when one is missing
    table = rosbag.read_bag("run_bag", "/target", "point.x,point.y", obs_dim=2, state_dim=4)

A rosbag2 log is a folder with ``metadata.yaml`` or its ``.mcap`` file (MCAP storage, CDR
messages), read with ``rosbags`` (the ``[ros2]`` or ``[rosbag]`` extra). One message of the
topic is one step; the bag's receive time becomes the step's time (the table's ``times`` in
seconds, its ``stamps`` in nanoseconds: the stamps of the run's estimates). Every problem is
one line (:class:`~dtpf.entity.observations.ObservationError`): a bag without the topic, a
field path the message type does not have, a NaN, a bag that cannot be read to its end.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path

import numpy as np

from dtpf.entity.observations import ObservationError, ObservationTable

__all__ = [
    "MODEL_HOOK",
    "ROSBAG_INSTALL",
    "FieldPath",
    "FieldPathError",
    "check_fields",
    "is_bag",
    "need_rosbags",
    "parse_fields",
    "read_bag",
    "stamp_of",
    "type_name",
    "values_of",
]

#: What to install for rosbag2 files.
ROSBAG_INSTALL = "pip install 'dtpf[rosbag]' (rosbags, pure Python) or 'dtpf[ros2]'"
#: The model method that maps a ROS 2 message to an observation when no field paths are given.
MODEL_HOOK = "observation_from_ros2"

_SEGMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(?:\[(-?\d+)\]|\[(-?\d*):(-?\d*)\])?$")


class FieldPathError(ObservationError):
    """A field path that does not parse, or that a message does not have; one line."""


@dataclass(frozen=True)
class FieldPath:
    """One field path: its text and its steps (name, index or slice or None)."""

    text: str
    steps: tuple[tuple[str, int | slice | None], ...]


def parse_fields(spec: str) -> list[FieldPath]:
    """The field paths of ``spec`` ('range', 'point.x,point.y', 'ranges[0:8]'); FieldPathError if one
    does not parse."""
    if spec is None or not str(spec).strip():
        raise FieldPathError("--ros2-fields: no field path given (e.g. 'range', 'point.x,point.y', 'ranges[0:8]')")
    paths = []
    for text in str(spec).split(","):
        text = text.strip()
        steps = []
        for segment in text.split("."):
            match = _SEGMENT.match(segment.strip())
            if match is None:
                raise FieldPathError(f"--ros2-fields: {text!r} is not a field path (names joined by '.', each "
                                     f"with an optional [i] or [a:b], e.g. 'point.x' or 'ranges[0:8]')")
            name, index, start, stop = match.groups()
            if index is not None:
                selector = int(index)
            elif start is not None or stop is not None:
                selector = slice(int(start) if start else None, int(stop) if stop else None)
            else:
                selector = None
            steps.append((name, selector))
        paths.append(FieldPath(text, tuple(steps)))
    return paths


def type_name(message) -> str:
    """'pkg/msg/Name' of an rclpy or rosbags message (its class name otherwise)."""
    name = getattr(message, "__msgtype__", None)
    if isinstance(name, str):
        return name
    cls = type(message)
    module = cls.__module__.split(".")
    if len(module) >= 2 and module[1] == "msg":
        return f"{module[0]}/msg/{cls.__name__}"
    return cls.__name__


def _field_names(message) -> list[str] | None:
    """The field names of a message object (None if it is not one)."""
    get = getattr(type(message), "get_fields_and_field_types", None)
    if get is not None:  # rclpy
        return list(get())
    if is_dataclass(message):  # rosbags
        return [f.name for f in fields(message) if not f.name.startswith("__")]
    return None


def _is_message(value) -> bool:
    return _field_names(value) is not None


def _numbers(value, path: FieldPath, msgtype: str) -> list[float]:
    if isinstance(value, (bool, int, float, np.number, np.bool_)):
        return [float(value)]
    if _is_message(value):
        raise FieldPathError(f"--ros2-fields: {path.text!r} of {msgtype} is a {type_name(value)}, not a number; "
                             f"name one of its fields ({', '.join(_field_names(value))})")
    if isinstance(value, (str, bytes)):
        raise FieldPathError(f"--ros2-fields: {path.text!r} of {msgtype} is text, not a number")
    try:
        items = list(value)
    except TypeError:
        raise FieldPathError(f"--ros2-fields: {path.text!r} of {msgtype} is a {type(value).__name__}, "
                             f"not a number") from None
    out = []
    for item in items:
        out.extend(_numbers(item, path, msgtype))
    return out


def _walk(message, path: FieldPath, msgtype: str, *, check_only: bool = False):
    value = message
    for name, selector in path.steps:
        names = _field_names(value)
        if names is None:
            raise FieldPathError(f"--ros2-fields: {path.text!r}: {name!r} is below a value that has no fields "
                                 f"in {msgtype}")
        if name not in names:
            raise FieldPathError(f"--ros2-fields: {msgtype} has no field {path.text!r} ({name!r} is not one of "
                                 f"{', '.join(names)})")
        value = getattr(value, name)
        if selector is not None:
            if check_only and len(value) == 0:
                return None  # an unbounded array: its length is known per message only
            try:
                value = value[selector]
            except IndexError:
                raise FieldPathError(f"--ros2-fields: {path.text!r}: index {selector} is out of range "
                                     f"({len(value)} values)") from None
            except TypeError:
                raise FieldPathError(f"--ros2-fields: {path.text!r}: {name!r} is not an array") from None
    return value


def values_of(message, paths: list[FieldPath]) -> list[float]:
    """The observation vector of ``message`` by ``paths``; FieldPathError when a path does not fit."""
    msgtype = type_name(message)
    out = []
    for path in paths:
        out.extend(_numbers(_walk(message, path, msgtype), path, msgtype))
    return out


def check_fields(message, paths: list[FieldPath]) -> None:
    """Check ``paths`` against a (default) instance of the message type: every name exists; indices into
    arrays that are empty in the instance are left to each message."""
    msgtype = type_name(message)
    for path in paths:
        value = _walk(message, path, msgtype, check_only=True)
        if value is not None and not (isinstance(value, (list, tuple, np.ndarray)) or hasattr(value, "__len__")) or value is not None and _is_message(value):
            _numbers(value, path, msgtype)


def stamp_of(message) -> tuple[int, int] | None:
    """(sec, nanosec) of the message's ``header.stamp``, or None when it has no header."""
    header = getattr(message, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    sec, nsec = getattr(stamp, "sec", None), getattr(stamp, "nanosec", None)
    if not isinstance(sec, (int, np.integer)) or not isinstance(nsec, (int, np.integer)):
        return None
    return int(sec), int(nsec)


def is_bag(path) -> bool:
    """Whether ``path`` is a rosbag2 log: a folder with metadata.yaml, or an .mcap file."""
    p = Path(os.fsdecode(path))
    return (p.is_dir() and (p / "metadata.yaml").is_file()) or p.suffix.lower() == ".mcap"


def need_rosbags():
    """The rosbags package, or an ObservationError saying what to install."""
    try:
        import rosbags.highlevel
        import rosbags.typesys
    except ImportError:
        raise ObservationError(f"reading a rosbag2 log needs the rosbags package: {ROSBAG_INSTALL}") from None
    return rosbags


def _mapper(fields_spec: str | None, model, name: str):
    if fields_spec:
        paths = parse_fields(fields_spec)
        return (lambda message: values_of(message, paths)), paths
    hook = getattr(model, MODEL_HOOK, None)
    if hook is None:
        raise ObservationError(f"{name}: say how a message becomes an observation: --ros2-fields (e.g. 'range', "
                               f"'point.x,point.y', 'ranges[0:8]'), or a method {MODEL_HOOK}(message) in the model")

    def mapped(message):
        values = hook(message)
        try:
            return [float(v) for v in np.asarray(values, dtype=np.float64).reshape(-1)]
        except (TypeError, ValueError) as error:
            raise FieldPathError(f"{MODEL_HOOK} returned {type(values).__name__}, not numbers: {error}") from None
    return mapped, None


def read_bag(path, topic: str | None, fields_spec: str | None, *, obs_dim: int | None = None,
             state_dim: int | None = None, steps: int | None = None, model=None) -> ObservationTable:
    """The observations of ``topic`` in the rosbag2 log ``path``: one step per message, in the bag's
    order; times are the bag's receive times in seconds, stamps the same in nanoseconds (made non-decreasing
    both). ObservationError for anything wrong.

    A bag whose MCAP file was cut short (a recording that did not end: no summary or footer) is read up to
    the cut, with the message types of ROS 2 Kilted and those its schemas define; the table's ``problem``
    says so and how many messages were read.
    """
    source = os.fsdecode(path)
    name = source
    p = Path(source)
    if not p.exists():
        raise ObservationError(f"{name}: no such file or folder", source=source)
    if topic is None:
        raise ObservationError(f"{name}: a rosbag2 log: name the topic to filter with --topic", source=source)
    need_rosbags()
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    mapper, _ = _mapper(fields_spec, model, name)
    rows, times = [], []
    taker = _Taker(name, source, topic, mapper, obs_dim, steps, rows, times)
    problem = None
    try:
        with AnyReader([p], default_typestore=get_typestore(Stores.ROS2_KILTED)) as reader:
            connections = [c for c in reader.connections if c.topic == topic]
            if not connections:
                found = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
                raise ObservationError(f"{name}: no topic {topic!r} in the bag (it has: "
                                       f"{', '.join(found) or 'no topics'})", source=source)
            types = sorted({c.msgtype for c in connections})
            if len(types) > 1:
                raise ObservationError(f"{name}: topic {topic!r} has messages of {len(types)} types "
                                       f"({', '.join(types)})", source=source)
            for connection, timestamp, raw in reader.messages(connections=connections):
                if not taker.wants_more():
                    break
                taker.take(timestamp, lambda: reader.deserialize(raw, connection.msgtype))
    except ObservationError:
        raise
    except Exception as error:  # a cut or corrupt bag: rosbags' own errors
        text = " ".join(str(error).split())
        cut = _cut_mcap(p) if taker.read == 0 else None
        if cut is None:
            raise ObservationError(f"{name}: cannot read the bag after {taker.read} messages of {topic}: "
                                   f"{type(error).__name__}: {text}", source=source) from None
        problem = _read_cut_bag(cut, name, source, topic, taker)
    if not rows:
        raise ObservationError(f"{name}: no message on {topic!r}" + (f" ({problem})" if problem else ""),
                               source=source)
    width = len(rows[0])
    if any(len(r) != width for r in rows):
        row = next(i for i, r in enumerate(rows) if len(r) != width)
        raise ObservationError(f"{name} message {row + 1} on {topic}: {len(rows[row])} values, the first had "
                               f"{width}", source=source, row=row)
    columns = tuple(f"z{j}" for j in range(width)) if fields_spec is None else _column_names(fields_spec, width)
    stamps = np.maximum.accumulate(np.asarray(times, dtype=np.int64))
    return ObservationTable(observations=np.asarray(rows, dtype=np.float64), truth=None, times=stamps / 1e9,
                            stamps=stamps, columns=columns, truth_columns=(), source=source, problem=problem)


class _Taker:
    """Messages of a bag's topic to rows of observations: mapped, checked, counted."""

    def __init__(self, name, source, topic, mapper, obs_dim, steps, rows, times):
        self.name, self.source, self.topic, self.mapper = name, source, topic, mapper
        self.obs_dim, self.steps, self.rows, self.times = obs_dim, steps, rows, times
        self.read = 0

    def wants_more(self) -> bool:
        return self.steps is None or len(self.rows) < self.steps

    def take(self, timestamp: int, deserialize) -> None:
        name, topic, source = self.name, self.topic, self.source
        self.read += 1
        read = self.read
        message = deserialize()
        try:
            values = self.mapper(message)
        except FieldPathError as error:
            raise ObservationError(f"{name} message {read} on {topic}: {error}", source=source,
                                   row=read - 1) from None
        bad = [v for v in values if not math.isfinite(v)]
        if bad:
            raise ObservationError(f"{name} message {read} on {topic}: {bad[0]} (observations must be "
                                   f"finite)", source=source, row=read - 1)
        if self.obs_dim is not None and len(values) != self.obs_dim:
            count = f"{len(values)} value{'' if len(values) == 1 else 's'}"
            raise ObservationError(f"{name} message {read} on {topic}: {count}, the model observes "
                                   f"{self.obs_dim} per step", source=source, row=read - 1)
        self.rows.append(values)
        self.times.append(timestamp)


def _cut_mcap(path: Path) -> Path | None:
    """The bag's one MCAP file if it lacks its footer (a recording that did not end), else None."""
    files = [path] if path.is_file() else sorted(path.glob("*.mcap"))
    if len(files) != 1 or not files[0].is_file():
        return None
    with open(files[0], "rb") as file:
        size = file.seek(0, os.SEEK_END)
        if size < 8 + 8:
            return files[0] if size >= 8 else None
        file.seek(size - 8)
        return None if file.read(8) == b"\x89MCAP0\r\n" else files[0]


def _read_cut_bag(path: Path, name: str, source: str, topic: str, taker: _Taker) -> str:
    """Take the topic's messages of a cut MCAP bag up to the cut (dtpf's reader of damaged MCAP files);
    what is missing, in words. ObservationError when nothing of the file can be read as MCAP."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    from dtpf.recording.logfile import LogError, read_log

    try:
        log = read_log(path)
    except LogError as error:
        raise ObservationError(f"{name}: cannot read the bag: {error}", source=source) from None
    typestore = get_typestore(Stores.ROS2_KILTED)
    channels = {cid: channel for cid, channel in log.channels.items() if channel.topic == topic}
    if not channels:
        found = sorted({channel.topic for channel in log.channels.values()})
        raise ObservationError(f"{name}: no topic {topic!r} in what the cut bag holds (it has: "
                               f"{', '.join(found) or 'no topics'}; {log.problem})", source=source)
    msgtypes = {}
    for cid, channel in channels.items():
        schema = log.schemas.get(channel.schema_id)
        if schema is None or channel.message_encoding != "cdr":
            raise ObservationError(f"{name}: topic {topic!r} of the cut bag has no ROS 2 schema or is not CDR "
                                   f"({channel.message_encoding!r})", source=source)
        msgtypes[cid] = schema.name
        if schema.name not in typestore.fielddefs and schema.encoding == "ros2msg":
            try:
                typestore.register(get_types_from_msg(schema.data.decode("utf-8"), schema.name))
            except Exception as error:  # a schema rosbags cannot parse
                raise ObservationError(f"{name}: the cut bag's type {schema.name}: {error}", source=source) from None
    if len(set(msgtypes.values())) > 1:
        raise ObservationError(f"{name}: topic {topic!r} has messages of {len(set(msgtypes.values()))} types "
                               f"({', '.join(sorted(set(msgtypes.values())))})", source=source)
    for item in log.messages:
        if item.channel_id in channels:
            if not taker.wants_more():
                break
            try:
                taker.take(item.log_time, lambda: typestore.deserialize_cdr(item.data, msgtypes[item.channel_id]))
            except ObservationError:
                raise
            except Exception as error:  # a message rosbags cannot deserialise
                raise ObservationError(f"{name} message {taker.read} on {topic}: cannot deserialise it: "
                                       f"{type(error).__name__}: {error}", source=source) from None
    held = sum(1 for item in log.messages if item.channel_id in channels)
    return (f"{name} was cut short: read up to the cut, where {held} message{'' if held == 1 else 's'} of "
            f"{topic} end ({log.problem})")


def _column_names(spec: str, width: int) -> tuple[str, ...]:
    names = [text.strip() for text in spec.split(",")]
    return tuple(names) if len(names) == width else tuple(f"z{j}" for j in range(width))
