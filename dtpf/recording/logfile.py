"""Reading a dtpf MCAP log, complete or damaged, and writing it back as a valid file.

::

    from dtpf.recording.logfile import read_log, write_log, LogError
    log = read_log("runs/ungm-1.mcap")      # LogError if it is not an MCAP file at all
    log.complete, log.problem               # True, None for a finished recording
    for item, message in log.decoded():     # message is a Message or a MessageError
        ...
    write_log(log, "runs/ungm-1.fixed.mcap")  # a valid MCAP with everything that was read

How damaged files are read
--------------------------
Records are read in file order with ``mcap``'s :class:`~mcap.stream_reader.StreamReader`,
so everything before the damage is kept: a recorder killed mid-run leaves a
file without summary or footer whose last chunk may be cut. What the cut
chunk still holds is recovered too: an uncompressed chunk is parsed up to the
cut, an lz4 or zstd chunk is decompressed as far as its complete blocks go.
Every message whose record lies completely in the recoverable bytes is kept,
so the messages read are always a prefix, in file order, of those of the
intact file. Reading never goes past the file size seen when it started, so
a recording still being written reads as "cut short" at that size.

What is missing is said in words in :attr:`Log.problem`, for example::

    log cut short: records readable up to byte 120,000 of 130,000; no data end, summary or
    footer; 2,345 messages read, the last at step 57 of dtpf/ungm-1/entity/estimate;
    the file ends inside the chunk at byte 120,000, after 9,954 of its 60,000 bytes of records
    (lz4): 12 of its messages recovered

A chunk whose CRC does not match its content is dropped (and said so);
reading goes on with the next record. Anything that cannot be read as MCAP
records stops the reading there, with the byte offset in the problem. Only a
file that is not MCAP at all (empty, or not starting with the MCAP magic)
raises :class:`LogError`.
"""
from __future__ import annotations

import heapq
import io
import os
import struct
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable, Iterator

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    Metadata,
    Schema,
    Statistics,
)
from mcap.records import (
    Message as McapMessage,
)
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from dtpf.messages import keys
from dtpf.messages.codec import MessageError, class_for_schema, decode_for_key, message_encoding, schema_name
from dtpf.messages.errors import DtpfError
from dtpf.messages.models import Message
from dtpf.recording.crc import crc32, use_fast_crc

# mcap's readers and writer check and compute CRCs with it too (dtpf/recording/crc.py).
use_fast_crc()

__all__ = ["Log", "LogMessage", "LogError", "CutRecord", "read_log", "read_logs", "join_logs", "write_log", "MAGIC",
           "last_estimate_steps", "what_it_holds", "in_step_order", "MixedRunsError", "RunIdentity", "run_identity",
           "check_one_run"]

#: The eight bytes every MCAP file starts and ends with.
MAGIC = b"\x89MCAP0\r\n"
#: Chunk size and compression of the files :func:`write_log` writes (as the recorder).
CHUNK_SIZE = 1 << 20

#: How many messages from the end :attr:`Log.problem` looks through for the last filter step.
_LAST_STEP_LOOKBACK = 64
_RECORD_PREFIX = struct.Struct("<BQ")      # opcode, record length
_MESSAGE_HEAD = struct.Struct("<HIQQ")     # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQII")      # start time, end time, uncompressed size, crc, compression length


class LogError(DtpfError, ValueError):
    """A file that cannot be read as an MCAP log at all; the text names the file and why."""


@dataclass(frozen=True, slots=True)
class LogMessage:
    """One message record of the log, as stored (payload undecoded).

    ``log_time`` and ``publish_time`` are nanoseconds since the Unix epoch;
    ``topic`` is the key expression of its channel.
    """

    topic: str
    channel_id: int
    log_time: int
    publish_time: int
    sequence: int
    data: bytes


@dataclass(frozen=True)
class CutRecord:
    """The record the file ends inside of, when the file is cut short."""

    offset: int        #: byte offset of the record's opcode
    name: str          #: record kind, e.g. "CHUNK", "MESSAGE_INDEX"; "" when the file ends between records
    length: int | None  #: record length the record declares (None if the length itself is cut)
    available: int     #: bytes of the record present in the file (after opcode and length)
    compression: str | None = None  #: chunks only: "", "lz4" or "zstd"
    chunk_data_length: int | None = None  #: chunks only: length of the (compressed) records
    chunk_data_available: int = 0  #: chunks only: bytes of it present in the file
    recovered: int = 0  #: chunks only: messages recovered from it


