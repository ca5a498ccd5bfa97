"""Particle sets over the bus by reference: shared-memory slots on one host, bytes between hosts.

A service puts a particle set of at least :data:`MIN_SHARED_BYTES` into a slot of its own ring
(:class:`dtpf.shell.slots.SlotWriter`) and publishes the slot's reference on the set's key; a subscriber
on the same host reads the set where it lies, one on another host asks the publisher's queryable
``<key>/@slot`` (``?writer=<id>;seq=<n>``) for the bytes. Who may publish, subscribe and ask is what the
access control says of ``<key>`` and ``<key>/@slot``; on a host, slot files are readable by their owner
only (mode 0600), like the process's memory.

Smaller payloads, and every payload when the process's sets are not shared
(:func:`set_shared_sets`, or ``DTPF_SHARED_SETS=0`` in the environment), go as bytes, as every other
message does; Zenoh itself moves large byte payloads between the processes of a host through its own
shared memory, with a copy on each side.
"""
from __future__ import annotations

import collections
import logging
import os
import threading

import zenoh

from dtpf.shell.slots import Held, Reference, SlotError, SlotMiss, SlotReader, SlotWriter, shm_folder

__all__ = ["MIN_SHARED_BYTES", "SLOT_BUDGET", "shared_sets", "set_shared_sets", "SetPublisher", "SetResolver",
           "SetLost", "SetDropped", "slot_key"]

log = logging.getLogger("dtpf.shared_sets")

#: Payloads from this size on go through a slot (a set of 16,384 particles in one dimension is 256 KiB).
MIN_SHARED_BYTES = 256 << 10
#: Bytes of slots a publisher keeps: as many sets as fit, at least 4 and at most 64.
SLOT_BUDGET = 64 << 20
MIN_SLOTS, MAX_SLOTS = 4, 64
#: Seconds a reader on another host waits for the bytes of a set.
FETCH_TIMEOUT = 10.0
#: Writers an inbox keeps track of (each the sets it holds in their slots); more, and those holding none go.
MAX_WRITERS = 256
#: Seconds a publisher that ends waits for the readers on its host to take its last set.
DRAIN_TIMEOUT = 10.0

_SHARED = [os.environ.get("DTPF_SHARED_SETS", "1").strip().lower() not in ("0", "false", "no", "off")]


def shared_sets() -> bool:
    """Whether this process puts large sets into shared memory (and a shm folder exists)."""
    return _SHARED[0] and shm_folder() is not None


def set_shared_sets(enabled: bool) -> None:
    """Share this process's large sets through slots (True, the default) or send them as bytes."""
    _SHARED[0] = bool(enabled)


def slot_key(key: str) -> str:
    """The key of the queryable that gives the bytes of ``key``'s sets to readers on other hosts."""
    return f"{key}/@slot"


