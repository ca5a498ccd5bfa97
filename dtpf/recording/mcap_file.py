"""Writing MCAP files (https://mcap.dev/spec) at a few microseconds per message.

::

    with open("run.mcap", "wb") as file:
        writer = McapWriter(file, chunk_size=1 << 20, compression="lz4")
        writer.start()
        schema = writer.register_schema("Estimate", "jsonschema", schema_bytes)
        channel = writer.register_channel("dtpf/ungm-1/entity/estimate", "json", schema)
        writer.add_message(channel, log_time, payload, publish_time, sequence)
        writer.flush()      # the open chunk to the file (a reader of the file sees it)
        writer.finish()     # summary and footer; the stream is left open

The file it writes::

    magic, Header,
    Chunk, its Message Index records (one per channel in the chunk), Chunk, ...   (the data section)
    Data End,
    Schema..., Channel..., Statistics, Chunk Index...                              (the summary section)
    Summary Offset... (one per group of the summary), Footer, magic

Schema and Channel records go into the chunk that is open when they are
registered, before the messages that use them, so a reader going through the
file in order meets them first; the summary repeats them. A chunk is closed
once its records exceed ``chunk_size`` bytes (uncompressed), on :meth:`flush`
and on :meth:`finish`; a chunk without a message is never written (its Schema
and Channel records wait for the next one).

A message is kept by reference until its chunk is written: ``data`` must not
change after :meth:`add_message` (pass bytes). Chunk CRCs are computed
(:func:`dtpf.recording.crc.crc32`), the summary CRC too; the data section CRC
is 0 ("not computed"). Every OSError of the stream propagates as it is; the
writer is not usable after one.

Records: opcode (uint8), content length (uint64), content. Integers are
little-endian; a string is its UTF-8 length (uint32) and bytes; a map is its
byte length (uint32) and its entries.
"""
from __future__ import annotations

import io
import struct

import lz4.frame
import zstandard

from dtpf.recording.crc import crc32

__all__ = ["McapWriter", "MAGIC", "COMPRESSIONS"]

#: The eight bytes an MCAP file starts and ends with.
MAGIC = b"\x89MCAP0\r\n"

#: Compression names taken by :class:`McapWriter` -> the name written in each Chunk record.
COMPRESSIONS = {"none": "", "lz4": "lz4", "zstd": "zstd"}

HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07
CHUNK_INDEX, STATISTICS, DATA_END, SUMMARY_OFFSET = 0x08, 0x0B, 0x0F, 0x0E

#: Message (0x05): opcode, length, channel_id uint16, sequence uint32, log_time uint64, publish_time uint64,
#: then the data (the rest of the record).
_MESSAGE = struct.Struct("<BQHIQQ")
_MESSAGE_SIZE = _MESSAGE.size  # 31 bytes
_MESSAGE_FIXED = _MESSAGE_SIZE - 9  # 22 bytes of content before the data
_pack_message = _MESSAGE.pack

_PREFIX = struct.Struct("<BQ")  # opcode, content length
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_ENTRY = struct.Struct("<HQ")  # an entry of a map<uint16, uint64>


def _string(text: str) -> bytes:
    data = text.encode("utf-8")
    return _U32.pack(len(data)) + data


def _record(opcode: int, content: bytes) -> bytes:
    return _PREFIX.pack(opcode, len(content)) + content


def _id_map(pairs) -> bytes:
    """map<uint16, uint64>: byte length, then (key, value) entries."""
    entries = b"".join(_ENTRY.pack(key, value) for key, value in pairs)
    return _U32.pack(len(entries)) + entries