@dataclass
class Log:
    """Everything read from one MCAP log.

    ``schemas`` and ``channels`` are ``mcap.records`` objects by their id in
    the file; ``messages`` are in file order. ``complete`` is True when the
    footer was read; ``problem`` says what is missing or damaged (None for a
    sound file).
    """

    path: Path
    size: int
    header: Header | None = None
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[LogMessage] = field(default_factory=list)
    attachments: list[Attachment] = field(default_factory=list)
    metadata: list[Metadata] = field(default_factory=list)
    statistics: Statistics | None = None
    complete: bool = False
    data_end: bool = False  #: the DataEnd record (end of the data section) was read
    read_to: int = 0        #: every record before this byte offset was read completely
    cut: CutRecord | None = None
    problems: list[str] = field(default_factory=list)
    #: The files this log was joined from (:func:`join_logs`); empty for one file.
    segments: list[Path] = field(default_factory=list)

    @property
    def problem(self) -> str | None:
        """What is missing or damaged, in words; None for a sound, complete file."""
        return "; ".join(self.problems) if self.problems else None

    def topics(self) -> list[str]:
        """Topics of the channels, in channel-id order."""
        return [self.channels[cid].topic for cid in sorted(self.channels)]

    def decoded(self, topics: Iterable[str] | Callable[[str], bool] | None = None
                ) -> Iterator[tuple[LogMessage, Message | MessageError]]:
        """Each message (or only those on ``topics``) with its decoded dtpf message, in file order.

        ``topics`` is a collection of topics or a predicate on the topic. The
        schema of the channel in the file decides the message class; it must
        agree with the topic table (:func:`dtpf.messages.codec.decode_for_key`
        checks the rest). A message that cannot be decoded comes with the
        :class:`~dtpf.messages.codec.MessageError` saying why; nothing is raised.
        """
        if topics is None:
            wanted = None
        elif callable(topics):
            wanted = topics
        else:
            chosen = set(topics)
            wanted = chosen.__contains__
        decoders: dict[int, Callable[[bytes], Message]] = {}
        for item in self.messages:
            if wanted is not None and not wanted(item.topic):
                continue
            decoder = decoders.get(item.channel_id)
            if decoder is None:
                decoder = decoders[item.channel_id] = self._decoder(item.channel_id)
            try:
                yield item, decoder(item.data)
            except MessageError as error:
                yield item, error

    def _decoder(self, channel_id: int) -> Callable[[bytes], Message]:
        channel = self.channels[channel_id]
        topic = channel.topic
        schema = self.schemas.get(channel.schema_id)

        def fail(reason: str) -> Callable[[bytes], Message]:
            def decoder(data: bytes) -> Message:
                raise MessageError(reason, key=topic)
            return decoder

        if channel.schema_id == 0 or schema is None:
            return fail(f"channel {channel_id} has no schema in the file "
                        f"(message encoding {channel.message_encoding!r})")
        cls = class_for_schema(schema.name)
        if cls is None:
            return fail(f"schema {schema.name!r} of channel {channel_id} is not a dtpf message")
        if message_encoding(cls) != channel.message_encoding:
            return fail(f"channel {channel_id} has message encoding {channel.message_encoding!r}, "
                        f"but its schema {schema.name} is encoded as {message_encoding(cls)!r}")
        try:
            table = keys.topic_of(topic).message
        except ValueError as error:
            return fail(str(error))
        if table is not cls:
            return fail(f"schema {schema.name} of the channel does not match the topic, "
                        f"which carries {schema_name(table)}")
        return lambda data: decode_for_key(topic, data)


# --- reading ---

class _Cut(Exception):
    """The file ends before the record being read does."""


class _Bounded:
    """A binary file that refuses to read past ``size``, so a short read is an error, never a short record."""

    def __init__(self, file, size: int):
        self._file = file
        self._size = size

    def read(self, n: int) -> bytes:
        if n > self._size - self._file.tell():
            raise _Cut()
        data = self._file.read(n)
        if len(data) < n:
            raise _Cut()
        return data

    def tell(self) -> int:
        return self._file.tell()


