"""Large payloads between the processes of one host, through shared memory: a ring of slots and references.

A publisher of large payloads (particle sets of 16k particles and more) writes each one, once, into a slot
of a ring in a shared-memory file of its own (``/dev/shm/dtpf-<hex>``, mode 0600) and puts on the bus only
a :class:`Reference` of a few hundred bytes: which host, file, slot and sequence number. A subscriber on the
same host maps the file and reads the payload where it lies (a read-only view, no copy); one on another host
cannot, and asks the publisher for the bytes (:mod:`dtpf.shell.bus` does that over Zenoh). "Host" means one
kernel boot, one ``/dev/shm`` and one network namespace: processes that could not reach each other's files,
or that talk over a network, exchange bytes.

A slot is not written again while a reader on the host still reads it: each reader of a file holds an entry
of its reader table (process id, and the last sequence number it is done with, or skipped), and the writer
waits before reusing a slot until every reader is done with what the slot held, as a publisher with
congestion control BLOCK waits for room in its queue; a reader that has not moved for ``wait`` seconds, or
whose process is gone, is dropped from the table and finds the slot's sequence number changed: the payload
is lost to it, and it says so (:class:`SlotMiss`). Everything a reference says is checked before a file is
opened: a reference comes from the bus, and the bus is hostile.

Layout of a file: a 4096-byte header (magic ``DTPFSLOT``, version, slots, slot capacity, the writer's
process id, then
:data:`MAX_READERS` reader entries of 32 bytes: pid, done, two words reserved), then the slots, each a
64-byte header (sequence number, length) and ``capacity`` bytes. All integers are little-endian uint64.

Example (one process playing both sides)::

    writer = SlotWriter(slots=4)
    reference = writer.write([b"header", particles, weights])      # bytes to put on the bus
    reader = SlotReader()
    held = reader.resolve(reference)       # a Held: .view is a read-only memoryview of the payload
    ...
    reader.release(held)                   # done with it: the writer may reuse the slot
"""
from __future__ import annotations

import fcntl
import json
import mmap
import os
import re
import secrets
import struct
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from dtpf.messages.codec import SET_REFERENCE
from dtpf.messages.errors import DtpfError

__all__ = ["SlotError", "SlotMiss", "Reference", "Held", "SlotWriter", "SlotReader", "is_reference",
           "host_id", "shm_folder", "remove_stale", "MAX_READERS"]

#: Where the slot files live (a tmpfs on Linux); None where there is none: payloads then go as bytes.
SHM_FOLDER = "/dev/shm"
MAGIC = b"DTPFSLOT"
VERSION = 1
#: Most bytes a reference may have (a longer payload starting with the magic is not one).
MAX_REFERENCE = 1024
HEADER_BYTES = 4096
SLOT_HEADER = 64
#: Reader entries of a file: more readers than this on one host read a copy instead.
MAX_READERS = 64
_ENTRY = 32
_READERS_AT = 64
_WORD = struct.Struct("<Q")
_FILE_NAME = re.compile(r"^dtpf-[0-9a-f]{32}$")
#: Largest slot a reference may claim (a set of 1e7 particles in 16 dimensions is 1.4 GB).
MAX_SLOT_BYTES = 4 << 30
MAX_SLOTS = 1024


class SlotError(DtpfError, ValueError):
    """A reference that is malformed, or names a file this process may not or cannot read."""


class SlotMiss(DtpfError, RuntimeError):
    """The slot a reference names holds another payload now: the reader was too slow, or dropped."""


def shm_folder() -> str | None:
    """The folder of slot files, None if this system has none (no ``/dev/shm`` to write in)."""
    return SHM_FOLDER if os.path.isdir(SHM_FOLDER) and os.access(SHM_FOLDER, os.W_OK) else None