class McapWriter:
    """An MCAP file written to ``stream`` (a binary file object whose ``write`` takes all it is given).

    ``compression``: "lz4" (LZ4 frame), "zstd" or "none"; ``chunk_size``:
    uncompressed bytes of records above which a chunk is closed. File offsets
    count from the stream's position when :meth:`start` is called (0 for a
    stream that cannot tell).
    """

    def __init__(self, stream, *, chunk_size: int = 1 << 20, compression: str = "lz4"):
        if compression not in COMPRESSIONS:
            raise ValueError(f"unknown compression {compression!r}; expected one of {', '.join(COMPRESSIONS)}")
        self._stream = stream
        self._chunk_size = chunk_size
        self._compression = COMPRESSIONS[compression]
        if compression == "lz4":
            self._compress = lz4.frame.compress
        elif compression == "zstd":
            self._compress = zstandard.ZstdCompressor().compress
        else:
            self._compress = None
        self._position = 0                    # file offset of the next byte written
        self._schemas: list[bytes] = []       # Schema records, by id - 1
        self._channels: list[bytes] = []      # Channel records, in id order
        self._chunk_indexes: list[bytes] = []  # Chunk Index records
        self._message_counts: dict[int, int] = {}
        self._start_time = self._end_time = None
        # The open chunk: its records (headers and data, not joined), their size, and per channel a flat
        # list log_time, offset, log_time, offset, ... of its messages.
        self._records: list = []
        self._append = self._records.append
        self._size = 0
        self._index: dict[int, list[int]] = {}

    # - records of the data section -

    def start(self, profile: str = "", library: str = "dtpf") -> None:
        """Magic and Header (0x01): profile string, library string."""
        try:
            self._position = self._stream.tell()
        except (AttributeError, io.UnsupportedOperation):
            self._position = 0
        self._write(MAGIC + _record(HEADER, _string(profile) + _string(library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """A new schema; returns its id (1, 2, ...).

        Schema (0x03): id uint16, name string, encoding string, data (uint32 length and bytes).
        """
        schema_id = len(self._schemas) + 1
        if schema_id > 0xFFFF:
            raise ValueError("an MCAP file holds at most 65535 schemas")
        data = bytes(data)
        record = _record(SCHEMA, _U16.pack(schema_id) + _string(name) + _string(encoding)
                         + _U32.pack(len(data)) + data)
        self._schemas.append(record)
        self._add_record(record)
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str] | None = None) -> int:
        """A new channel; returns its id (1, 2, ...). ``schema_id`` 0: messages without a schema.

        Channel (0x04): id uint16, schema_id uint16, topic string, message_encoding string,
        metadata map<string, string>.
        """
        channel_id = len(self._channels) + 1
        if channel_id > 0xFFFF:
            raise ValueError("an MCAP file holds at most 65535 channels")
        if schema_id and not 0 < schema_id <= len(self._schemas):
            raise ValueError(f"schema {schema_id} was not registered")
        pairs = b"".join(_string(key) + _string(value) for key, value in (metadata or {}).items())
        record = _record(CHANNEL, _U16.pack(channel_id) + _U16.pack(schema_id) + _string(topic)
                         + _string(message_encoding) + _U32.pack(len(pairs)) + pairs)
        self._channels.append(record)
        self._message_counts[channel_id] = 0
        self._add_record(record)
        return channel_id

    @property
    def chunk_size(self) -> int:
        """Bytes of records above which a chunk is closed."""
        return self._chunk_size

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int) -> None:
        """One message on a registered channel, times in nanoseconds; a Message record (0x05) of the open chunk.

        ``data`` (bytes, or a bytearray or memoryview of bytes) is kept, not copied, until the chunk is
        written: it must not change meanwhile. A message larger than :attr:`chunk_size` closes its chunk
        before this returns, so it is not kept.
        """
        size = len(data)
        head = _pack_message(MESSAGE, _MESSAGE_FIXED + size, channel_id, sequence, log_time, publish_time)
        entries = self._index.get(channel_id)
        if entries is None:  # the channel's first message in this chunk
            if channel_id not in self._message_counts:
                raise ValueError(f"channel {channel_id} was not registered")
            entries = self._index[channel_id] = []
        offset = self._size
        entries += (log_time, offset)
        append = self._append
        append(head)
        append(data)
        offset += _MESSAGE_SIZE + size
        self._size = offset
        if offset > self._chunk_size:
            self._close_chunk()

    def flush(self) -> None:
        """Write the open chunk, if it holds a message, and its indexes; then flush the stream."""
        self._close_chunk()
        self._stream.flush()

    def _add_record(self, record: bytes) -> None:
        self._append(record)
        self._size += len(record)
        if self._size > self._chunk_size:
            self._close_chunk()

    def _write(self, data: bytes) -> None:
        self._stream.write(data)
        self._position += len(data)

    def _close_chunk(self) -> None:
        """Write the open chunk and its Message Index records, and keep its Chunk Index.

        Chunk (0x06): message_start_time, message_end_time, uncompressed_size uint64,
        uncompressed_crc uint32, compression string, records (uint64 length and bytes).
        Message Index (0x07): channel_id uint16, records (uint32 byte length, then log_time uint64,
        offset uint64 of each message of the channel; offsets into the uncompressed records).
        """
        index = self._index
        if not index:
            return
        if self._compress is None:  # the records as they are: no joined copy of them (a large set is written
            parts = self._records   # from where it lies)
            size = sum(len(part) for part in parts)
            crc = 0
            for part in parts:
                crc = crc32(part, crc)
            compressed_size = size
        else:
            records = b"".join(self._records)
            parts = [self._compress(records)]
            size, crc, compressed_size = len(records), crc32(records), len(parts[0])
        start_time = min(min(entries[0::2]) for entries in index.values())
        end_time = max(max(entries[0::2]) for entries in index.values())
        compression = _string(self._compression)
        head = struct.pack(f"<BQQQQI{len(compression)}sQ", CHUNK, 36 + len(compression) + compressed_size,
                           start_time, end_time, size, crc, compression, compressed_size)
        chunk_start = self._position
        chunk_length = len(head) + compressed_size
        offset = index_start = chunk_start + chunk_length
        offsets, index_records = [], []
        counts = self._message_counts
        for channel_id, entries in index.items():
            record = struct.pack(f"<BQHI{len(entries)}Q", MESSAGE_INDEX, 6 + 8 * len(entries), channel_id,
                                 8 * len(entries), *entries)
            offsets.append((channel_id, offset))
            offset += len(record)
            index_records.append(record)
            counts[channel_id] += len(entries) // 2
        indexes = b"".join(index_records)
        self._stream.write(head)
        for part in parts:
            self._stream.write(part)
        self._stream.write(indexes)
        self._position = offset
        self._chunk_indexes.append(_record(CHUNK_INDEX, struct.pack("<QQQQ", start_time, end_time, chunk_start,
                                                                    chunk_length)
                                           + _id_map(offsets) + _U64.pack(len(indexes)) + compression
                                           + struct.pack("<QQ", compressed_size, size)))
        if self._start_time is None or start_time < self._start_time:
            self._start_time = start_time
        if self._end_time is None or end_time > self._end_time:
            self._end_time = end_time
        self._records.clear()
        self._size = 0
        index.clear()

    # - the end -

    def finish(self) -> None:
        """Write the open chunk, Data End, the summary section, Footer and the closing magic; the stream is
        flushed, not closed.

        Data End (0x0F): data_section_crc uint32 (0).
        Statistics (0x0B): message_count uint64, schema_count uint16, channel_count, attachment_count,
        metadata_count, chunk_count uint32, message_start_time, message_end_time uint64,
        channel_message_counts map<uint16, uint64>.
        Chunk Index (0x08): message_start_time, message_end_time, chunk_start_offset, chunk_length uint64,
        message_index_offsets map<uint16, uint64>, message_index_length uint64, compression string,
        compressed_size, uncompressed_size uint64.
        Summary Offset (0x0E): group_opcode uint8, group_start, group_length uint64.
        Footer (0x02): summary_start, summary_offset_start uint64, summary_crc uint32 (CRC-32 of the
        bytes from summary_start to the end of summary_offset_start).
        """
        self._close_chunk()
        self._write(_record(DATA_END, _U32.pack(0)))
        counts = {channel_id: count for channel_id, count in self._message_counts.items() if count}
        statistics = _record(STATISTICS, struct.pack(
            "<QHIIIIQQ", sum(counts.values()), len(self._schemas), len(self._channels), 0, 0,
            len(self._chunk_indexes), self._start_time or 0, self._end_time or 0) + _id_map(counts.items()))
        summary_start = position = self._position
        groups, offsets = [], []
        for opcode, records in ((SCHEMA, self._schemas), (CHANNEL, self._channels), (STATISTICS, [statistics]),
                                (CHUNK_INDEX, self._chunk_indexes)):
            if records:
                group = b"".join(records)
                offsets.append(_record(SUMMARY_OFFSET, struct.pack("<BQQ", opcode, position, len(group))))
                groups.append(group)
                position += len(group)
        summary = b"".join(groups + offsets)
        footer = _PREFIX.pack(FOOTER, 20) + struct.pack("<QQ", summary_start, position)
        crc = crc32(footer, crc32(summary))
        self._write(summary + footer + _U32.pack(crc) + MAGIC)
        self._stream.flush()