def read_log(path: str | os.PathLike) -> Log:
    """Read every record of an MCAP log that can be read, in file order.

    Raises
    ------
    LogError
        The file cannot be opened, is empty, or does not start with the MCAP
        magic. Any other damage is reported in :attr:`Log.problem`.
    """
    path = Path(path)
    try:
        file = open(path, "rb")
    except OSError as error:
        raise LogError(f"cannot read {path}: {error.strerror or error}") from None
    with file:
        size = os.fstat(file.fileno()).st_size
        head = file.read(len(MAGIC))
        if not head:
            raise LogError(f"{path} is empty (0 bytes): not an MCAP log")
        if head != MAGIC[:len(head)]:
            raise LogError(f"{path} is not an MCAP file: it starts with {head!r}, not the MCAP magic {MAGIC!r}")
        log = Log(path, size)
        if len(head) < len(MAGIC):
            log.problems.append(f"log cut short: the file ends at byte {size:,}, inside the MCAP magic; "
                                f"no header, messages, summary or footer")
            return log
        file.seek(0)
        _Reading(log, file).run()
    return log


class _Reading:
    """One pass over a file; fills a :class:`Log`."""

    def __init__(self, log: Log, file):
        self.log = log
        self.file = file
        self.unknown_channel = 0
        #: Messages read before their channel: (their place in the messages, the record).
        self.orphans: list[tuple[int, McapMessage]] = []
        self.stopped: str | None = None  # why reading stopped before the end, if it did

    def run(self) -> None:
        log = self.log
        stream = _Bounded(self.file, log.size)
        records = iter(StreamReader(stream, emit_chunks=True, record_size_limit=None).records)
        start = len(MAGIC)
        while True:
            try:
                record = next(records)
            except StopIteration:
                start = stream.tell()  # after the closing magic
                if start < log.size:
                    log.problems.append(f"{log.size - start:,} bytes after the closing magic were ignored")
                break
            except _Cut:
                self._cut_at(start)
                break
            except Exception as error:  # anything the records say that makes no sense
                self._unreadable_at(start, error)
                break
            end = stream.tell()
            self._take(record, start)
            start = end
        log.read_to = start
        self._finish()

    # - records -

    def _take(self, record, offset: int) -> None:
        log = self.log
        if isinstance(record, Chunk):
            self._chunk(record, offset)
        elif isinstance(record, (Schema, Channel, McapMessage)):
            self._inner(record)
        elif isinstance(record, Header):
            log.header = record
        elif isinstance(record, DataEnd):
            log.data_end = True
        elif isinstance(record, Footer):
            log.complete = True
        elif isinstance(record, Statistics):
            log.statistics = record
        elif isinstance(record, Attachment):
            log.attachments.append(record)
        elif isinstance(record, Metadata):
            log.metadata.append(record)
        # indexes and summary offsets: nothing to keep

    def _inner(self, record) -> None:
        """A Schema, Channel or Message record (top level or inside a chunk)."""
        log = self.log
        if isinstance(record, Schema):
            log.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            log.channels.setdefault(record.id, record)
        else:
            channel = log.channels.get(record.channel_id)
            if channel is None:
                # Its channel record may have been in a damaged chunk: the summary section repeats it.
                self.orphans.append((len(log.messages), record))
                return
            log.messages.append(LogMessage(channel.topic, record.channel_id, record.log_time,
                                           record.publish_time, record.sequence, record.data))

    def _chunk(self, chunk: Chunk, offset: int) -> None:
        where = f"chunk at byte {offset:,}"
        try:
            data = _decompress(chunk.compression, chunk.data, chunk.uncompressed_size)
        except Exception as error:
            self.log.problems.append(f"{where} cannot be decompressed ({chunk.compression}: {error}); "
                                     f"its records were dropped")
            return
        if chunk.uncompressed_crc != 0 and (computed := crc32(data)) != chunk.uncompressed_crc:
            self.log.problems.append(f"{where} failed its CRC check (expected {chunk.uncompressed_crc:#010x}, "
                                     f"computed {computed:#010x}); its records were dropped")
            return
        records, used, error = _chunk_records(data)
        for record in records:
            self._inner(record)
        if error is not None or used != len(data):
            self.log.problems.append(f"{where}: record at chunk offset {used:,} unreadable "
                                     f"({error or 'cut'}); the rest of the chunk was dropped")

    # - the end -

    def _cut_at(self, offset: int) -> None:
        """The file ends inside the record that starts at ``offset``: keep what it still holds."""
        log = self.log
        self.file.seek(offset)
        tail = self.file.read(log.size - offset)
        if len(tail) < _RECORD_PREFIX.size:
            log.cut = CutRecord(offset, _opcode_name(tail[0]) if tail else "", None, max(0, len(tail) - 1))
            return
        opcode, length = _RECORD_PREFIX.unpack_from(tail)
        body = tail[_RECORD_PREFIX.size:]
        cut = CutRecord(offset, _opcode_name(opcode), length, len(body))
        if opcode == Opcode.CHUNK and len(body) >= _CHUNK_HEAD.size:
            *_, compression_length = _CHUNK_HEAD.unpack_from(body)
            start = _CHUNK_HEAD.size + compression_length + 8
            if len(body) >= start:
                compression = body[_CHUNK_HEAD.size:start - 8].decode("utf-8", "replace")
                (data_length,) = struct.unpack_from("<Q", body, start - 8)
                data = body[start:start + data_length]
                recovered = self._partial_chunk(compression, data)
                cut = CutRecord(offset, cut.name, length, len(body), compression, data_length, len(data), recovered)
        log.cut = cut

    def _partial_chunk(self, compression: str, data: bytes) -> int:
        """Messages recovered from the start of a cut chunk."""
        try:
            if compression == "":
                plain = data
            elif compression == "lz4":
                plain = lz4.frame.LZ4FrameDecompressor().decompress(data)
            elif compression == "zstd":
                plain = zstandard.ZstdDecompressor().decompressobj().decompress(data)
            else:
                return 0
        except Exception:  # a frame header cut or damaged: nothing to recover
            return 0
        before = len(self.log.messages)
        records, _, _ = _chunk_records(plain)
        for record in records:
            self._inner(record)
        return len(self.log.messages) - before

    def _unreadable_at(self, offset: int, error: Exception) -> None:
        text = str(error) or type(error).__name__
        if self.log.complete:
            self.stopped = f"the closing magic after the footer is wrong ({text})"
        else:
            self.stopped = (f"unreadable record at byte {offset:,} ({text}); "
                            f"the last {self.log.size - offset:,} bytes were not read")

    def _adopt_orphans(self) -> None:
        """Put the messages whose channel was defined only later (in the summary) in their place."""
        if not self.orphans:
            return
        log = self.log
        merged, taken = [], 0
        for place, record in self.orphans:
            channel = log.channels.get(record.channel_id)
            if channel is None:
                self.unknown_channel += 1
                continue
            merged.extend(log.messages[taken:place])
            taken = place
            merged.append(LogMessage(channel.topic, record.channel_id, record.log_time,
                                     record.publish_time, record.sequence, record.data))
        merged.extend(log.messages[taken:])
        log.messages[:] = merged

    def _finish(self) -> None:
        log = self.log
        self._adopt_orphans()
        head = []
        if not log.complete:
            missing = "no footer" if log.data_end else "no data end, summary or footer"
            if log.cut is not None:
                head += [f"log cut short: records readable up to byte {log.read_to:,} of {log.size:,}", missing]
            else:
                head += [self.stopped or "the records end before the footer", missing]
            head.append(self._messages_read())
            if log.cut is not None:
                head.append(_describe_cut(log.cut, log.data_end))
        elif log.cut is not None:
            head.append(f"the file ends at byte {log.size:,} inside the closing magic")
        elif self.stopped:
            head.append(self.stopped)
        tail = []
        if self.unknown_channel:
            tail.append(f"{self.unknown_channel:,} messages on channels never defined in the file were dropped")
        stats = log.statistics
        if log.complete and stats is not None and stats.message_count != len(log.messages) and not log.problems:
            tail.append(f"the summary counts {stats.message_count:,} messages, {len(log.messages):,} were read")
        log.problems[:] = head + log.problems + tail

    def _messages_read(self) -> str:
        """'N messages read, the last at step k of TOPIC', naming the last message of a filter step."""
        messages = self.log.messages
        if not messages:
            return "no messages read"
        text = f"{len(messages):,} messages read"
        for back, item in enumerate(reversed(messages[-_LAST_STEP_LOOKBACK:])):
            try:
                step = decode_for_key(item.topic, item.data).step
            except MessageError:
                continue
            if step >= 1:
                after = f" (then {back} run-level message{'s' * (back != 1)})" if back else ""
                return f"{text}, the last at step {step} of {item.topic}{after}"
        return f"{text}, the last on {messages[-1].topic}"


