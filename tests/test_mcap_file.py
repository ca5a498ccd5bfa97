"""The MCAP writer (dtpf.recording.mcap_file) and the recorder's files written with it (dtpf.recording.writer).

Files are read back with the ``mcap`` package's readers (the indexed reader and the streaming
reader, CRCs checked) and with the product's own reader, whole and cut short.
"""
from __future__ import annotations

import errno
import io
import os
import random
import struct
import zlib

import lz4.frame
import pytest
import zstandard
from mcap.reader import make_reader
from mcap.records import (Channel, Chunk, ChunkIndex, DataEnd, Footer, Message, MessageIndex, Schema, Statistics,
                          SummaryOffset)
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from dtpf.messages.codec import MessageError, encode, schema_for
from dtpf.messages.models import Estimate
from dtpf.recording.logfile import read_log, write_log
from dtpf.recording.mcap_file import MAGIC, McapWriter
from dtpf.recording.writer import LogWriteError, McapRecording

COMPRESSIONS = ["none", "lz4", "zstd"]
MCAP_COMPRESSION = {"none": CompressionType.NONE, "lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD}


def _operations(seed: int = 1) -> list[tuple]:
    """What a recording does, in order: schemas and channels registered along the way (one without a
    schema, one with metadata), messages of 0 bytes to 100 kB, and a few flushes."""
    rng = random.Random(seed)
    ops = [("schema", "dtpf.A", "jsonschema", b'{"type": "object"}'),
           ("channel", "dtpf/t/a", "json", 1, {}),
           ("channel", "dtpf/t/raw", "application/octet-stream", 0, {"origin": "test", "\u00e9": "\u00fc"})]
    sizes = [0, 1, 3, 17, 200, 1500, 9000, 100_000]
    channels = 2
    for i in range(400):
        if i == 120:
            ops += [("schema", "dtpf.B", "protobuf", bytes(range(256))), ("channel", "dtpf/t/b", "protobuf", 2, {})]
            channels += 1
        if i == 300:
            ops.append(("channel", "dtpf/t/late", "json", 1, {}))
            channels += 1
        size = sizes[i % len(sizes)] if i < 40 else rng.choice(sizes[:7])
        data = rng.randbytes(size) if i % 2 else (b"{\"step\": %d}" % i * (size // 12 + 1))[:size]
        log_time = 1_700_000_000_000_000_000 + i * 1000 + rng.randrange(500)
        ops.append(("message", 1 + rng.randrange(channels), log_time, data, log_time - 7, i))
        if i % 97 == 96:
            ops.append(("flush",))
    return ops


def _play(writer, ops) -> list[tuple]:
    """Do ``ops`` on an McapWriter or an mcap Writer; returns the messages written as (channel id, log time,
    publish time, sequence, data)."""
    written = []
    writer.start(profile="", library="dtpf")
    for op in ops:
        if op[0] == "schema":
            writer.register_schema(name=op[1], encoding=op[2], data=op[3])
        elif op[0] == "channel":
            writer.register_channel(topic=op[1], message_encoding=op[2], schema_id=op[3], metadata=op[4])
        elif op[0] == "message":
            _, channel, log_time, data, publish_time, sequence = op
            writer.add_message(channel, log_time=log_time, data=data, publish_time=publish_time, sequence=sequence)
            written.append((channel, log_time, publish_time, sequence, data))
        else:
            writer.flush()
    writer.finish()
    return written


def _write(path, compression: str, chunk_size: int = 8 << 10, ops=None) -> list[tuple]:
    with open(path, "wb") as file:
        return _play(McapWriter(file, chunk_size=chunk_size, compression=compression), ops or _operations())


def _expected(ops, written) -> list[tuple]:
    """(topic, schema (name, encoding, data) or None, log time, publish time, sequence, data) of each message."""
    schemas = {i + 1: op[1:4] for i, op in enumerate(op for op in ops if op[0] == "schema")}
    channels = {i + 1: op for i, op in enumerate(op for op in ops if op[0] == "channel")}
    return [(channels[c][1], schemas.get(channels[c][3]), t, p, s, d) for c, t, p, s, d in written]


def _as_read(schema, channel, message) -> tuple:
    return (channel.topic, (schema.name, schema.encoding, schema.data) if schema else None, message.log_time,
            message.publish_time, message.sequence, message.data)


def _decompress(chunk: Chunk) -> bytes:
    if chunk.compression == "lz4":
        return lz4.frame.decompress(chunk.data)
    if chunk.compression == "zstd":
        return zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    assert chunk.compression == ""
    return chunk.data


def _records_with_offsets(data: bytes):
    """(offset, record) of every record of a whole file, in order, with mcap's StreamReader."""
    stream = io.BytesIO(data)
    reader = StreamReader(stream, emit_chunks=True, validate_crcs=True)
    out, offset = [], len(MAGIC)
    for record in reader.records:
        out.append((offset, record))
        offset = stream.tell()
    return out


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_a_file_reads_back_through_mcaps_indexed_and_streaming_readers(tmp_path, compression):
    ops = _operations()
    path = tmp_path / "file.mcap"
    written = _write(path, compression)
    expected = _expected(ops, written)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        got = [_as_read(s, c, m) for s, c, m in reader.iter_messages(log_time_order=False)]
        summary = reader.get_summary()
    assert got == expected
    stats = summary.statistics
    assert stats.message_count == len(written)
    assert stats.schema_count == 2 and stats.channel_count == 4
    counts = {}
    for channel, *_ in written:
        counts[channel] = counts.get(channel, 0) + 1
    assert stats.channel_message_counts == counts
    assert stats.message_start_time == min(m[1] for m in written)
    assert stats.message_end_time == max(m[1] for m in written)
    assert {s.id: (s.name, s.encoding, s.data) for s in summary.schemas.values()} == {
        1: ("dtpf.A", "jsonschema", b'{"type": "object"}'), 2: ("dtpf.B", "protobuf", bytes(range(256)))}
    assert summary.channels[2].metadata == {"origin": "test", "\u00e9": "\u00fc"}
    assert summary.channels[2].schema_id == 0

    # The streaming reader, chunks broken up with their CRCs checked: the same messages, each after the
    # Schema and Channel records it needs.
    with open(path, "rb") as f:
        schemas, channels, streamed = {}, {}, []
        for record in StreamReader(f, validate_crcs=True).records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                assert record.schema_id == 0 or record.schema_id in schemas
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels[record.channel_id]
                streamed.append(_as_read(schemas.get(channel.schema_id), channel, record))
    assert streamed == expected

    # Chunk indexes and message indexes point at what they describe.
    data = path.read_bytes()
    records = _records_with_offsets(data)
    chunks = [(offset, record) for offset, record in records if isinstance(record, Chunk)]
    assert len(chunks) == stats.chunk_count == len(summary.chunk_indexes) > 10
    assert all(chunk.compression == ("" if compression == "none" else compression) for _, chunk in chunks)
    after = {offset: [] for offset, _ in chunks}
    current = None
    for offset, record in records:
        if isinstance(record, Chunk):
            current = offset
        elif isinstance(record, MessageIndex):
            after[current].append((offset, record))
    total = 0
    for (offset, chunk), index in zip(chunks, summary.chunk_indexes):
        assert index.chunk_start_offset == offset
        (opcode, length) = struct.unpack_from("<BQ", data, offset)
        assert opcode == 0x06 and index.chunk_length == 9 + length
        assert index.compression == chunk.compression and index.compressed_size == len(chunk.data)
        plain = _decompress(chunk)
        assert index.uncompressed_size == chunk.uncompressed_size == len(plain)
        assert chunk.uncompressed_crc == zlib.crc32(plain)
        times = []
        message_indexes = after[offset]
        assert message_indexes and message_indexes[0][0] == offset + index.chunk_length
        assert index.message_index_offsets == {record.channel_id: at for at, record in message_indexes}
        last_offset, last = message_indexes[-1]
        assert index.message_index_length == last_offset + 9 + 6 + 16 * len(last.records) - message_indexes[0][0]
        for _, message_index in message_indexes:
            for log_time, at in message_index.records:
                opcode, length, channel_id, _, record_time = struct.unpack_from("<BQHIQ", plain, at)
                assert (opcode, channel_id, record_time) == (0x05, message_index.channel_id, log_time)
                times.append(log_time)
                total += 1
        assert (index.message_start_time, index.message_end_time) == (min(times), max(times))
        assert (chunk.message_start_time, chunk.message_end_time) == (min(times), max(times))
    assert total == len(written)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_the_summary_its_offsets_and_its_crc_are_right(tmp_path, compression):
    path = tmp_path / "file.mcap"
    _write(path, compression)
    data = path.read_bytes()
    assert data.startswith(MAGIC) and data.endswith(MAGIC)
    records = _records_with_offsets(data)
    footer_offset, footer = records[-1]
    assert isinstance(footer, Footer)
    (data_end_offset, data_end), = [(o, r) for o, r in records if isinstance(r, DataEnd)]
    assert footer.summary_start == data_end_offset + 9 + 4
    crc_end = footer_offset + 1 + 8 + 8 + 8
    assert footer.summary_crc == zlib.crc32(data[footer.summary_start:crc_end])
    summary = [(o, r) for o, r in records if footer.summary_start <= o < footer_offset]
    offsets = [r for o, r in summary if isinstance(r, SummaryOffset)]
    assert [o for o, r in summary if isinstance(r, SummaryOffset)][0] == footer.summary_offset_start
    assert [r.group_opcode for r in offsets] == [0x03, 0x04, 0x0B, 0x08]
    kinds = {0x03: Schema, 0x04: Channel, 0x0B: Statistics, 0x08: ChunkIndex}
    for group in offsets:
        inside = [r for o, r in summary if group.group_start <= o < group.group_start + group.group_length]
        assert inside and all(type(r) is kinds[group.group_opcode] for r in inside)
    assert sum(r.group_length for r in offsets) == footer.summary_offset_start - footer.summary_start
    assert sum(isinstance(r, ChunkIndex) for _, r in summary) == sum(isinstance(r, Chunk) for _, r in records)


def test_the_data_section_is_byte_for_byte_what_mcaps_writer_writes():
    # Same chunks (closed once their records exceed chunk_size), same records in them, same message indexes
    # (uncompressed chunks: the bytes a compressor makes are its own library's).
    compression = "none"
    ops = _operations(seed=2)
    ours, theirs = io.BytesIO(), io.BytesIO()
    _play(McapWriter(ours, chunk_size=5000, compression=compression), ops)
    _play(Writer(theirs, chunk_size=5000, compression=MCAP_COMPRESSION[compression]), ops)
    ends = []
    for data in (ours.getvalue(), theirs.getvalue()):
        summary_start, = struct.unpack_from("<Q", data, len(data) - len(MAGIC) - 20)
        ends.append(summary_start)
    assert ends[0] == ends[1]
    assert ours.getvalue()[:ends[0]] == theirs.getvalue()[:ends[1]]


def test_a_chunk_is_closed_once_its_records_exceed_chunk_size(tmp_path):
    path = tmp_path / "file.mcap"
    with open(path, "wb") as file:
        writer = McapWriter(file, chunk_size=1000, compression="none")
        writer.start()
        channel = writer.register_channel("t", "json", 0)
        for i in range(100):
            writer.add_message(channel, i, b"x" * (i % 7 * 50), i, i)
        writer.finish()
    with open(path, "rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    for chunk in chunks[:-1]:
        records, at = [], 0
        while at < len(chunk.data):
            length, = struct.unpack_from("<Q", chunk.data, at + 1)
            records.append(9 + length)
            at += 9 + length
        assert chunk.uncompressed_size > 1000 >= chunk.uncompressed_size - records[-1]
    assert chunks[-1].uncompressed_size <= 1000 + 31 + 300


def test_an_empty_recording_and_an_empty_flush(tmp_path):
    path = tmp_path / "empty.mcap"
    with open(path, "wb") as file:
        writer = McapWriter(file, chunk_size=1 << 20, compression="lz4")
        writer.start()
        size = file.tell()
        writer.register_schema("S", "jsonschema", b"{}")
        writer.register_channel("t", "json", 1)
        writer.flush()  # no message: no chunk
        assert file.tell() == size
        writer.finish()
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert list(reader.iter_messages()) == []
        summary = reader.get_summary()
    assert summary.statistics.message_count == 0 and summary.statistics.chunk_count == 0
    assert summary.channels[1].topic == "t" and summary.schemas[1].name == "S"
    log = read_log(path)
    assert log.complete and log.problem is None and log.channels[1].topic == "t"


def test_a_message_that_cannot_be_written_is_refused_and_leaves_no_trace():
    stream = io.BytesIO()
    writer = McapWriter(stream, chunk_size=1000, compression="none")
    writer.start()
    channel = writer.register_channel("t", "json", 0)
    with pytest.raises(ValueError, match="channel 2 was not registered"):
        writer.add_message(channel + 1, 1, b"x", 1, 0)
    with pytest.raises(ValueError, match="schema 1 was not registered"):
        writer.register_channel("u", "json", 1)
    with pytest.raises(struct.error):  # a sequence number past uint32
        writer.add_message(channel, 2, b"y", 2, 1 << 32)
    writer.add_message(channel, 1, b"x", 1, 0)
    writer.finish()
    stream.seek(0)
    reader = make_reader(stream, validate_crcs=True)
    assert [(m.log_time, m.data) for _, _, m in reader.iter_messages()] == [(1, b"x")]
    assert reader.get_summary().statistics.message_count == 1


def test_payloads_may_be_bytearrays_and_memoryviews(tmp_path):
    path = tmp_path / "views.mcap"
    buffer = bytes(range(256)) * 10
    payloads = [bytearray(b"abc"), memoryview(buffer)[100:1100], memoryview(b""), b"plain"]
    with open(path, "wb") as file:
        writer = McapWriter(file, chunk_size=600, compression="zstd")
        writer.start()
        channel = writer.register_channel("t", "application/octet-stream", 0)
        for i, payload in enumerate(payloads):
            writer.add_message(channel, i, payload, i, i)
        writer.finish()
    with open(path, "rb") as f:
        assert [m.data for _, _, m in make_reader(f).iter_messages()] == [bytes(p) for p in payloads]


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_the_products_reader_reads_it(tmp_path, compression):
    ops = _operations()
    path = tmp_path / "file.mcap"
    written = _write(path, compression)
    log = read_log(path)
    assert log.complete and log.problem is None
    assert log.header.library == "dtpf"
    assert [(m.topic, m.log_time, m.publish_time, m.sequence, m.data) for m in log.messages] == [
        (topic, t, p, s, d) for topic, _, t, p, s, d in _expected(ops, written)]
    assert log.statistics.message_count == len(written)
    assert sorted(c.topic for c in log.channels.values()) == ["dtpf/t/a", "dtpf/t/b", "dtpf/t/late", "dtpf/t/raw"]


def _chunk_bounds(data: bytes) -> list[tuple[int, int, int]]:
    """(start, end, messages) of each chunk of a file that may lack its summary; end is after its indexes."""
    stream = io.BytesIO(data)
    bounds, offset = [], len(MAGIC)
    try:
        for record in StreamReader(stream, emit_chunks=True).records:
            end = stream.tell()
            if isinstance(record, Chunk):
                count = 0
                plain, at = _decompress(record), 0
                while at < len(plain):
                    opcode, length = struct.unpack_from("<BQ", plain, at)
                    count += opcode == 0x05
                    at += 9 + length
                bounds.append([offset, end, count])
            elif isinstance(record, MessageIndex):
                bounds[-1][1] = end
            offset = end
    except Exception:  # the end of a file without a summary
        pass
    return [tuple(b) for b in bounds]


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_a_file_cut_short_keeps_every_message_of_its_complete_chunks(tmp_path, compression):
    # A recorder killed after some flushes: the file holds the chunks flushed so far, no summary; then cut
    # anywhere, as a full disk or a crash leaves it. What `dtpf recover` does: read_log, then write_log.
    path = tmp_path / "killed.mcap"
    ops = [op for op in _operations(seed=3) if op[0] != "flush"]
    file = open(path, "wb")
    writer = McapWriter(file, chunk_size=6000, compression=compression)
    written = []
    writer.start()
    for i, op in enumerate(ops):
        if op[0] == "schema":
            writer.register_schema(*op[1:])
        elif op[0] == "channel":
            writer.register_channel(*op[1:])
        else:
            writer.add_message(op[1], op[2], op[3], op[4], op[5])
            written.append(op)
        if i == 300:
            writer.flush()
            break
    data = path.read_bytes()
    file.close()
    expected = [(t, p, s, d) for _, _, t, d, p, s in written]
    chunks = _chunk_bounds(data)
    assert len(chunks) > 5 and sum(count for _, _, count in chunks) == len(written)
    rng = random.Random(4)
    cuts = {len(data)} | {end for _, end, _ in chunks} | {(start + end) // 2 for start, end, _ in chunks}
    cuts |= {rng.randrange(len(MAGIC), len(data)) for _ in range(10)}
    for cut in sorted(cuts):
        damaged = tmp_path / "cut.mcap"
        damaged.write_bytes(data[:cut])
        log = read_log(damaged)
        assert not log.complete and log.problem
        got = [(m.log_time, m.publish_time, m.sequence, m.data) for m in log.messages]
        assert got == expected[:len(got)], cut
        assert len(got) >= sum(count for _, end, count in chunks if end <= cut), cut
        out = tmp_path / "recovered.mcap"
        write_log(log, out)
        again = read_log(out)
        assert again.complete and again.problem is None
        assert [(m.log_time, m.publish_time, m.sequence, m.data) for m in again.messages] == got


# --- the recorder's files --------------------------------------------------------------------------------------

def _estimate(step: int) -> bytes:
    return encode(Estimate(run_id="r", twin_id="t", step=step, mean=[0.5 * step], var=[1.0], lower=[-2.0],
                           upper=[2.0], ess=10.0, ess_ratio=0.5, resampled=step % 2 == 0, degraded=False))


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_a_recording_reads_back_equal(tmp_path, compression):
    path = tmp_path / "run.mcap"
    rng = random.Random(5)
    sent = []
    with McapRecording(path, compression=compression, chunk_size=16 << 10, flush_interval=1e9) as recording:
        for step in range(1, 120):
            if step % 50 == 0:
                recording.flush()
            for key, payload in (("dtpf/t/entity/estimate", _estimate(step)),
                                 ("dtpf/t/entity/unknown", rng.randbytes(rng.choice([0, 10, 3000, 40_000])))):
                recording.write(key, payload, 1_700_000_000_000_000_000 + len(sent))
                sent.append((key, payload))
        mutable = bytearray(b"before")
        recording.write("dtpf/t/entity/unknown", mutable, 1_800_000_000_000_000_000)
        mutable[:] = b"after!"  # before its chunk is written: the recording copied it
        sent.append(("dtpf/t/entity/unknown", b"before"))
    assert recording.messages == len(sent)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        got = [(c.topic, m.data, m.sequence, s.name if s else None) for s, c, m in reader.iter_messages()]
        summary = reader.get_summary()
    sequences = {"dtpf/t/entity/estimate": 0, "dtpf/t/entity/unknown": 0}
    expected = []
    for key, payload in sent:
        expected.append((key, payload, sequences[key], schema_for(Estimate).name if key.endswith("estimate") else None))
        sequences[key] += 1
    assert got == expected
    assert summary.statistics.message_count == len(sent) and summary.statistics.chunk_count > 3
    log = read_log(path)
    assert log.complete and log.problem is None
    decoded = [(item.topic, message) for item, message in log.decoded()]
    estimates = [message for topic, message in decoded if topic.endswith("estimate")]
    assert [e.step for e in estimates] == list(range(1, 120))
    assert not any(isinstance(e, MessageError) for e in estimates)


# --- a stream that cannot be written -----------------------------------------------------------------------------

class _Full(io.RawIOBase):
    """A stream that takes ``room`` bytes, then fails every write with ENOSPC."""

    def __init__(self, room: int):
        self.room = room

    def writable(self) -> bool:
        return True

    def write(self, data) -> int:
        if len(data) > self.room:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return len(data)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_a_full_stream_raises_its_oserror(compression):
    writer = McapWriter(_Full(40), chunk_size=1000, compression=compression)
    writer.start()
    channel = writer.register_channel("t", "json", 0)
    writer.add_message(channel, 1, b"x" * 10, 1, 0)  # in the open chunk: nothing written yet
    with pytest.raises(OSError) as raised:
        writer.flush()
    assert type(raised.value) is OSError and raised.value.errno == errno.ENOSPC
    writer = McapWriter(_Full(40), chunk_size=1000, compression=compression)
    writer.start()
    channel = writer.register_channel("t", "json", 0)
    with pytest.raises(OSError) as raised:
        writer.add_message(channel, 1, os.urandom(2000), 1, 0)  # closes the chunk
    assert type(raised.value) is OSError and raised.value.errno == errno.ENOSPC


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_a_recording_on_a_full_disk_is_a_log_write_error():
    recording = McapRecording("/dev/full", compression="lz4", chunk_size=4096, flush_interval=1e9)
    with pytest.raises(LogWriteError) as raised:
        for _ in range(100):
            recording.write("dtpf/t/entity/unknown", os.urandom(1000))
    assert raised.value.cause.errno == errno.ENOSPC and raised.value.disk_full
    recording.close()  # ended: closing again is quiet
