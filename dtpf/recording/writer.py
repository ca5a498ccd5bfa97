"""Recording dtpf messages to MCAP.

One channel per key expression (the MCAP topic is the key expression), every
schema written into the file (:func:`dtpf.messages.codec.schema_for`), so a reader
with only the ``mcap`` library and the file can decode it. The file is written
by :class:`dtpf.recording.mcap_file.McapWriter`::

    with McapRecording("run.mcap") as recording:
        recording.write("dtpf/ungm-1/entity/estimate", payload, log_time_ns)

The open chunk is flushed to disk at least every ``flush_interval`` seconds,
so a killed recorder loses at most that much; ``close()`` (also on leaving
the ``with`` block, whatever the exception) writes the summary and footer.

A write that fails (a full disk, a file-size limit, a file system turned
read-only, the file deleted under the recorder) raises :class:`LogWriteError`
once and ends the recording: the file keeps every chunk written before, and
``dtpf recover`` rewrites it as a complete file once there is room.
"""
from __future__ import annotations

import errno
import os
import time
from pathlib import Path

from dtpf.messages import keys
from dtpf.messages.codec import message_encoding, schema_for
from dtpf.messages.errors import DtpfError
from dtpf.recording.mcap_file import COMPRESSIONS, McapWriter

__all__ = ["EXIT_LOG_WRITE", "LogWriteError", "McapRecording", "UNKNOWN_ENCODING"]

#: Exit code of a recorder whose log could not be written: starting another on the same disk would not help.
EXIT_LOG_WRITE = 3

#: Message encoding of payloads on keys outside the topic table (no schema).
UNKNOWN_ENCODING = "application/octet-stream"

#: Chunk compressions by name -> the name written in each chunk ("" for none).
COMPRESSION = COMPRESSIONS

#: Particle-set payload size above which ``auto`` leaves chunks uncompressed.
AUTO_LIMIT = 64 << 10


def auto_compression(particle_set_bytes: int) -> str:
    """The chunk compression ``auto`` picks for particle sets of this many bytes.

    Random float64 states do not compress: measured on ``dtpf launch`` logs,
    lz4 chunks kept 0.997 of the bytes at N = 5000, 0.999 at 2e4 and 1.000 at
    1e5, against 0.694 at N = 1000 (where the JSON topics weigh more). lz4
    still costs CPU on every chunk (1.6 MB messages: 4.9 ms each with lz4,
    2.5 ms without), and on two cores the recorder competes with the
    lockstep layers. So: lz4 up to :data:`AUTO_LIMIT` bytes, none above.
    """
    return "lz4" if particle_set_bytes <= AUTO_LIMIT else "none"


class LogWriteError(DtpfError, RuntimeError):
    """The log could not be written; the recording has ended.

    ``path``: the file; ``cause``: the OSError (``cause.errno``: ENOSPC for a
    full disk, EFBIG past a file-size limit, EROFS on a read-only file
    system; None when the file was deleted); ``messages``: those written
    before it failed.
    """

    def __init__(self, path: Path, cause: OSError | None, messages: int, what: str):
        self.path, self.cause, self.messages = path, cause, messages
        super().__init__(f"cannot write the log {path}: {what}")

    @property
    def disk_full(self) -> bool:
        """True when retrying on the same disk would fail again (full, over a size limit, read-only)."""
        return self.cause is not None and self.cause.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT,
                                                               errno.EROFS)


class McapRecording:
    """An MCAP file being written.

    Parameters
    ----------
    path : str or Path
        Output file; its folder is created if missing.
    compression : "lz4", "zstd" or "none"
        Chunk compression; the recorder service picks one with
        :func:`auto_compression`. lz4 is the default here: of the codecs it
        costs least, and JSON-heavy small runs shrink by about 30%.
    chunk_size : int
        Bytes per chunk before it is closed.
    flush_interval : float
        Seconds between forced flushes of the open chunk.
    """

    def __init__(self, path, *, compression: str = "lz4", chunk_size: int = 1 << 20,
                 flush_interval: float = 1.0):
        if compression not in COMPRESSION:
            raise ValueError(f"unknown compression {compression!r}; expected one of {', '.join(COMPRESSION)}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = McapWriter(self._file, chunk_size=chunk_size, compression=compression)
        self._writer.start(profile="", library="dtpf")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self.flush_interval = flush_interval
        self._last_flush = time.monotonic()
        self.messages = 0
        self.closed = False
        self.failure: LogWriteError | None = None

    def _channel(self, key: str) -> int:
        channel = self._channels.get(key)
        if channel is not None:
            return channel
        try:
            cls = keys.topic_of(key).message
        except ValueError:
            channel = self._writer.register_channel(topic=key, message_encoding=UNKNOWN_ENCODING, schema_id=0)
        else:
            record = schema_for(cls)
            schema = self._schemas.get(record.name)
            if schema is None:
                schema = self._schemas[record.name] = self._writer.register_schema(
                    name=record.name, encoding=record.encoding, data=record.data)
            channel = self._writer.register_channel(topic=key, message_encoding=message_encoding(cls),
                                                    schema_id=schema)
        self._channels[key] = channel
        return channel

    def write(self, key: str, payload: bytes, log_time_ns: int | None = None) -> None:
        """Append one message received on ``key`` at ``log_time_ns`` (default: now); LogWriteError if the
        file cannot take it (and every call after)."""
        if self.failure is not None:
            raise self.failure
        if self.closed:
            raise ValueError(f"recording {self.path} is closed")
        now = time.time_ns() if log_time_ns is None else int(log_time_ns)
        try:
            channel = self._channel(key)
            sequence = self._sequence.get(channel, 0)
            self._sequence[channel] = sequence + 1
            # bytes(): the writer keeps the payload until its chunk is written (a bytes object is not copied).
            self._writer.add_message(channel, now, bytes(payload), now, sequence)
        except OSError as error:
            raise self._fail(error) from None
        self.messages += 1
        self.flush_if_due()

    def flush_if_due(self) -> None:
        """Flush the open chunk if ``flush_interval`` has passed since the last flush."""
        if time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()

    def flush(self) -> None:
        """Close the open chunk and push it to the file (no fsync); LogWriteError if it cannot, or if the
        file was deleted meanwhile (what is written then goes nowhere)."""
        if self.failure is not None:
            raise self.failure
        try:
            self._writer.flush()
            self._file.flush()
            removed = os.fstat(self._file.fileno()).st_nlink == 0
        except OSError as error:
            raise self._fail(error) from None
        if removed:
            raise self._fail(None, "the file was deleted while it was being written (its folder removed?)")
        self._last_flush = time.monotonic()

    def _fail(self, cause: OSError | None, what: str | None = None) -> LogWriteError:
        """End the recording after a failed write: the file is closed as it stands (no summary or footer,
        which would not fit either)."""
        if what is None:
            what = f"{cause.strerror or cause} ({errno.errorcode.get(cause.errno, cause.errno)})"
        self.failure = LogWriteError(self.path, cause, self.messages, what)
        self.closed = True
        try:
            self._file.close()
        except OSError:  # the buffer's tail does not fit either
            pass
        return self.failure

    def close(self) -> None:
        """Write the summary and footer and close the file; safe to call twice. LogWriteError if they
        cannot be written (the file keeps what was flushed before)."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
            self._file.close()
        except OSError as error:
            self.closed = False
            raise self._fail(error) from None

    def __enter__(self) -> "McapRecording":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