def _describe_cut(cut: CutRecord, data_end: bool) -> str:
    if not cut.name:
        return f"the file ends between two records, at byte {cut.offset:,} (no record cut)"
    where = f"a {cut.name} record at byte {cut.offset:,}"
    if data_end:
        return f"the file ends inside the summary section ({where}): every message of the data section was read"
    if cut.name == "HEADER":
        return f"the file ends inside the header record at byte {cut.offset:,}"
    if cut.compression is None:
        if cut.name == "MESSAGE_INDEX":
            return f"the file ends inside {where} (an index: no message lost there)"
        return f"the file ends inside {where}"
    compression = cut.compression or "uncompressed"
    return (f"the file ends inside the chunk at byte {cut.offset:,}, after {cut.chunk_data_available:,} of its "
            f"{cut.chunk_data_length:,} bytes of records ({compression}): {cut.recovered:,} of its messages recovered")


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name
    except ValueError:
        return f"unknown (opcode {opcode:#04x})"


#: Piece by which a chunk is decompressed (nothing is allocated for what a chunk only claims).
_PIECE = 1 << 20
#: Most bytes a chunk may decompress to: its claimed size, and at most this many times its
#: compressed size (lz4 tops out near 255) or _MIN_EXPANSION_LIMIT, whichever is larger.
_MAX_RATIO, _MIN_EXPANSION_LIMIT = 256, 64 << 20


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    """The chunk's records, decompressed piece by piece up to the size the chunk claims.

    Neither the chunk's ``uncompressed_size`` nor a frame header's content size
    is believed before the bytes exist: a few-KB file claiming 8 GiB allocates
    what its data really expands to, and a decompression bomb stops at the
    limit (ValueError, the chunk is dropped).
    """
    if compression == "":
        return data
    limit = min(size, max(_MIN_EXPANSION_LIMIT, _MAX_RATIO * len(data)))
    if compression == "lz4":
        reader = lz4.frame.LZ4FrameDecompressor()
        pieces, total, pending = [], 0, data
        while not reader.eof:
            piece = reader.decompress(pending, max_length=_PIECE)
            pending = b""
            if not piece and reader.needs_input:
                break  # the frame is cut: what came out is checked against the CRC and size
            pieces.append(piece)
            total += len(piece)
            if total > limit:
                break
        out = b"".join(pieces)
    elif compression == "zstd":
        with zstandard.ZstdDecompressor().stream_reader(data) as reader:
            pieces, total = [], 0
            while piece := reader.read(_PIECE):
                pieces.append(piece)
                total += len(piece)
                if total > limit:
                    break
        out = b"".join(pieces)
    else:
        raise ValueError(f"unknown compression {compression!r}")
    if len(out) > limit:
        raise ValueError(f"decompresses to more than {limit:,} bytes (the chunk claims {size:,})")
    return out


