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

A log is never overwritten: the recorder creates its file exclusively
(``exclusive=True``: O_EXCL, :class:`LogExistsError` when it exists) and holds
an advisory lock on it (``fcntl.flock``) while writing, so a second writer on
the same path fails at once and can say that another recorder holds it.
:func:`existing_log_files` finds a log and its segments (``run.mcap``,
``run.1.mcap``, ...), :func:`claim_log` refuses them or (``overwrite``)
removes them before a launch.
"""
from __future__ import annotations

import errno
import fcntl
import os
import re
import stat
import time
from pathlib import Path

from dtpf.messages import keys
from dtpf.messages.codec import message_encoding, schema_for
from dtpf.messages.errors import DtpfError
from dtpf.recording.mcap_file import COMPRESSIONS, McapWriter

__all__ = ["EXIT_LOG_WRITE", "LogWriteError", "LogExistsError", "McapRecording", "UNKNOWN_ENCODING",
           "existing_log_files", "claim_log", "held_by_writer"]

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


class LogExistsError(DtpfError, FileExistsError):
    """A log that would be overwritten (or is being written by another recorder); the text says which
    file and why, in one line."""


def held_by_writer(path) -> bool:
    """True when another process holds the writer's lock on ``path`` (a recorder writing it)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
    except OSError:
        return False
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return False
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:  # BlockingIOError: an exclusive lock is held
        return True
    finally:
        os.close(fd)
    return False


def existing_log_files(path) -> list[Path]:
    """The files of the log ``path`` that exist: the log itself and its segments (``NAME.1.mcap``,
    ``NAME.2.mcap``, ... as :func:`dtpf.scripts.launch.segment_path` names them), in segment order."""
    path = Path(path)
    found = [path] if path.exists() or path.is_symlink() else []
    segment = re.compile(re.escape(path.stem) + r"\.([1-9][0-9]*)" + re.escape(path.suffix) + r"$")
    try:
        names = os.listdir(path.parent if str(path.parent) else ".")
    except OSError:
        return found
    numbered = sorted((int(match.group(1)), name) for name in names if (match := segment.match(name)))
    return found + [path.with_name(name) for _, name in numbered]


def _named(paths: list[Path]) -> str:
    return ", ".join(str(path) for path in paths[:4]) + (f" and {len(paths) - 4} more" if len(paths) > 4 else "")


def claim_log(path, overwrite: bool = False) -> list[Path]:
    """Make sure a new log can be written at ``path``: LogExistsError when it or its segments exist,
    unless ``overwrite``, which removes them (never one a recorder is writing). Returns the files removed."""
    existing = existing_log_files(path)
    if not existing:
        return []
    held = [file for file in existing if held_by_writer(file)]
    if held:
        raise LogExistsError(f"the log {_named(held)} is being written by another recorder; choose another "
                             f"output file")
    if not overwrite:
        segments = [file for file in existing if file != Path(path)]
        what = "exists" if not segments else f"and its segments {_named(segments)} exist" \
            if len(segments) < len(existing) else f"has segments on disk: {_named(segments)}"
        raise LogExistsError(f"the log {path} {what}: a log is never overwritten; choose another output file "
                             f"or add --overwrite to replace {'it' if existing == [Path(path)] else 'them'}")
    for file in existing:
        file.unlink(missing_ok=True)
    return existing


def _open_locked(path: Path, exclusive: bool):
    """``path`` opened for writing from its start, with the writer's lock held (see McapRecording)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC | (os.O_EXCL if exclusive else 0)
    try:
        fd = os.open(path, flags, 0o666)
    except FileExistsError:
        held = " and another recorder is writing it" if held_by_writer(path) else ""
        raise LogExistsError(f"cannot write the log {path}: it exists{held}; a log is never "
                             f"overwritten") from None
    try:
        if stat.S_ISREG(os.fstat(fd).st_mode):
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise LogExistsError(f"cannot write the log {path}: another recorder is writing it") from None
            if not exclusive:
                os.ftruncate(fd, 0)
        return os.fdopen(fd, "wb")
    except BaseException:
        os.close(fd)
        raise


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
    exclusive : bool
        Create the file, never open an existing one (:class:`LogExistsError`
        says so, and whether another recorder holds it). Otherwise an
        existing file is replaced, unless another writer holds its lock.

    While open, the recording holds an exclusive advisory lock on the file
    (``fcntl.flock``), so that another writer can tell it is in use.
    """

    def __init__(self, path, *, compression: str = "lz4", chunk_size: int = 1 << 20,
                 flush_interval: float = 1.0, exclusive: bool = False):
        if compression not in COMPRESSION:
            raise ValueError(f"unknown compression {compression!r}; expected one of {', '.join(COMPRESSION)}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = _open_locked(self.path, exclusive)
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
            # bytes(): the writer keeps the payload until its chunk is written (a bytes object is not copied); a
            # payload larger than a chunk (a large set, a view of a publisher's shared memory) is written from
            # where it lies before add_message returns.
            data = payload if len(payload) > self._writer.chunk_size else bytes(payload)
            self._writer.add_message(channel, now, data, now, sequence)
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
