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
           "SetLost", "slot_key"]

log = logging.getLogger("dtpf.shared_sets")

#: Payloads from this size on go through a slot (a set of 16,384 particles in one dimension is 256 KiB).
MIN_SHARED_BYTES = 256 << 10
#: Bytes of slots a publisher keeps: as many sets as fit, at least 4 and at most 64.
SLOT_BUDGET = 64 << 20
MIN_SLOTS, MAX_SLOTS = 4, 64
#: Seconds a reader on another host waits for the bytes of a set.
FETCH_TIMEOUT = 10.0
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


class SetResolver:
    """Turns references into payloads for one inbox: a view of the slot on this host (held until the next
    :meth:`resolve` or :meth:`release`), the bytes asked of the publisher from another host."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        self.reader = SlotReader()
        self._held: Held | None = None
        #: References dropped unread (the inbox was full), added by the subscriber's thread.
        self.skipped: collections.deque = collections.deque(maxlen=1024)

    def resolve(self, key: str, payload, views: bool):
        """The payload of a reference received on ``key``: a read-only memoryview if ``views`` (valid until
        the next call), else bytes. SetLost if it cannot be had, SlotError if the reference is malformed."""
        self.release()
        reference = Reference.parse(payload)
        if not self.reader.is_local(reference):
            return self._fetch(key, reference)
        try:
            held = self.reader.resolve(reference)
        except SlotMiss as error:
            raise SetLost(str(error)) from None
        if views:
            self._held = held
            return held.view
        data = bytes(held.view)
        self.reader.release(held)
        return data

    def _skip(self) -> None:
        """The references dropped unread: their writers need not wait for this reader."""
        while self.skipped:
            try:
                self.reader.skip(Reference.parse(self.skipped.popleft()))
            except (SlotError, IndexError):
                pass

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
        """Done with the view last given (and with the references dropped unread since)."""
        if self._held is not None:
            self.reader.release(self._held)
            self._held = None
        if self.skipped:
            self._skip()

    def close(self) -> None:
        self.release()
        self.reader.close()