def _chunk_records(data: bytes) -> tuple[list, int, Exception | None]:
    """The complete Schema, Channel and Message records at the start of ``data``.

    Returns the records, the number of bytes they span, and the error that
    stopped the walk (None when it stopped at the end or at a cut record).
    """
    view = memoryview(data)
    records, position = [], 0
    while position + _RECORD_PREFIX.size <= len(view):
        opcode, length = _RECORD_PREFIX.unpack_from(view, position)
        start = position + _RECORD_PREFIX.size
        end = start + length
        if end > len(view):
            break
        try:
            if opcode == Opcode.MESSAGE:
                channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(view, start)
                if length < _MESSAGE_HEAD.size:
                    raise ValueError(f"MESSAGE record of {length} bytes is shorter than its fixed fields")
                records.append(McapMessage(channel_id=channel_id, sequence=sequence, log_time=log_time,
                                           publish_time=publish_time,
                                           data=bytes(view[start + _MESSAGE_HEAD.size:end])))
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                stream = _Bounded(io.BytesIO(view[start:end]), length)
                reader = ReadDataStream(stream)
                records.append((Schema if opcode == Opcode.SCHEMA else Channel).read(reader))
        except Exception as error:
            return records, position, error
        position = end
    return records, position, None


# --- writing ---