@lru_cache(maxsize=1)
def host_id() -> str:
    """This host as slot files see it: the kernel's boot id, the ``/dev/shm`` file system and the network
    namespace. Two processes with the same id can map each other's slot files."""
    parts = []
    try:
        with open("/proc/sys/kernel/random/boot_id", encoding="ascii") as file:
            parts.append(file.read().strip())
    except OSError:
        parts.append("no-boot-id")
    try:
        info = os.stat(SHM_FOLDER)
        parts.append(f"{info.st_dev}:{info.st_ino}")
    except OSError:
        parts.append("no-shm")
    try:
        parts.append(os.readlink("/proc/self/ns/net"))
    except OSError:
        parts.append("no-netns")
    return "/".join(parts)[:200]


@dataclass(frozen=True)
class Reference:
    """Where a payload lies: host, slot file (its name in the shm folder), slot, sequence number and length,
    and the writer that wrote it (its id, for a reader on another host to ask it for the bytes)."""

    host: str
    file: str
    slot: int
    seq: int
    length: int
    writer: str

    def encode(self) -> bytes:
        return SET_REFERENCE + json.dumps({"host": self.host, "file": self.file, "slot": self.slot,
                                             "seq": self.seq, "length": self.length, "writer": self.writer},
                                            separators=(",", ":")).encode("ascii")

    @classmethod
    def parse(cls, payload) -> "Reference":
        """The reference a payload holds; SlotError says what is wrong with one that is malformed."""
        data = bytes(payload[:MAX_REFERENCE + 1])
        if len(data) > MAX_REFERENCE or not data.startswith(SET_REFERENCE):
            raise SlotError("not a slot reference")
        try:
            fields = json.loads(data[len(SET_REFERENCE):].decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            raise SlotError("a slot reference that is not JSON") from None
        if not isinstance(fields, dict) or set(fields) != {"host", "file", "slot", "seq", "length", "writer"}:
            raise SlotError("a slot reference without exactly host, file, slot, seq, length and writer")
        text = {name: fields[name] for name in ("host", "file", "writer")}
        numbers = {name: fields[name] for name in ("slot", "seq", "length")}
        if not all(isinstance(value, str) and len(value) <= 200 for value in text.values()):
            raise SlotError("a slot reference whose host, file or writer is not a short string")
        if not all(type(value) is int for value in numbers.values()):
            raise SlotError("a slot reference whose slot, seq or length is not an integer")
        if not re.fullmatch(r"[0-9a-f]{1,64}", text["writer"]):
            raise SlotError("a slot reference whose writer is not a hex id")
        if not _FILE_NAME.match(text["file"]):
            raise SlotError(f"a slot reference to {text['file'][:60]!r}, not a slot file (dtpf-<32 hex>)")
        if not (0 <= numbers["slot"] < MAX_SLOTS and 1 <= numbers["seq"] < 2 ** 63
                and 0 <= numbers["length"] <= MAX_SLOT_BYTES):
            raise SlotError(f"a slot reference out of range: slot {numbers['slot']}, seq {numbers['seq']}, "
                            f"length {numbers['length']}")
        return cls(**text, **numbers)


def is_reference(payload) -> bool:
    """Whether a payload is (claims to be) a slot reference rather than a message."""
    return len(payload) <= MAX_REFERENCE and bytes(payload[:len(SET_REFERENCE)]) == SET_REFERENCE


def _word(buffer, offset: int) -> int:
    return _WORD.unpack_from(buffer, offset)[0]


def _put_word(buffer, offset: int, value: int) -> None:
    _WORD.pack_into(buffer, offset, value)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class _File:
    """One mapped slot file (the writer's, or one a reader opened)."""

    def __init__(self, path: str, fd: int, size: int):
        self.path = path
        self.name = os.path.basename(path)
        self.fd = fd
        self.map = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        self.slots = _word(self.map, 16)
        self.capacity = _word(self.map, 24)

    def slot_at(self, slot: int) -> int:
        return HEADER_BYTES + slot * (SLOT_HEADER + self.capacity)

    def entry_at(self, index: int) -> int:
        return _READERS_AT + index * _ENTRY

    def close(self) -> None:
        try:
            self.map.close()
        except BufferError:  # a view of it is still held somewhere: the mapping goes with the last one
            pass
        os.close(self.fd)


class SlotWriter:
    """A ring of ``slots`` slots in a shared-memory file of its own; :meth:`write` puts a payload in the next
    one and returns its reference. A payload larger than a slot moves the ring to a new, larger file (the
    old one is removed once every slot of the new one has been written: references to it in flight still
    resolve). ``wait``: seconds a reader may hold up a write before it is dropped from the reader table."""

    def __init__(self, slots: int = 4, wait: float = 60.0, folder: str | None = None):
        if not 1 <= slots <= MAX_SLOTS:
            raise ValueError(f"slots must be 1..{MAX_SLOTS}, got {slots}")
        self.slots = slots
        self.wait = wait
        self.folder = folder or shm_folder()
        if self.folder is None:
            raise SlotError("no shared-memory folder on this system")
        self.id = secrets.token_hex(8)
        self.seq = 0
        self.file: _File | None = None
        self._retired: list[tuple[_File, int]] = []
        #: Readers dropped because they held a write up for ``wait`` seconds or their process was gone.
        self.dropped_readers = 0

    def write(self, parts) -> bytes:
        """Copy ``parts`` (bytes-like objects, e.g. a header and numpy arrays), one after the other, into the
        next slot; the encoded :class:`Reference` to it."""
        views = [memoryview(part).cast("B") if isinstance(part, np.ndarray) else memoryview(part) for part in parts]
        length = sum(view.nbytes for view in views)
        if self.file is None or length > self.file.capacity:
            self._grow(length)
        file = self.file
        self.seq += 1
        slot = self.seq % file.slots
        self._wait_for_readers(file, self.seq - file.slots)
        start = file.slot_at(slot)
        _put_word(file.map, start, 0)  # being written: a reader of the old payload sees it is gone
        offset = start + SLOT_HEADER
        target = np.frombuffer(file.map, dtype=np.uint8, count=length, offset=offset)
        at = 0
        for view in views:
            target[at:at + view.nbytes] = np.frombuffer(view, dtype=np.uint8)
            at += view.nbytes
        del target
        _put_word(file.map, start + 8, length)
        _put_word(file.map, start, self.seq)
        self._retire_old()
        return Reference(host_id(), file.name, slot, self.seq, length, self.id).encode()

    def read(self, seq: int) -> bytes | None:
        """The payload of ``seq`` if its slot still holds it (for a reader on another host), else None."""
        file = self.file
        if file is None or not 1 <= seq <= self.seq:
            return None
        start = file.slot_at(seq % file.slots)
        if _word(file.map, start) != seq:
            return None
        length = _word(file.map, start + 8)
        data = bytes(file.map[start + SLOT_HEADER:start + SLOT_HEADER + length])
        return data if _word(file.map, start) == seq else None

    def _grow(self, length: int) -> None:
        capacity = -(-int(length * 1.25 + 4096) // 65536) * 65536
        size = HEADER_BYTES + self.slots * (SLOT_HEADER + capacity)
        path = os.path.join(self.folder, f"dtpf-{secrets.token_hex(16)}")
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        try:
            os.posix_fallocate(fd, 0, size)  # the room is taken now: a full tmpfs fails here, not with SIGBUS
            header = bytearray(HEADER_BYTES)
            header[0:8] = MAGIC
            _put_word(header, 8, VERSION)
            _put_word(header, 16, self.slots)
            _put_word(header, 24, capacity)
            _put_word(header, 32, os.getpid())
            os.pwrite(fd, bytes(header), 0)
            file = _File(path, fd, size)
        except BaseException:
            os.close(fd)
            os.unlink(path)
            raise
        if self.file is not None:
            self._retired.append((self.file, self.seq + self.slots))
        else:
            remove_stale(self.folder)
        self.file = file

    def _retire_old(self) -> None:
        while self._retired and self._retired[0][1] <= self.seq:
            old, _ = self._retired.pop(0)
            self._remove(old)

    def drain(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for every reader on this host to be done with the last payload (a
        process about to end lets its readers take what it wrote); False if some were not."""
        if self.file is None or self.seq < 1:
            return True
        dropped = self.dropped_readers
        self._wait_for_readers(self.file, self.seq, timeout)
        return self.dropped_readers == dropped

    def _wait_for_readers(self, file: _File, done_needed: int, wait: float | None = None) -> None:
        """Wait until every reader of ``file`` is done with sequence number ``done_needed`` (the slot's last
        payload); drop readers that are gone or that hold the write up for ``wait`` seconds (default: the
        writer's)."""
        if done_needed < 1:
            return
        wait = self.wait if wait is None else wait
        deadline = None
        pause = 0.0001
        while True:
            late = []
            for index in range(MAX_READERS):
                at = file.entry_at(index)
                pid = _word(file.map, at)
                if pid and _word(file.map, at + 8) < done_needed:
                    late.append((index, pid))
            if not late:
                return
            now = time.monotonic()
            deadline = deadline or now + wait
            for index, pid in late:
                if now >= deadline or not _pid_alive(pid):
                    self._drop_reader(file, index, pid)
            time.sleep(pause)
            pause = min(pause * 2, 0.002)

    def _drop_reader(self, file: _File, index: int, pid: int) -> None:
        with _locked(file.fd):
            if _word(file.map, file.entry_at(index)) == pid:
                _put_word(file.map, file.entry_at(index), 0)
                self.dropped_readers += 1

    def _remove(self, file: _File) -> None:
        try:
            os.unlink(file.path)
        except FileNotFoundError:
            pass
        file.close()

    def close(self) -> None:
        """Remove the files (readers that mapped them keep what they hold)."""
        for old, _ in self._retired:
            self._remove(old)
        self._retired.clear()
        if self.file is not None:
            self._remove(self.file)
            self.file = None


def remove_stale(folder: str) -> list[str]:
    """Remove the slot files of this user whose writer process is gone (one killed before it could): the
    names removed. A file being created (no writer yet) is left alone."""
    removed = []
    try:
        names = [name for name in os.listdir(folder) if _FILE_NAME.match(name)]
    except OSError:
        return removed
    for name in names:
        path = os.path.join(folder, name)
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            if os.fstat(fd).st_uid != os.geteuid():
                continue
            header = os.pread(fd, 40, 0)
            if len(header) == 40 and header[:8] == MAGIC and _word(header, 32) and not _pid_alive(_word(header, 32)):
                os.unlink(path)
                removed.append(name)
        except OSError:
            pass
        finally:
            os.close(fd)
    return removed


class _locked:
    """An exclusive lock on a slot file while its reader table changes."""

    def __init__(self, fd: int):
        self.fd = fd

    def __enter__(self):
        fcntl.flock(self.fd, fcntl.LOCK_EX)

    def __exit__(self, *exc):
        fcntl.flock(self.fd, fcntl.LOCK_UN)


@dataclass
class Held:
    """A payload a reader holds in a slot: ``view`` (read-only) stays valid until :meth:`SlotReader.release`.
    ``file`` is None for a payload copied at once (one its reader could not keep the writer from)."""

    view: memoryview
    reference: Reference
    file: _File | None
    entry: int


class _Reading:
    """A slot file a reader maps: its entry in the file's reader table, the payloads it holds or has queued
    (sequence number: count), and the last sequence number it has seen."""

    def __init__(self, file: _File, entry: int, seen: int):
        self.file = file
        self.entry = entry
        self.pins: dict[int, int] = {}
        self.seen = seen

    def pin(self, seq: int) -> None:
        """Hold payload ``seq`` (once more)."""
        self.pins[seq] = self.pins.get(seq, 0) + 1
        self.seen = max(self.seen, seq)

    def done(self) -> int:
        """What the writer may overwrite: everything before the oldest payload held, else all seen."""
        return min(self.pins) - 1 if self.pins else self.seen


class SlotReader:
    """The reading side: maps the slot files that references name (at most ``max_files`` at once, the least
    recently used closed first), holds an entry in each one's reader table, and says what it is done with:
    everything before the oldest payload it holds or has pinned for later (:meth:`pin`). Thread-safe: a
    subscriber's thread may pin, copy and skip while another resolves and releases."""

    def __init__(self, max_files: int = 16, folder: str | None = None):
        self.folder = folder or shm_folder()
        self.max_files = max_files
        self._files: OrderedDict[str, _Reading] = OrderedDict()
        self._unreadable: OrderedDict[str, str] = OrderedDict()
        self._lock = threading.RLock()

    def is_local(self, reference: Reference) -> bool:
        return self.folder is not None and reference.host == host_id()

    def pin(self, reference: Reference) -> None:
        """Keep the writer from overwriting ``reference``'s slot until :meth:`resolve` (``pinned=True``) and
        :meth:`release`, or :meth:`unpin`. SlotError as for :meth:`resolve`."""
        with self._lock:
            self._reading(reference).pin(reference.seq)

    def unpin(self, reference: Reference) -> None:
        """Let go of a payload pinned and never resolved."""
        with self._lock:
            reading = self._files.get(reference.file)
            if reading is not None:
                self._let_go(reading, reference.seq)

    def resolve(self, reference: Reference, pinned: bool = False) -> Held:
        """The payload ``reference`` names, held until :meth:`release` (``pinned``: :meth:`pin` was called
        for it, and this takes that pin over). SlotError: the file cannot be read (gone, not a slot file,
        not this user's) or the reference does not fit it; SlotMiss: its slot holds another payload now."""
        with self._lock:
            try:
                reading = self._reading(reference)
            except SlotError:
                if pinned:
                    self.unpin(reference)
                raise
            if not pinned:
                reading.pin(reference.seq)
            file, start = reading.file, reading.file.slot_at(reference.slot)
            if _word(file.map, start) != reference.seq or _word(file.map, start + 8) != reference.length:
                self._let_go(reading, reference.seq)
                raise SlotMiss(f"slot {reference.slot} of {reference.file} no longer holds payload {reference.seq}")
            view = memoryview(file.map)[start + SLOT_HEADER:start + SLOT_HEADER + reference.length].toreadonly()
            if reference.seq > _word(file.map, file.entry_at(reading.entry) + 8):
                return Held(view, reference, file, reading.entry)
        # The reader table says this reader was already done with it (a reference that came late, as one
        # recovered from a publisher's cache): the writer may be rewriting the slot, so copy and check.
        data = bytes(view)
        view.release()
        valid = _word(file.map, start) == reference.seq
        self.unpin(reference)
        if not valid:
            raise SlotMiss(f"slot {reference.slot} of {reference.file} no longer holds payload {reference.seq}")
        return Held(memoryview(data).toreadonly(), reference, None, reading.entry)

    def copy(self, reference: Reference) -> bytes:
        """The payload's bytes, its slot let go at once. SlotError and SlotMiss as for :meth:`resolve`."""
        held = self.resolve(reference)
        try:
            return bytes(held.view)
        finally:
            self.release(held)

    def skip(self, reference: Reference) -> None:
        """Done with a payload never read (dropped unread): the writer need not wait for it."""
        with self._lock:
            reading = self._files.get(reference.file)
            if reading is not None:
                reading.seen = max(reading.seen, reference.seq)
                self._publish(reading)

    def release(self, held: Held) -> None:
        """Done with ``held``: its slot may be written again. Its view must not be used any more."""
        held.view.release()
        if held.file is not None:
            self.unpin(held.reference)

    def still_valid(self, held: Held) -> bool:
        """Whether ``held``'s slot still holds its payload (a reader dropped for holding a write up loses it)."""
        if held.file is None:
            return True
        return _word(held.file.map, held.file.slot_at(held.reference.slot)) == held.reference.seq

    def _let_go(self, reading: _Reading, seq: int) -> None:
        count = reading.pins.get(seq, 0)
        if count > 1:
            reading.pins[seq] = count - 1
        elif count == 1:
            del reading.pins[seq]
        self._publish(reading)

    def _publish(self, reading: _Reading) -> None:
        """Tell the writer what this reader is done with (never less than before)."""
        at = reading.file.entry_at(reading.entry)
        done = reading.done()
        if _word(reading.file.map, at) == os.getpid() and _word(reading.file.map, at + 8) < done:
            _put_word(reading.file.map, at + 8, done)

    def _reading(self, reference: Reference) -> _Reading:
        """The mapped file of a local ``reference``, checked against it; its entry taken again if the writer
        dropped this reader for holding a write up."""
        if not self.is_local(reference):
            raise SlotError("a slot reference of another host")
        reading = self._open(reference.file, reference.seq)
        file = reading.file
        if reference.slot >= file.slots or reference.length > file.capacity:
            raise SlotError(f"a slot reference beyond its file: slot {reference.slot} of {file.slots}, "
                            f"{reference.length} bytes in slots of {file.capacity}")
        if _word(file.map, file.entry_at(reading.entry)) != os.getpid():
            # Dropped for holding a write up: back in, and what it held before is lost to it.
            reading.pins = {seq: count for seq, count in reading.pins.items() if seq >= reference.seq}
            reading.entry = self._register(file, reference.seq)
        return reading

    def _open(self, name: str, seq: int) -> _Reading:
        known = self._files.get(name)
        if known is not None:
            self._files.move_to_end(name)
            return known
        if name in self._unreadable:
            raise SlotError(self._unreadable[name])
        try:
            file = self._map(name)
        except SlotError as error:
            self._unreadable[name] = str(error)
            while len(self._unreadable) > 64:
                self._unreadable.popitem(last=False)
            raise
        try:
            entry = self._register(file, seq)
        except SlotError:
            file.close()
            raise
        reading = self._files[name] = _Reading(file, entry, seq - 1)
        while len(self._files) > self.max_files:
            _, old = self._files.popitem(last=False)
            self._unregister(old.file, old.entry)
            old.file.close()
        return reading

    def _map(self, name: str) -> _File:
        path = os.path.join(self.folder, name)
        try:
            fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW)
        except OSError as error:
            raise SlotError(f"cannot open slot file {name}: {error.strerror}") from None
        try:
            info = os.fstat(fd)
            if not (info.st_mode & 0o170000 == 0o100000) or info.st_uid != os.geteuid():
                raise SlotError(f"slot file {name} is not a regular file of this user")
            if info.st_size < HEADER_BYTES or info.st_size > HEADER_BYTES + MAX_SLOTS * (SLOT_HEADER + MAX_SLOT_BYTES):
                raise SlotError(f"slot file {name} has a size ({info.st_size}) no slot file has")
            header = os.pread(fd, 32, 0)
            slots, capacity = _word(header, 16), _word(header, 24)
            if header[:8] != MAGIC or _word(header, 8) != VERSION or not 1 <= slots <= MAX_SLOTS \
                    or HEADER_BYTES + slots * (SLOT_HEADER + capacity) != info.st_size:
                raise SlotError(f"slot file {name} does not have a slot file's header")
            return _File(path, fd, info.st_size)
        except BaseException:
            os.close(fd)
            raise

    def _register(self, file: _File, seq: int) -> int:
        """Take a free entry of ``file``'s reader table, done with what came before ``seq``."""
        pid = os.getpid()
        with _locked(file.fd):
            for index in range(MAX_READERS):
                at = file.entry_at(index)
                if _word(file.map, at) == 0:
                    _put_word(file.map, at + 8, seq - 1)
                    _put_word(file.map, at, pid)
                    return index
        raise SlotError(f"slot file {file.name} has {MAX_READERS} readers already")

    def _unregister(self, file: _File, entry: int) -> None:
        with _locked(file.fd):
            if _word(file.map, file.entry_at(entry)) == os.getpid():
                _put_word(file.map, file.entry_at(entry), 0)

    def close(self) -> None:
        """Leave every reader table (the writers stop waiting for this reader) and unmap the files."""
        with self._lock:
            for reading in self._files.values():
                self._unregister(reading.file, reading.entry)
                reading.file.close()
            self._files.clear()