def slots_for(length: int) -> int:
    """Slots of a ring of payloads of ``length`` bytes: :data:`SLOT_BUDGET` of them, within the bounds."""
    return max(MIN_SLOTS, min(MAX_SLOTS, SLOT_BUDGET // max(1, length)))


class SetPublisher:
    """Puts large payloads of one key into slots and their references on ``publisher``; answers readers on
    other hosts. ``wait``: seconds a reader on this host may hold a slot up before it is dropped."""

    def __init__(self, session: zenoh.Session, key: str, publisher, wait: float = 60.0):
        self.key = key
        self.publisher = publisher
        self.wait = wait
        self.writer: SlotWriter | None = None
        self._lock = threading.Lock()
        self._queryable = session.declare_queryable(slot_key(key), self._on_query)

    def put_parts(self, parts, length: int) -> None:
        """Publish the payload made of ``parts`` (``length`` bytes in all) by reference."""
        with self._lock:
            if self.writer is None:
                self.writer = SlotWriter(slots=slots_for(length), wait=self.wait)
            reference = self.writer.write(parts)
        self.publisher.put(reference)

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            params = dict(query.parameters)
            writer, seq = params.get("writer", ""), int(params.get("seq", "0"))
        except (ValueError, TypeError):
            query.reply_err("expected ?writer=<id>;seq=<n>")
            return
        with self._lock:
            data = self.writer.read(seq) if self.writer is not None and writer == self.writer.id else None
        if data is None:
            query.reply_err(f"set {seq} of writer {writer[:40]} is not held any more")
        else:
            query.reply(query.key_expr, data)

    def undeclare(self, drain: float = DRAIN_TIMEOUT) -> None:
        """Stop answering and remove the slots, once the readers on this host have taken the last set (at
        most ``drain`` seconds)."""
        with self._lock:
            if self.writer is not None and not self.writer.drain(drain):
                log.warning("a reader on this host had not taken the last set of %s after %.0f s", self.key, drain)
        try:
            self._queryable.undeclare()
        except zenoh.ZError:
            pass
        with self._lock:
            if self.writer is not None:
                self.writer.close()


class SetLost(Exception):
    """A set whose reference came but whose payload could not be had; the message says why."""


class SetDropped(Exception):
    """A set the inbox dropped after it was queued (reported when it was dropped)."""


_DROPPED = object()


class SetResolver:
    """Turns references into payloads for one inbox: a view of the slot on this host (held until the next
    :meth:`resolve` or :meth:`release`), the bytes asked of the publisher from another host.

    The inbox's subscriber thread calls :meth:`arrive` for each reference of this host it queues: the
    newest set of each writer waits in its slot (read in place by its get), and one that still waits when
    its writer's next arrives is copied out then, so that a reader that falls behind, or whose loop is
    stuck, holds a writer up by two sets at most (the one it reads and the newest). A set that finds no room to be copied
    is dropped, counted, as bytes would be; with ``back_pressure`` it stays in its slot, and its writer
    waits."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        self.reader = SlotReader()
        self._held: Held | None = None
        #: By writer, the references queued whose slots are held for their get, oldest first.
        self._waiting: dict[str, collections.deque[tuple[bytes, Reference]]] = {}
        #: Payloads copied out of their slots (or why not), by reference, until their get.
        self._copied: dict[bytes, object] = {}
        #: Bytes of the payloads copied out and not yet taken.
        self.copied_bytes = 0
        self._lock = threading.Lock()

    def local(self, payload: bytes) -> Reference | None:
        """The reference ``payload`` holds if it names a slot of this host; None for another host's or a
        malformed one (:meth:`resolve` says what is wrong with it)."""
        try:
            reference = Reference.parse(payload)
        except SlotError:
            return None
        return reference if self.reader.is_local(reference) else None

    def arrive(self, reference: Reference, payload: bytes, room, back_pressure: bool, on_drop) -> None:
        """``reference`` (received as ``payload``) is about to be queued: hold its slot, and copy out the
        sets of its writer that were waiting in theirs if ``room(nbytes)`` says they fit; those that do not
        are dropped (``on_drop()``), or, with ``back_pressure``, keep their slots."""
        with self._lock:
            waiting = self._waiting.setdefault(reference.writer, collections.deque())
            keep = collections.deque()
            while waiting:
                older_payload, older = waiting.popleft()
                if room(older.length):
                    try:
                        data = self.reader.copy(older)
                    except (SlotError, SlotMiss) as error:
                        self._keep(older_payload, SetLost(str(error)))
                    else:
                        self._keep(older_payload, data)
                    self.reader.unpin(older)
                elif back_pressure:
                    keep.append((older_payload, older))
                else:
                    self._keep(older_payload, _DROPPED)
                    self.reader.unpin(older)
                    on_drop()
            waiting.extend(keep)
            try:
                self.reader.pin(reference)
            except SlotError:
                return  # its get says why
            waiting.append((payload, reference))
            while len(self._waiting) > MAX_WRITERS:  # writers long gone: their sets were taken or copied
                oldest = next(iter(self._waiting))
                if self._waiting[oldest]:
                    break
                del self._waiting[oldest]

    def _keep(self, payload: bytes, what) -> None:
        """Keep what became of a waiting set (its bytes, SetLost or dropped) for its get; the same reference
        received twice keeps the last, counted once."""
        before = self._copied.get(payload)
        if isinstance(before, bytes):
            self.copied_bytes -= len(before)
        self._copied[payload] = what
        if isinstance(what, bytes):
            self.copied_bytes += len(what)

    def skip(self, reference: Reference) -> None:
        """A reference dropped unread: its writer need not wait for this reader."""
        self.reader.skip(reference)

    def resolve(self, key: str, payload: bytes, views: bool):
        """The payload of a reference received on ``key``: a read-only memoryview if ``views`` (valid until
        the next call), else bytes. SetLost if it cannot be had, SlotError if the reference is malformed,
        SetDropped if the inbox dropped it after it was queued."""
        self.release()
        pinned = False
        reference = Reference.parse(payload)
        with self._lock:
            copied = self._copied.pop(payload, None)
            if isinstance(copied, bytes):
                self.copied_bytes -= len(copied)
            elif copied is None:
                waiting = self._waiting.get(reference.writer, ())
                for index, (queued, _) in enumerate(waiting):
                    if queued == payload:
                        del waiting[index]
                        pinned = True
                        break
        if copied is _DROPPED:
            raise SetDropped()
        if isinstance(copied, SetLost):
            raise copied
        if copied is not None:
            return memoryview(copied).toreadonly() if views else copied
        if not self.reader.is_local(reference):
            return self._fetch(key, reference)
        try:
            held = self.reader.resolve(reference, pinned=pinned)
        except SlotMiss as error:
            raise SetLost(str(error)) from None
        if views:
            self._held = held
            return held.view
        data = bytes(held.view)
        self.reader.release(held)
        return data

    def _fetch(self, key: str, reference: Reference) -> bytes:
        replies = self.session.get(f"{slot_key(key)}?writer={reference.writer};seq={reference.seq}",
                                   timeout=FETCH_TIMEOUT)
        reasons = []
        for reply in replies:
            if reply.ok is not None:
                data = reply.ok.payload.to_bytes()
                if len(data) == reference.length:
                    return data
                reasons.append(f"{len(data)} bytes instead of {reference.length}")
            else:
                reasons.append(reply.err.payload.to_bytes().decode("utf-8", "replace")[:200])
        raise SetLost(f"set {reference.seq} on {key[:200]} lies in another host's shared memory and its "
                      f"publisher did not give it: {'; '.join(reasons) or 'no answer'}")

    def release(self) -> None:
        """Done with the view last given."""
        if self._held is not None:
            self.reader.release(self._held)
            self._held = None

    def close(self) -> None:
        self.release()
        self.reader.close()