def last_estimate_steps(log: Log) -> dict[str, int]:
    """The highest step of an estimate each twin has in ``log``, by twin (estimates that do not decode
    are left out)."""
    last: dict[str, int] = {}
    for item, message in log.decoded(lambda topic: topic.endswith("/entity/estimate")):
        if not isinstance(message, MessageError):
            last[message.twin_id] = max(last.get(message.twin_id, 0), message.step)
    return last


def in_step_order(messages: list) -> tuple[dict[int, object], dict[int, int]]:
    """One message per step from ``messages`` (a twin's messages of one topic, in file order): (chosen by
    step, how many competed for each step that had more than one).

    A layer publishes its steps in increasing order and Zenoh keeps one publisher's order, so the real
    messages form an increasing run of steps through the file; a forged one breaks it (an estimate of a
    future step sent early, a copy sent late). Where a step has several, the one on the longest strictly
    increasing run of steps is chosen (the earliest where two runs tie); a step with none on that run keeps
    its first. O(n log n).
    """
    import bisect

    tail_steps: list[int] = []   # the smallest last step of an increasing run of each length
    tail_index: list[int] = []
    before = [-1] * len(messages)
    for i, message in enumerate(messages):
        at = bisect.bisect_left(tail_steps, message.step)
        if at < len(tail_steps) and tail_steps[at] == message.step:
            continue  # an earlier message of this step already ends such a run
        before[i] = tail_index[at - 1] if at else -1
        if at == len(tail_steps):
            tail_steps.append(message.step)
            tail_index.append(i)
        else:
            tail_steps[at], tail_index[at] = message.step, i
    chosen: dict[int, object] = {}
    i = tail_index[-1] if tail_index else -1
    while i >= 0:
        chosen[messages[i].step] = messages[i]
        i = before[i]
    counts: dict[int, int] = {}
    for message in messages:
        counts[message.step] = counts.get(message.step, 0) + 1
        chosen.setdefault(message.step, message)
    return dict(sorted(chosen.items())), {step: n for step, n in counts.items() if n > 1}


def what_it_holds(path) -> str:
    """'it holds the run up to step S (M messages) ...': in words, what the log at ``path`` holds (for a log
    whose writing failed)."""
    try:
        log = read_log(path)
    except (LogError, OSError) as error:
        return f"nothing of it can be read ({error})"
    last = last_estimate_steps(log)
    if not last:
        held = f"it holds no estimate ({len(log.messages):,} messages)"
    elif len(last) == 1:
        held = f"it holds the run up to step {next(iter(last.values()))} ({len(log.messages):,} messages)"
    else:
        held = (f"it holds {len(last)} twins up to steps {min(last.values())}-{max(last.values())} "
                f"({len(log.messages):,} messages)")
    return held + (f"; 'dtpf recover {path} --output FILE' writes it as a complete file" if not log.complete else "")


