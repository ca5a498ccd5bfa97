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
topic is one step; the message's ``header.stamp`` becomes the step's time, as on a live topic
(the bag's receive time for a message without a header or with a zero stamp): the table's
``stamps`` in integer nanoseconds, the stamps of the run's estimates to the nanosecond, and its
``times`` the same in seconds. Every problem is
one line (:class:`~dtpf.entity.observations.ObservationError`): a bag without the topic, a
field path the message type does not have, a NaN, a bag that cannot be read to its end.

A bag is read whole or refused: the messages read are checked against the counts of its MCAP summary,
the messages its message indexes list (place and log time) and a folder's metadata.yaml. A bag with fewer
messages than it declares, other messages than its index lists, or a chunk that does not decode is refused
in one line naming how many can be read, how many it declares and which are missing (steps and log times);
``partial=True`` reads the messages the index finds intact and says in the table's ``problem`` what it
skipped (a bag whose summary or index cannot be read: its records in file order, each chunk up to its first
damaged record, as a cut bag's). A bag cut short (no summary) is read up to the cut, as before. Without
CRCs (rosbags writes none), a flipped bit inside a message's data cannot be seen.
"""
from __future__ import annotations

import math
import os
import re
import struct
import zlib
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
    "stamp_ns",
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


def stamp_ns(message) -> int | None:
    """The message's ``header.stamp`` as integer nanoseconds since the epoch (a nanosec of 1e9 or more
    carried into the seconds, as rclpy's Time reads it), or None when it has no header or a stamp of zero or
    before the epoch (a driver that leaves it unset): the caller then takes the receive time."""
    stamp = stamp_of(message)
    if stamp is None or stamp[0] < 0 or stamp == (0, 0):
        return None
    return stamp[0] * 1_000_000_000 + stamp[1]


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
             state_dim: int | None = None, steps: int | None = None, model=None,
             partial: bool = False) -> ObservationTable:
    """The observations of ``topic`` in the rosbag2 log ``path``: one step per message, in the bag's
    order; stamps are the messages' header stamps in integer nanoseconds (:func:`stamp_ns`; the receive time
    without one), made non-decreasing, and times the same in seconds. ObservationError for anything wrong.

    A bag whose MCAP file was cut short (a recording that did not end: no summary or footer) is read up to
    the cut, with the message types of ROS 2 Kilted and those its schemas define; the table's ``problem``
    says so and how many messages were read.

    A bag is read whole or refused: the messages read are checked against what the bag declares (its MCAP
    summary's message counts and message indexes, a folder's metadata.yaml). Fewer messages than declared,
    messages other than the indexed ones, or a chunk that does not decode is an ObservationError naming how
    many were read, how many declared and where the gap is, unless ``partial``: then the messages the index
    finds intact are read and the table's ``problem`` says what was skipped.
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
    failure = None  # what stopped rosbags, for a bag that is not cut short
    counted = None  # the topic's message count that rosbags gives (a folder's metadata.yaml)
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
            counts = [getattr(c, "msgcount", None) for c in connections]
            counted = sum(counts) if counts and all(isinstance(n, int) and n > 0 for n in counts) else None
            try:
                for connection, timestamp, raw in reader.messages(connections=connections):
                    if not taker.wants_more():
                        break
                    taker.take(timestamp, lambda: reader.deserialize(raw, connection.msgtype))
            except ObservationError as error:  # a message that does not fit: the bag's fault or damage?
                failure = error
    except ObservationError:
        raise
    except Exception as error:  # a cut or corrupt bag: rosbags' own errors
        text = " ".join(str(error).split())
        cut = _cut_mcap(p) if taker.read == 0 else None
        if cut is None:
            failure = f"{type(error).__name__}: {text}"
        else:
            problem = _read_cut_bag(cut, name, source, topic, taker)
    if problem is None:
        problem = _whole_or_refused(p, name, source, topic, taker, failure, counted, partial)
    if not rows:
        raise ObservationError(f"{name}: no message on {topic!r}" + (f" ({problem})" if problem else ""),
                               source=source)
    width = len(rows[0])
    if any(len(r) != width for r in rows):
        row = next(i for i, r in enumerate(rows) if len(r) != width)
        raise ObservationError(f"{name} message {row + 1} on {topic}: {len(rows[row])} values, the first had "
                               f"{width}", source=source, row=row)
    columns = tuple(f"z{j}" for j in range(width)) if fields_spec is None else _column_names(fields_spec, width)
    stamps = np.maximum.accumulate(np.asarray(taker.stamps, dtype=np.int64))
    return ObservationTable(observations=np.asarray(rows, dtype=np.float64), truth=None, times=stamps / 1e9,
                            stamps=stamps, columns=columns, truth_columns=(), source=source, problem=problem)


class _Taker:
    """Messages of a bag's topic to rows of observations: mapped, checked, counted."""

    def __init__(self, name, source, topic, mapper, obs_dim, steps, rows, times):
        self.name, self.source, self.topic, self.mapper = name, source, topic, mapper
        self.obs_dim, self.steps, self.rows, self.times = obs_dim, steps, rows, times
        self.read = 0
        self.last: int | None = None  # the log time of the message taken last
        #: Each row's time in integer ns: its message's header stamp, else its log time (:func:`stamp_ns`).
        self.stamps: list[int] = []

    def wants_more(self) -> bool:
        return self.steps is None or len(self.rows) < self.steps

    def take(self, timestamp: int, deserialize) -> None:
        name, topic, source = self.name, self.topic, self.source
        self.read += 1
        self.last = timestamp
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
        stamp = stamp_ns(message)
        self.stamps.append(timestamp if stamp is None else stamp)


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


# --- a bag read whole or refused: what it declares, what its index finds intact ---------------------

_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<BQQQQI")   # opcode, length, start time, end time, uncompressed size, crc


@dataclass(frozen=True)
class _Entry:
    """One message of the topic as a message index lists it."""

    log_time: int
    file: Path
    chunk: int   # the chunk record's byte offset in the file
    offset: int  # the message record's offset in the chunk's records
    channel: int


class _Index:
    """What a bag's MCAP files declare about a topic: the message counts of their summaries (``stated``),
    and the messages their message indexes list (``entries``, in log-time order; None when an index cannot
    be read, ``unusable`` says why)."""

    def __init__(self, path: Path, topic: str):
        self.stated: int | None = 0
        self.entries: list[_Entry] | None = []
        self.unusable: str | None = None
        self.chunks: dict[tuple[Path, int], object] = {}
        self.msgtypes: dict[tuple[Path, int], tuple[str, str, str]] = {}  # (file, channel): name, encoding, text
        files = [path] if path.is_file() else sorted(path.glob("*.mcap"))
        if not files:
            self.stated, self.entries, self.unusable = None, None, "no MCAP file"
        for file in files:
            try:
                self._read(file, topic)
            except Exception as error:  # a summary or index that does not parse: the index cannot locate
                self.stated, self.entries = None, None
                self.unusable = f"{file.name}: its summary or message index is unreadable ({_say(error)})"
            if self.entries is None:
                break
        if self.entries is not None:
            self.entries.sort(key=lambda e: e.log_time)
            if self.stated is not None and len(self.entries) != self.stated:
                self.unusable = (f"its message indexes list {len(self.entries)} messages of the {self.stated} "
                                 f"its statistics count")
                self.entries = None

    def _read(self, file: Path, topic: str) -> None:
        from mcap.reader import make_reader

        with open(file, "rb") as stream:
            summary = make_reader(stream).get_summary()
            if summary is None:
                raise ValueError("no summary")
            ids = {cid for cid, channel in summary.channels.items() if channel.topic == topic}
            for cid in ids:
                channel = summary.channels[cid]
                schema = summary.schemas.get(channel.schema_id)
                self.msgtypes[(file, cid)] = (schema.name if schema else "", channel.message_encoding,
                                              schema.data.decode("utf-8", "replace") if schema else "")
            if summary.statistics is None:
                self.stated = None
            elif self.stated is not None:
                self.stated += sum(summary.statistics.channel_message_counts.get(cid, 0) for cid in ids)
            for chunk in summary.chunk_indexes:
                self.chunks[(file, chunk.chunk_start_offset)] = chunk
                for cid, at in chunk.message_index_offsets.items():
                    if cid not in ids:
                        continue
                    stream.seek(at)
                    head = stream.read(15)
                    opcode, length, channel, size = struct.unpack("<BQHI", head) if len(head) == 15 else (0,) * 4
                    if opcode != 0x07 or channel != cid or size % 16 or size + 6 != length:
                        raise ValueError(f"the message index at byte {at:,} is damaged")
                    body = stream.read(size)
                    if len(body) != size:
                        raise ValueError(f"the message index at byte {at:,} is cut")
                    for log_time, offset in struct.iter_unpack("<QQ", body):
                        if not chunk.message_start_time <= log_time <= chunk.message_end_time \
                                or offset >= chunk.uncompressed_size:
                            raise ValueError(f"the message index at byte {at:,} is damaged")
                        self.entries.append(_Entry(log_time, file, chunk.chunk_start_offset, offset, cid))

    def records(self, file: Path, at: int) -> bytes:
        """The decompressed records of the chunk at byte ``at``; ValueError saying why not."""
        from dtpf.recording.logfile import _decompress

        chunk = self.chunks[(file, at)]
        with open(file, "rb") as stream:
            stream.seek(at)
            raw = stream.read(chunk.chunk_length)
        if len(raw) != chunk.chunk_length or len(raw) < _CHUNK_HEAD.size + 4:
            raise ValueError(f"the chunk at byte {at:,} is cut")
        opcode, length, _, _, size, crc = _CHUNK_HEAD.unpack_from(raw)
        if opcode != 0x06 or length + 9 != chunk.chunk_length:
            raise ValueError(f"the chunk at byte {at:,} has a damaged header or is not where the index puts it")
        (name_length,) = struct.unpack_from("<I", raw, _CHUNK_HEAD.size)
        start = _CHUNK_HEAD.size + 4 + name_length
        compression = raw[_CHUNK_HEAD.size + 4:start].decode("utf-8", "replace")
        (data_length,) = struct.unpack_from("<Q", raw, start) if len(raw) >= start + 8 else (len(raw),)
        if compression != chunk.compression or start + 8 + data_length > len(raw):
            raise ValueError(f"the chunk at byte {at:,} has a damaged header")
        try:
            data = _decompress(compression, raw[start + 8:start + 8 + data_length], size)
        except Exception as error:
            raise ValueError(f"the chunk at byte {at:,} does not decompress ({compression}: {_say(error)})") from None
        if len(data) != size:
            raise ValueError(f"the chunk at byte {at:,} decompresses to {len(data):,} bytes, not {size:,}")
        if crc and zlib.crc32(data) != crc:
            raise ValueError(f"the chunk at byte {at:,} fails its CRC")
        return data

    def intact(self):
        """(position, entry, raw message) of each indexed message whose record is where its index says,
        and (position, entry, why) of the others; positions count from 0 in log-time order."""
        good, bad, chunks = [], [], {}
        for position, entry in enumerate(self.entries):
            key = (entry.file, entry.chunk)
            if key not in chunks:
                try:
                    chunks[key] = self.records(*key)
                except ValueError as error:
                    chunks[key] = str(error)
                compression = self.chunks[key].compression
                if compression and not isinstance(chunks[key], str) and not _records_walk(chunks[key]):
                    # a damaged compressed chunk that still decompresses: the damage spreads through what it
                    # decompresses to (back-references), so none of its records is trusted
                    chunks[key] = f"the chunk at byte {entry.chunk:,} ({compression}) decompresses to damaged records"
            data = chunks[key]
            if isinstance(data, str):
                bad.append((position, entry, data))
                continue
            o = entry.offset
            if o + _MESSAGE_HEAD.size <= len(data):
                opcode, length, channel, _, log_time, _ = _MESSAGE_HEAD.unpack_from(data, o)
                if (opcode == 0x05 and 22 <= length and o + 9 + length <= len(data) and channel == entry.channel
                        and log_time == entry.log_time and _sound_after(data, o + 9 + length)):
                    good.append((position, entry, bytes(data[o + _MESSAGE_HEAD.size:o + 9 + length])))
                    continue
            bad.append((position, entry, f"their records in the chunk at byte {entry.chunk:,} are damaged"))
        return good, bad

    def deserializer(self, name: str, source: str):
        """deserialize(entry, raw) -> the message, with ROS 2 Kilted's types and those the schemas define."""
        from rosbags.typesys import Stores, get_typestore, get_types_from_msg

        typestore = get_typestore(Stores.ROS2_KILTED)
        for msgtype, encoding, text in set(self.msgtypes.values()):
            if encoding != "cdr":
                raise ObservationError(f"{name}: messages in {encoding!r}, not CDR", source=source)
            if msgtype not in typestore.fielddefs:
                try:
                    typestore.register(get_types_from_msg(text, msgtype))
                except Exception as error:
                    raise ObservationError(f"{name}: its type {msgtype}: {_say(error)}", source=source) from None
        return lambda entry, raw: typestore.deserialize_cdr(raw, self.msgtypes[(entry.file, entry.channel)][0])


def _records_walk(data: bytes) -> bool:
    """Whether ``data`` is a sequence of sound Schema, Channel and Message records to its last byte."""
    at = 0
    while at < len(data):
        if not _sound_after(data, at):
            return False
        at += 9 + struct.unpack_from("<Q", data, at + 1)[0]
    return at == len(data)


def _sound_after(data: bytes, at: int) -> bool:
    """Whether a sound record (or the chunk's end) follows a record that ends at ``at``: damage that starts
    inside a message's data and runs on shows in the record after it."""
    if at == len(data):
        return True
    if at + 9 > len(data) or data[at] not in (0x03, 0x04, 0x05):
        return False
    (length,) = struct.unpack_from("<Q", data, at + 1)
    return at + 9 + length <= len(data) and (data[at] != 0x05 or length >= 22)


def _say(error: Exception) -> str:
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _gaps(bad, entries, declared: int) -> str:
    """'messages 605-672 (log times 1030.200-1033.550 s; chunk ... does not decompress)', runs joined."""
    runs = []
    for position, entry, why in bad:
        if runs and runs[-1][1] == position - 1 and runs[-1][2] == why:
            runs[-1][1] = position
        else:
            runs.append([position, position, why])
    parts = []
    for first, last, why in runs[:3]:
        span = f"message {first + 1}" if first == last else f"messages {first + 1}-{last + 1}"
        times = f"{entries[first].log_time / 1e9:.3f}" + (
            "" if first == last else f"-{entries[last].log_time / 1e9:.3f}")
        parts.append(f"{span} (log time{'' if first == last else 's'} {times} s; {why})")
    if len(runs) > 3:
        parts.append(f"{len(runs) - 3} more gaps")
    return ", ".join(parts) + f" of the {declared}"


def _metadata_count(path: Path, topic: str) -> int | None:
    """The topic's message count in a bag folder's metadata.yaml (None: no folder, file or count)."""
    if not path.is_dir():
        return None
    try:
        from ruamel.yaml import YAML

        info = YAML(typ="safe").load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        counts = [int(t["message_count"]) for t in info["topics_with_message_count"]
                  if t["topic_metadata"]["name"] == topic]
    except Exception:  # no metadata.yaml, or one that does not parse: it declares nothing
        return None
    return sum(counts) if counts else None


def _whole_or_refused(path: Path, name: str, source: str, topic: str, taker: _Taker, failure, counted: int | None,
                      partial: bool) -> str | None:
    """Check what was read against what the bag declares: None when it agrees; else the ObservationError
    that names the gap, or (``partial``) the intact messages read into ``taker`` and what was skipped."""
    if counted is None:
        counted = _metadata_count(path, topic)
    index = _Index(path, topic) if (path.is_file() or any(path.glob("*.mcap"))) else None
    entries = None if index is None else index.entries
    declared = [n for n in (counted, None if index is None else index.stated,
                            None if entries is None else len(entries)) if n is not None]
    declared = max(declared) if declared else None
    times, read = taker.times, len(taker.rows)
    whole = taker.wants_more() and failure is None  # read to the end (not stopped at ``steps``)
    out_of_place = None
    if entries is not None:
        seen = times + ([taker.last] if isinstance(failure, ObservationError) and taker.last is not None else [])
        out_of_place = next((i for i, t in enumerate(seen) if i >= len(entries) or t != entries[i].log_time), None)
    if isinstance(failure, ObservationError) and out_of_place is None:
        raise failure  # the message is where the bag says and does not fit the model: the bag is sound
    if isinstance(failure, str):
        what = f"rosbags stopped after {read} messages ({failure})"
    elif failure is not None:
        what = str(failure)
    elif whole or out_of_place is not None:
        what = f"{read} were read" + ("" if out_of_place is None else
                                      f", from message {out_of_place + 1} on not the ones its index lists")
    else:
        what = None  # the first ``steps`` read agree with the index
    if entries is None:  # nothing to place a gap by: the counts alone
        if failure is None and (declared is None or read == declared or not whole and read < declared):
            return None
        where = ""
        if len(times) > 1:
            k = int(np.argmax(np.diff(np.asarray(times, dtype=np.int64))))
            where = (f"; the widest gap in the log times read is after message {k + 1} ({times[k] / 1e9:.3f} s), "
                     f"before message {k + 2} ({times[k + 1] / 1e9:.3f} s)")
        why = index.unusable if index is not None else "it has no MCAP file to index its messages"
        files = [path] if path.is_file() else sorted(path.glob("*.mcap"))
        if partial and len(files) == 1:  # what its records hold, in file order, each at its own log time
            taker.rows.clear()
            taker.times.clear()
            taker.stamps.clear()
            taker.read = 0
            try:
                _read_cut_bag(files[0], name, source, topic, taker)
            except ObservationError:
                taker.rows.clear()
            if taker.rows:
                of = f"the {declared}" if declared is not None else "an unknown number"
                return (f"{name}: {why}; read the {len(taker.rows)} messages on {topic} its records hold, in file "
                        f"order (--partial), of {of} it declares; where others were cannot be told")
        count = declared if declared is not None else "an unknown number of"
        raise ObservationError(f"{name}: the bag declares {count} messages on {topic}, {what}; {why}, so what is "
                               f"intact cannot be told{where}",
                               source=source)
    good = bad = None
    if failure is None and out_of_place is None and declared == len(entries):
        if whole and read == declared:
            return None  # every message the bag declares, each where its index says
        if not whole:  # the first ``steps`` agree with the index: are the others where it says?
            good, bad = index.intact()
            if not bad:
                return None
    if good is None:
        good, bad = index.intact()
    deserialize = index.deserializer(name, source)
    messages = []
    for position, entry, raw in good:
        try:
            messages.append((position, entry, deserialize(entry, raw)))
        except Exception as error:  # a payload damaged beyond decoding
            bad.append((position, entry, f"cannot deserialise it: {_say(error)}"))
    spoilt = {(entry.file, entry.chunk) for _, entry, _ in bad if index.chunks[(entry.file, entry.chunk)].compression}
    if spoilt:  # a compressed chunk with one damaged message: the damage spreads through the rest of it
        keep = []
        for position, entry, message in messages:
            if (entry.file, entry.chunk) in spoilt:
                bad.append((position, entry, f"the chunk at byte {entry.chunk:,} "
                                                         f"({index.chunks[(entry.file, entry.chunk)].compression}) "
                                                         f"decompresses to damaged records"))
            else:
                keep.append((position, entry, message))
        messages = keep
    bad.sort(key=lambda item: item[0])
    intact = len(messages)
    gaps = _gaps(bad, entries, declared) if bad else f"none of the {len(entries)} its index lists"
    if declared > len(entries):
        gaps += (f", and {declared - len(entries)} that its metadata.yaml declares and no MCAP index lists")
    if intact == declared:  # every message of the topic is where its index says: read them so
        partial, gaps = True, None
    elif not partial:
        raise ObservationError(f"{name}: the bag declares {declared} messages on {topic}, {intact} can be read: "
                               f"missing {gaps}{f' ({what})' if what else ''}; --partial reads the {intact} intact "
                               f"ones", source=source)
    taker.rows.clear()
    taker.times.clear()
    taker.stamps.clear()
    taker.read = 0
    for _, entry, message in messages:
        if not taker.wants_more():
            break
        taker.take(entry.log_time, lambda: message)
    if gaps is None:
        return (f"{name}: the bag is damaged{f' ({what})' if what else ''}, but each of the {declared} messages on "
                f"{topic} is intact where its index puts it; read them so")
    return f"{name}: read {intact} of the {declared} messages on {topic} the bag declares (--partial); skipped {gaps}"


def _column_names(spec: str, width: int) -> tuple[str, ...]:
    names = [text.strip() for text in spec.split(",")]
    return tuple(names) if len(names) == width else tuple(f"z{j}" for j in range(width))