def join_logs(logs: list[Log]) -> Log:
    """Several logs of one run as one: the segments of a restarted recorder (``run.mcap``, ``run.1.mcap``,
    ...) or the logs of recorders on several hosts.

    Messages are merged by the time they were received (``log_time``; each log's own order kept), so the
    logs may be named in any order. A message that is in more than one log (the same bytes on the same
    topic: two recorders heard it) is kept once. Each log's channel and schema ids are moved to a range of
    their own, so no two logs' ids collide. The joined log is complete when every log is, and its problems
    name the log they come from. For reading; :func:`write_log` writes one log at a time.
    """
    if len(logs) == 1:
        return logs[0]
    # In the order they were written, whatever order they were named in (a shell glob sorts run.mcap last).
    logs = sorted(logs, key=lambda log: log.messages[0].log_time if log.messages else float("inf"))
    joined = Log(path=logs[0].path, size=sum(log.size for log in logs), header=logs[0].header,
                 complete=all(log.complete for log in logs), data_end=all(log.data_end for log in logs),
                 segments=[log.path for log in logs])
    streams = []
    for index, log in enumerate(logs):
        offset = index << 16  # MCAP ids are 16 bits: each log gets a range of its own
        for sid, schema in log.schemas.items():
            joined.schemas[sid + offset] = replace(schema, id=sid + offset)
        for cid, channel in log.channels.items():
            joined.channels[cid + offset] = replace(
                channel, id=cid + offset, schema_id=channel.schema_id + offset if channel.schema_id else 0)
        streams.append([(m.log_time, index, replace(m, channel_id=m.channel_id + offset)) for m in log.messages])
        joined.attachments.extend(log.attachments)
        joined.metadata.extend(log.metadata)
        joined.problems.extend(f"{log.path}: {problem}" for problem in log.problems)
        joined.cut = log.cut or joined.cut
    seen: set[tuple[str, bytes]] = set()
    for _, _, message in heapq.merge(*streams, key=lambda entry: (entry[0], entry[1])):
        if (message.topic, message.data) not in seen:
            seen.add((message.topic, message.data))
            joined.messages.append(message)
    return joined


def read_logs(paths) -> Log:
    """:func:`read_log` of each path, joined (:func:`join_logs`); LogError names the file.

    Several files must be the files of one run (its segments, or the logs of its recorders on several
    hosts): :class:`MixedRunsError` (one line naming the files that differ and how) when they are not, as
    :func:`check_one_run` tells.
    """
    logs = [read_log(path) for path in paths]
    check_one_run(logs)
    return join_logs(logs)


class MixedRunsError(LogError):
    """Files of different runs given as the files of one run; the text names them and how they differ."""


@dataclass
class RunIdentity:
    """What says which run a log file is of (:func:`run_identity`): its run ids, and per (run id, twin) the
    run configuration and the entity processes its statuses carry."""

    run_ids: set[str] = field(default_factory=set)
    configs: dict[tuple[str, str], dict] = field(default_factory=dict)
    entities: dict[tuple[str, str], set[int]] = field(default_factory=dict)


#: Fields of the run configuration that differ between the twins of one run (a fleet).
_PER_TWIN = frozenset({"twin"})


def run_identity(log: Log) -> RunIdentity:
    """The run ids of ``log``'s statuses (of its estimates when it has no status), and per (run id, twin)
    the configuration (``config_json``) and the process ids of its entity's statuses."""
    import json

    from dtpf.messages.models import Layer, Status

    identity = RunIdentity()
    for _, message in log.decoded(lambda topic: topic.endswith("/status")):
        if not isinstance(message, Status):
            continue
        identity.run_ids.add(message.run_id)
        if message.layer != Layer.ENTITY:
            continue  # a shared service's configuration is not its twins'
        key = (message.run_id, message.twin_id)
        identity.entities.setdefault(key, set()).add(message.pid)
        if message.config_json and key not in identity.configs:
            try:
                identity.configs[key] = json.loads(message.config_json)
            except ValueError:
                pass
    if not identity.run_ids:
        for _, message in log.decoded(lambda topic: topic.endswith("/entity/estimate")):
            if not isinstance(message, MessageError):
                identity.run_ids.add(message.run_id)
    return identity


def _config_differences(a: dict, b: dict, shown: int = 4) -> list[str]:
    """'seed 3 vs 0' for each field in which configuration ``a`` differs from ``b`` (twin excepted)."""
    names = [name for name in sorted(set(a) | set(b)) if name not in _PER_TWIN and a.get(name) != b.get(name)]
    said = [f"{name.replace('_', ' ')} {a.get(name)} vs {b.get(name)}" for name in names[:shown]]
    return said + ([f"{len(names) - shown} more fields"] if len(names) > shown else [])


def _without_twin(config: dict) -> str:
    import json
    return json.dumps({k: v for k, v in config.items() if k not in _PER_TWIN}, sort_keys=True)


def _how_they_differ(mine: RunIdentity, theirs: RunIdentity) -> str | None:
    """How the file of ``mine`` is not of the run of ``theirs`` (None when nothing says so)."""
    if mine.run_ids and theirs.run_ids and not mine.run_ids & theirs.run_ids:
        return f"run id {', '.join(sorted(mine.run_ids))} vs {', '.join(sorted(theirs.run_ids))}"
    common = sorted(set(mine.configs) & set(theirs.configs))
    for key in common:
        differences = _config_differences(mine.configs[key], theirs.configs[key])
        if differences:
            return f"{', '.join(differences)} (twin {key[1]})"
    if not common and mine.configs and theirs.configs:
        # Different twins: of one run (a fleet) only when their configurations agree but for the twin.
        ours = {_without_twin(config): config for config in mine.configs.values()}
        other = {_without_twin(config): config for config in theirs.configs.values()}
        if not set(ours) & set(other):
            first, second = next(iter(ours.values())), next(iter(other.values()))
            return ", ".join(_config_differences(first, second)) or "other twins"
    for key in sorted(set(mine.entities) & set(theirs.entities)):
        if not mine.entities[key] & theirs.entities[key]:
            pids = [", ".join(map(str, sorted(side.entities[key]))) for side in (mine, theirs)]
            return f"twin {key[1]}'s entity is process {pids[0]} vs {pids[1]} (two runs of one configuration)"
    return None


def check_one_run(logs: list[Log]) -> None:
    """MixedRunsError unless ``logs`` are the files of one run.

    Every file must agree with the others on the run id (of its statuses or estimates), on the run
    configuration of each twin (its entity's ``config_json``: seed, steps, N, model, ...) and on the
    entity process of each twin (its pid: a launch never restarts its entity, so the files of two
    launches of one configuration differ there). A file that does not say (no status in a short segment)
    agrees. The segments of a run (``run.mcap``, ``run.1.mcap``, ...) and its recorders' logs on several
    hosts pass.
    """
    if len(logs) < 2:
        return
    identities = [run_identity(log) for log in logs]
    for i in range(1, len(logs)):
        for j in range(i):
            how = _how_they_differ(identities[i], identities[j])
            if how is not None:
                raise MixedRunsError(f"{logs[i].path} and {logs[j].path} are not of one run: {how}; give the "
                                     f"files of one run only (its segments NAME.mcap, NAME.1.mcap, ...)")


def write_log(log: Log, out_path: str | os.PathLike) -> int:
    """Write ``log`` as a new, finished MCAP file; returns the number of messages written.

    Same schemas, channels (with their metadata), messages in the same order
    with the same times and sequence numbers, attachments and metadata
    records; lz4 chunks of 1 MiB as the recorder writes. Ids are renumbered
    from 1 in the order of the original ids. The file is written next to
    ``out_path`` and renamed into place, so a failure leaves no half file.
    """
    out_path = Path(out_path)
    temporary = out_path.with_name(f".{out_path.name}.{os.getpid()}.tmp")
    try:
        with open(temporary, "wb") as file:
            writer = Writer(file, chunk_size=CHUNK_SIZE, compression=CompressionType.LZ4)
            header = log.header
            writer.start(profile=header.profile if header else "", library=header.library if header else "dtpf")
            schema_ids = {0: 0}
            for old in sorted(log.schemas):
                schema = log.schemas[old]
                schema_ids[old] = writer.register_schema(name=schema.name, encoding=schema.encoding,
                                                         data=schema.data)
            channel_ids = {}
            for old in sorted(log.channels):
                channel = log.channels[old]
                channel_ids[old] = writer.register_channel(
                    topic=channel.topic, message_encoding=channel.message_encoding,
                    schema_id=schema_ids.get(channel.schema_id, 0), metadata=dict(channel.metadata))
            for item in log.messages:
                writer.add_message(channel_ids[item.channel_id], log_time=item.log_time, data=item.data,
                                   publish_time=item.publish_time, sequence=item.sequence)
            for attachment in log.attachments:
                writer.add_attachment(create_time=attachment.create_time, log_time=attachment.log_time,
                                      name=attachment.name, media_type=attachment.media_type,
                                      data=attachment.data)
            for record in log.metadata:
                writer.add_metadata(record.name, dict(record.metadata))
            writer.finish()
        os.replace(temporary, out_path)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise LogError(f"cannot write {out_path}: {error.strerror or error}") from None
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return len(log.messages)
