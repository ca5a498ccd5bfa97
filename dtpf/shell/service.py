"""The thin shell every layer's service shares.

A layer service is ``main(config, zenoh_config, options)`` around a
transport-free layer object; this module gives it the session, presence,
publishing, counting of rejected messages and status reports::

    with ServiceShell("information", config, zenoh_conf) as shell:
        inbox = shell.inbox("entity", "particles")
        while not shell.stopping:
            item = inbox.get(timeout=0.2)
            message = shell.receive(item, ParticleSet)   # None if rejected (logged once, counted)
            ...
            shell.publish(reply)

SIGINT and SIGTERM set :attr:`ServiceShell.stopping`; the service leaves its
loop, publishes a final status and closes the session.
"""
from __future__ import annotations

import argparse
import ctypes
import logging
import os
import signal
import sys
import threading
import time

import zenoh
from threadpoolctl import threadpool_limits

from dtpf.messages import family, keys
from dtpf.messages.admission import RunShape, kind_of
from dtpf.messages.codec import MessageError, decode_for_key, encode, encode_parts
from dtpf.messages.config import RunConfig
from dtpf.messages.errors import DtpfError
from dtpf.messages.models import Component, Layer, Message, NamedCount, ParticleSet, ServiceState, Status
from dtpf.shell.shared_sets import MIN_SHARED_BYTES, SetPublisher, shared_sets
from dtpf.shell.bus import (DEFAULT_MAX_ITEMS, BusError, Inbox, Presence, PublisherCache, Received, claims_alive, flush,
                            open_session, publisher, publisher_cache, set_publisher_cache)

__all__ = ["ServiceShell", "TwinTaken", "refuse_taken_twins", "add_service_arguments", "run_service"]

#: Seconds between two periodic status reports.
STATUS_INTERVAL = 1.0
#: Seconds between two statuses of a fleet's twin once it runs (a shared service's twin, a hosted entity twin).
#: Every status of a large fleet is decoded by the recorder, the launcher and (an entity's) by both shared
#: services, so a longer interval than one twin's leaves more time to the steps (measure with
#: python -m dtpf.scripts.bench.fleet --cases 1e3:100 --solo-max 0). A starting twin
#: still says so every STATUS_INTERVAL (its status is how the shared services learn it), and every twin
#: publishes its last status when it ends.
FLEET_STATUS_INTERVAL = 5.0
#: Seconds between two log lines that sum up the rejections since the last one.
REJECTION_LOG_INTERVAL = 10.0
#: Kinds of rejection (and keys) a service tallies by name; the rest are summed under "other".
_MAX_KINDS = 100
#: Longest error text a status or a log line carries.
_MAX_ERROR_TEXT = 500
#: What a status may list as a live peer (a liveliness token of any other name is not a peer).
_LAYER_NAMES = frozenset(layer.value for layer in Layer)
#: Seconds a service has to exit, from SIGINT/SIGTERM or from the end of its run, before it
#: exits anyway (and says which step of its shutdown was slow).
EXIT_GRACE = 1.8
#: Largest JSON message a service takes (a status with its configuration is about 3 KB).
MAX_JSON_PAYLOAD = 4 << 20
#: Bytes of a reference to a set in shared memory, for its publisher's cache (about 250 in practice).
REFERENCE_SIZE = 512
#: Seconds an ending process waits for the readers on its host to take its last sets by reference.
SET_DRAIN = 3.0
#: Bytes an inbox may hold: this many of its largest payload, at least MIN_INBOX_BYTES.
_INBOX_PAYLOADS, MIN_INBOX_BYTES = 16, 64 << 20
#: Most bad messages :meth:`ServiceShell.take` skips in one call.
TAKE_BUDGET = 64
#: Bytes of a particle set's envelope besides its arrays that an inbox allows.
_ENVELOPE_ALLOWANCE = 1 << 20


def add_service_arguments(parser: argparse.ArgumentParser) -> None:
    """Options every layer service takes besides the run and Zenoh options."""
    group = parser.add_argument_group("service")
    group.add_argument("--timeout", type=float, default=2.0, metavar="SECONDS",
                       help="lockstep wait for the answer of another layer before going on without it "
                            "(default: %(default)s)")
    group.add_argument("--startup-timeout", type=float, default=20.0, metavar="SECONDS",
                       help="wait at most this long for the other layers to appear (default: %(default)s)")
    group.add_argument("--wait-for", action="append", default=None, metavar="LAYER",
                       help="layer that must be alive before the run starts (repeatable; default: the "
                            "layers this service talks to)")
    group.add_argument("--exit-with-parent", action="store_true",
                       help="stop (as on SIGTERM) when the parent process dies; the launcher sets it")
    group.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                       help="logging level on stderr (default: %(default)s)")
    default = PublisherCache()
    group.add_argument("--cache-samples", type=int, default=default.samples, metavar="N",
                       help="each publisher of this process keeps its last N messages, from which a recorder "
                            "cut off by a partition or a restart recovers what it missed (30 s of a twin at "
                            "20 steps/s by default; 0: no cache, nothing recovered) (default: %(default)s)")
    group.add_argument("--cache-mb", type=float, default=default.bytes / 2**20, metavar="MB",
                       help="... and fewer when N of its messages would weigh more than its share of this budget "
                            "of the whole process (an equal share for each twin the process serves; at most 8 MB "
                            "for one publisher): large particle sets, large fleets (default: %(default)s)")


class TwinTaken(DtpfError, RuntimeError):
    """Another entity of the twin is alive on the bus: one twin, one entity (exit code 2, one line)."""


def refuse_taken_twins(session: zenoh.Session, twins) -> None:
    """Raise :class:`TwinTaken` naming every twin of ``twins`` that another entity runs on the bus now
    (:func:`~dtpf.shell.bus.claims_alive`: a liveliness query, about a millisecond when none is)."""
    twins = list(twins)
    found = claims_alive(session, twins)
    if not found:
        return
    taken = sorted({claim.twin for claim in found})
    which = f"twin {taken[0]} is" if len(taken) == 1 else \
        f"{len(taken)} twins ({', '.join(taken[:10])}{', ...' if len(taken) > 10 else ''}) are"
    holders = "; ".join(claim.describe() for claim in found[:5]) + ("; ..." if len(found) > 5 else "")
    started = "not started" if len(twins) == 1 else f"none of this process's {len(twins)} twins is started"
    raise TwinTaken(f"{which} already run by another entity on this bus ({holders}): one twin, one entity; "
                    f"{started} (stop that entity, or give this one another --twin)")


class Tally:
    """Counts by name, for at most ``limit`` names; later names are summed under ``other``."""

    def __init__(self, limit: int = _MAX_KINDS, other: str = "other"):
        self.limit = limit
        self.other = other
        self.counts: dict[str, int] = {}

    def add(self, name: str) -> bool:
        """Count one ``name``; True if it is a name not seen before (and not folded into other)."""
        if name in self.counts:
            self.counts[name] += 1
            return False
        if len(self.counts) < self.limit:
            self.counts[name] = 1
            return True
        self.counts[self.other] = self.counts.get(self.other, 0) + 1
        return False

    def most_common(self) -> list[NamedCount]:
        return [NamedCount(name=name, count=count)
                for name, count in sorted(self.counts.items(), key=lambda item: (-item[1], item[0]))]


class ExitWatchdog:
    """Makes a process exit within :data:`EXIT_GRACE` seconds of a stop, whatever blocks it.

    Armed by SIGINT/SIGTERM (through the interpreter's wakeup fd, so it works
    even when the main thread is stuck in a call into Zenoh) or by
    :meth:`arm` at the end of a run. When the grace runs out with no
    :meth:`progress` in it, it logs which step of the shutdown (:attr:`step`)
    was still going and ends the process with ``os._exit``; a second signal
    ends it at once.
    """

    def __init__(self, log: logging.Logger, grace: float = EXIT_GRACE):
        self.log = log
        self.grace = grace
        self.step = "running"
        self.code = 130
        self._started = False
        self._settled = False
        self._last_progress = time.monotonic()

    def install(self) -> None:
        """Watch SIGINT/SIGTERM through the wakeup fd (main thread only; elsewhere :meth:`arm` alone)."""
        try:
            read_fd, write_fd = os.pipe()
            os.set_blocking(write_fd, False)
            signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
        except (ValueError, OSError):  # not the main thread: arm() alone
            return
        threading.Thread(target=self._watch_signals, args=(read_fd,), name="exit-signals", daemon=True).start()

    def _watch_signals(self, read_fd: int) -> None:
        signals = 0
        while True:
            try:
                got = os.read(read_fd, 64)
            except OSError:
                return
            if not got:
                return
            signals += len(got)
            if signals >= 2 and self._started:
                self.log.warning("second signal during shutdown (at %s): exiting now", self.step)
                self._exit(130)
            self.arm(code=130)

    def arm(self, code: int | None = None) -> None:
        """Start the grace period (once); ``code`` is the exit code if it runs out (unless :meth:`settle`d)."""
        if code is not None and not self._started and not self._settled:
            self.code = code
        if self._started:
            return
        self._started = True
        threading.Thread(target=self._count_down, name="exit-watchdog", daemon=True).start()

    def settle(self, code: int) -> None:
        """The service's work is done and ``code`` is what it earned (a recorder whose log is finished): a
        shutdown cut by the grace afterwards, in a Zenoh close that hangs, exits with it, not with 130."""
        self.code = code
        self._settled = True

    def progress(self) -> None:
        """The shutdown is moving (a recorder writing what it received): the grace starts again."""
        self._last_progress = time.monotonic()

    def _count_down(self) -> None:
        self._last_progress = time.monotonic()
        while (left := self._last_progress + self.grace - time.monotonic()) > 0:
            time.sleep(left)
        self.log.warning("did not exit within %.1f s of the stop (still at: %s); exiting now",
                         self.grace, self.step)
        self._exit(self.code)

    @staticmethod
    def _exit(code: int) -> None:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)


class _TwinLog(logging.LoggerAdapter):
    """A layer's logger whose lines start with ``twin <id>:``."""

    def __init__(self, logger: logging.Logger, twin: str):
        super().__init__(logger, {"twin": twin})
        self._prefix = f"twin {twin}: "

    def process(self, msg, kwargs):
        return self._prefix + str(msg), kwargs


class ServiceShell:
    """Session, presence, publishers, counters and status of one layer process.

    A layer that serves many twins (:mod:`dtpf.shell.fleet`) has one shell per
    twin on the process's ``session``: such a shell neither opens nor closes
    the session, installs no signal handler and runs no status thread (the
    fleet calls :meth:`tick`); its inboxes ring the fleet's ``doorbell`` with
    the twin's name.
    """

    #: Shells of this process that have not ended: the twins it serves, which share its publishers' caches.
    live = 0

    def __init__(self, layer: str, config: RunConfig, zenoh_config: zenoh.Config | None = None, *,
                 session: zenoh.Session | None = None, doorbell=None, claim: bool = False):
        self.layer = keys.check_layer(layer)
        self.config = config
        self.shared = session is not None
        log = logging.getLogger(f"dtpf.{self.layer.value}")
        #: A process that serves many twins says which twin each line is about.
        self.log = _TwinLog(log, config.twin) if self.shared else log
        self.received = 0
        self.rejected = 0
        self.last_error: str | None = None
        self.state = ServiceState.STARTING
        #: What the service is doing or waiting for, in words (in its status).
        self.detail: str | None = None
        #: Returns the observation counters of a live entity for its status (None: none).
        self.observation_counts = None
        #: The sizes a message must have to apply to this run (:meth:`expect`); None: not checked.
        self.shape: RunShape | None = None
        self.rejections = Tally()
        self.rejected_on = Tally()
        self._rejected_logged = 0
        self._rejected_trimmed = 0
        self._rejected_last_tick = 0
        self._next_rejection_log = time.monotonic() + REJECTION_LOG_INTERVAL
        self._stop = threading.Event()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._set_publishers: dict[str, SetPublisher] = {}
        #: Keys whose sets go as bytes: their ring could not be made (no room in /dev/shm).
        self._bytes_only: set[str] = set()
        self._inboxes: list[Inbox] = []
        self._lock = threading.Lock()
        self._config_json = config.model_dump_json()
        self._components = [Component(**record) for record in family.component_records(config)]
        self.doorbell = doorbell
        self.watchdog = ExitWatchdog(self.log) if not self.shared else None
        self.session = session if self.shared else open_session(zenoh_config)
        self.presence = Presence(self.session, config.twin, self.layer.value, names=_LAYER_NAMES,
                                 doorbell=doorbell)
        if claim:  # an entity: refused while another runs its twin, before it publishes anything
            try:
                refuse_taken_twins(self.session, [config.twin])
            except BaseException:
                self.presence.close()
                if not self.shared:
                    self.session.close()
                raise
            self.presence.claim(config.run_id)
        self._status_thread = threading.Thread(target=self._report, name="status", daemon=True)
        self._next_status = time.monotonic() + STATUS_INTERVAL
        self._counted = True
        ServiceShell.live += 1

    # --- lifecycle ---------------------------------------------------------------

    def __enter__(self) -> "ServiceShell":
        if not self.shared:
            for signum in (signal.SIGINT, signal.SIGTERM):
                signal.signal(signum, self._on_signal)
            self.watchdog.install()
            self._status_thread.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if getattr(self, "_counted", False):
            self._counted = False
            ServiceShell.live -= 1
        if exc is not None and not isinstance(exc, KeyboardInterrupt):
            self.state = ServiceState.FAILED
            self.last_error = f"{type(exc).__name__}: {exc}"
        elif self.state != ServiceState.FAILED:
            self.state = ServiceState.FINISHED
        if self.shared:  # one twin of a fleet: its last status, its subscribers and token; the session stays
            self.publish_status()
            for inbox in self._inboxes:
                inbox.close()
            self.presence.close()
            self._close_publishers()
            return
        # From here on the process exits within the grace, however Zenoh's close behaves.
        self.watchdog.arm(code=130 if self.stopping else (1 if self.state == ServiceState.FAILED else 0))
        self._stop.set()
        self.watchdog.step = "status thread"
        self._status_thread.join(timeout=0.5)
        self.watchdog.step = "final status"
        self.publish_status()
        self.watchdog.step = "closing subscribers"
        for inbox in self._inboxes:
            inbox.close()
        self.watchdog.step = "letting readers on this host take the last sets"
        for sets in self._set_publishers.values():
            sets.undeclare(drain=SET_DRAIN)
        self.watchdog.step = "flushing what this process published"
        flush(self.session, f"{keys.PREFIX}/{self.config.twin}/{self.layer}/@adv/flush")
        self.watchdog.step = "closing the liveliness token"
        self.presence.close()
        self.watchdog.step = "closing the Zenoh session"
        self.session.close()
        self.watchdog.step = "exiting the interpreter"

    def _close_publishers(self) -> None:
        """Undeclare the publishers (and free their caches): a fleet's twin that ends leaves nothing behind.
        A publisher of sets by reference first gives the readers on this host a moment to take its last."""
        for sets in self._set_publishers.values():
            sets.undeclare()
        self._set_publishers.clear()
        for pub in self._publishers.values():
            try:
                pub.undeclare()
            except zenoh.ZError:
                pass
        self._publishers.clear()

    def _on_signal(self, signum, frame) -> None:
        self.log.info("received %s, stopping", signal.Signals(signum).name)
        self._stop.set()

    @property
    def stopping(self) -> bool:
        """True once SIGINT or SIGTERM arrived (or :meth:`stop` was called)."""
        return self._stop.is_set()

    def stop(self) -> None:
        self._stop.set()

    def running(self) -> None:
        """Mark the service as running, declare it alive and say so at once.

        Call it once the service's inboxes exist: peers wait for the liveliness
        token before they publish, so nothing is sent before it can be received.
        """
        self.presence.announce()
        self.state = ServiceState.RUNNING
        self.publish_status()

    def expect(self, shape: RunShape) -> None:
        """Reject (count) every received message that does not fit ``shape``; call before :meth:`inbox`."""
        self.shape = shape

    # --- receive -----------------------------------------------------------------

    def inbox(self, layer: str, topic: str) -> Inbox:
        """An inbox on ``dtpf/<twin>/<layer>/<topic>`` of this twin."""
        return self.inbox_on(keys.key(self.config.twin, layer, topic))

    def inbox_on(self, key_expr: str, *more: str, payloads: int = _INBOX_PAYLOADS,
                 min_bytes: int = MIN_INBOX_BYTES, max_items: int = DEFAULT_MAX_ITEMS, recover: bool = False,
                 back_pressure: bool = False) -> Inbox:
        """An inbox on key expressions (closed with the shell), bounded to what this run's messages
        can weigh: what is bigger, or arrives while the inbox is full, is counted as rejected.
        It holds ``payloads`` of the run's largest payload, at least ``min_bytes``; ``recover``: it recovers
        what it missed from the publishers' caches; ``back_pressure``: a set by reference that finds it full
        waits in its slot, and its writer for it (:class:`~dtpf.shell.bus.Inbox`)."""
        largest = self.largest_payload()
        inbox = Inbox(self.session, key_expr, *more, max_payload=largest, max_items=max_items,
                      max_bytes=max(min_bytes, payloads * largest), on_drop=self._on_drop,
                      doorbell=self.doorbell, name=self.config.twin, recover=recover, views=True,
                      back_pressure=back_pressure)
        self._inboxes.append(inbox)
        return inbox

    def largest_payload(self) -> int:
        """The largest payload a message of this run can have (its particle set, or a JSON message)."""
        dim = self.shape.dim if self.shape is not None and self.shape.dim is not None else 16
        return max(MAX_JSON_PAYLOAD, self.config.particles * (dim + 1) * 8 + _ENVELOPE_ALLOWANCE)

    def _on_drop(self, key: str, reason: str, detail: str) -> None:
        self.reject(reason, detail, key=key)

    def receive(self, item: Received | None, expected: type[Message]) -> Message | None:
        """Decode ``item``; None if there was none, it is bad or does not fit the run (logged
        once per kind, counted), or it belongs to another run (ignored, not counted)."""
        if item is None:
            return None
        with self._lock:
            self.received += 1
        try:
            message = decode_for_key(item.key, item.payload)
            if not isinstance(message, expected):
                raise MessageError(f"expected {expected.__name__}, got {type(message).__name__}", key=item.key)
        except MessageError as error:
            self.reject(error.reason, str(error), key=item.key)
            return None
        if message.run_id != self.config.run_id:
            self.log.debug("ignored a message of run %r on %s", message.run_id, item.key)
            return None
        misfit = self.shape.misfit(message) if self.shape is not None else None
        if misfit is not None:
            self.reject(misfit.kind, misfit.detail, key=item.key)
            return None
        return message

    def take(self, inbox: Inbox, expected: type[Message], budget: int = TAKE_BUDGET) -> Message | None:
        """The next message of ``inbox`` that applies to this run, without waiting (the bad ones on the
        way are counted); None once the inbox is empty, or after ``budget`` bad ones (the inbox then rings
        its doorbell again: a fleet looks at its other twins first, so a flood of one twin's keys cannot
        hold the others up)."""
        for _ in range(budget):
            item = inbox.get(timeout=0)
            if item is None:
                return None
            message = self.receive(item, expected)
            if message is not None:
                return message
        inbox.ring()
        return None

    def reject(self, reason: str, detail: str | None = None, key: str | None = None) -> None:
        """Count a rejected message by the kind of its reason (and its key); log a kind the first
        time it is seen. ``detail``: the same with this message's numbers, for the status's last
        error; every REJECTION_LOG_INTERVAL seconds one line sums up the rejections since."""
        kind = kind_of(reason)
        with self._lock:
            self.rejected += 1
            self.last_error = (detail or reason)[:_MAX_ERROR_TEXT]
            first = self.rejections.add(kind)
            if key is not None:
                self.rejected_on.add(key[:200])
        if first:
            self.log.warning("rejected a message (%s; further ones of this kind are counted): %s",
                             kind, (detail or reason)[:_MAX_ERROR_TEXT])

    # --- publish -----------------------------------------------------------------

    def publish(self, message: Message, payload: bytes | None = None) -> None:
        """Put ``message`` on its key expression (congestion control BLOCK): ``payload`` if given (its
        bytes, made by a codec function such as :func:`~dtpf.messages.codec.encode_with_base64`), else
        ``encode(message)``."""
        key = keys.key_for(message)
        if payload is None and isinstance(message, ParticleSet) and shared_sets() and key not in self._bytes_only \
                and message.particles.nbytes + message.weights.nbytes >= MIN_SHARED_BYTES:
            parts = encode_parts(message)
            length = sum(memoryview(part).nbytes for part in parts)
            sets = self._set_publishers.get(key)
            if sets is None:  # the references are small: the cache keeps as many as it would of JSON messages
                sets = self._set_publishers[key] = SetPublisher(
                    self.session, key, self._publisher(key, REFERENCE_SIZE))
            try:
                sets.put_parts(parts, length)
                return
            except OSError as error:  # no room for the ring (a small /dev/shm): this key's sets go as bytes
                self.log.warning("cannot keep the sets of %s in shared memory (%s): sending them as bytes", key,
                                 error)
                self._bytes_only.add(key)  # its ring stays until the end: the references sent still resolve
                self._publishers.pop(key).undeclare()  # its cache was sized for references
        data = encode(message) if payload is None else payload
        self._publisher(key, len(data)).put(data)

    def _publisher(self, key: str, size: int):
        """The publisher of ``key``, declared on first use with the cache that its share of the process's
        budget holds of messages of ``size`` bytes."""
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = publisher(self.session, key,
                                                    publisher_cache().samples_for(size, ServiceShell.live))
        return pub

    def header(self, step: int) -> dict:
        """The header fields of a message of this run at ``step``."""
        return {"run_id": self.config.run_id, "twin_id": self.config.twin, "step": step}

    def status(self) -> Status:
        """This process's status now."""
        counts = self.observation_counts() if self.observation_counts is not None else None
        with self._lock:
            return Status(**self.header(0), layer=self.layer, state=self.state, pid=os.getpid(),
                          received=self.received, rejected=self.rejected, last_error=self.last_error,
                          peers_alive=sorted(self.presence.alive & _LAYER_NAMES), config_json=self._config_json,
                          detail=self.detail, components=self._components, observations=counts, queued=sum(len(inbox) for inbox in self._inboxes),
                          rejections=self.rejections.most_common(),
                          rejected_on=self.rejected_on.most_common())

    def publish_status(self) -> None:
        status = self.status()
        try:
            self.publish(status)
        except zenoh.ZError as error:  # the session may be closing
            self.log.debug("status not published: %s", error)

    def _report(self) -> None:
        while not self._stop.wait(STATUS_INTERVAL):
            self.publish_status()
            self._sum_up_rejections()

    def tick(self, now: float) -> None:
        """A fleet's shell: publish the status and sum up rejections when STATUS_INTERVAL (starting) or
        FLEET_STATUS_INTERVAL (running) has passed."""
        if now >= self._next_status:
            self._next_status = now + (STATUS_INTERVAL if self.state == ServiceState.STARTING
                                       else FLEET_STATUS_INTERVAL)
            self.publish_status()
            self._sum_up_rejections()

    def _sum_up_rejections(self) -> None:
        """Every REJECTION_LOG_INTERVAL: one line for the rejections since the last; after a flood
        (rejections that have stopped for a status interval), the freed memory goes back to the system."""
        now = time.monotonic()
        rejected = self.rejected
        if rejected != self._rejected_trimmed and rejected == self._rejected_last_tick:
            release_memory()
            self._rejected_trimmed = rejected
        self._rejected_last_tick = rejected
        if now < self._next_rejection_log:
            return
        self._next_rejection_log = now + REJECTION_LOG_INTERVAL
        # Every 10 s the free pages go back as well: the freed message buffers kept for reuse
        # (keep_large_blocks) otherwise fragment the heap, and the recorder grew 2.1 MB per
        # 1,000 steps over a 20,000-step launch (scripts/bench/soak_memory.py).
        release_memory()
        new = rejected - self._rejected_logged
        if new:
            self._rejected_logged = rejected
            kinds = ", ".join(f"{c.name}: {c.count}" for c in self.rejections.most_common()[:5])
            self.log.warning("rejected %d messages in the last %.0f s (%d in all; by kind: %s)",
                             new, REJECTION_LOG_INTERVAL, rejected, kinds)


def release_memory() -> bool:
    """Give the heap's free pages back to the system (glibc ``malloc_trim``); False elsewhere.

    A layer keeps freed blocks for reuse (:func:`keep_large_blocks`); after a
    flood of rejected messages that would keep the flood's memory for good.
    """
    try:
        return bool(ctypes.CDLL("libc.so.6").malloc_trim(0))
    except (OSError, AttributeError):
        return False


#: glibc mallopt parameters (malloc.h) and the values a layer process uses.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_TRIM_THRESHOLD, _MMAP_THRESHOLD = 1 << 30, 256 << 20


def keep_large_blocks() -> bool:
    """Let glibc reuse freed particle-set buffers instead of returning them to the OS.

    Every message is a fresh buffer of N x (d + 1) x 8 bytes (copied out of Zenoh,
    decoded, encoded, written to MCAP); above glibc's mmap threshold each one is
    mapped and unmapped again, and its pages fault on first touch. Raising the mmap
    and trim thresholds keeps them on the heap, which shortens a lockstep step at
    large N (python -m dtpf.scripts.bench.pipeline). A layer process owns its
    allocator; the in-process pipeline, which runs inside the user's program, does
    not do this. False where mallopt is not glibc's.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))


def _watch_parent(interval: float = 0.5) -> None:
    """SIGTERM this process once its parent is gone (it is then re-parented)."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(interval)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def run_service(layer: str, main, parser: argparse.ArgumentParser, argv=None) -> int:
    """Parse arguments, set up logging, call ``main(config, zenoh_config, args)``; exit codes:
    0 done, 2 bad arguments or configuration, 1 failure, 130 interrupted."""
    from dtpf.messages.config import config_from_args
    from dtpf.shell.bus import zenoh_config_from_args

    args = parser.parse_args(argv)
    # One BLAS thread per layer process. OpenBLAS's idle worker threads spin, and with the layers
    # sharing the machine they took the CPU the other layers were waiting for: spinning OpenBLAS
    # threads slowed the lockstep pipeline at large N on 2 cores.
    threadpool_limits(limits=1, user_api="blas")
    keep_large_blocks()
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format=f"%(asctime)s {layer:<11} %(levelname)s %(message)s")
    try:
        config = config_from_args(args)
        zconf = zenoh_config_from_args(args, role=layer)
    except (ValueError, BusError) as error:
        parser.exit(2, f"{parser.prog}: error: {error}\n")
    if args.cache_samples < 0 or args.cache_mb <= 0:
        parser.exit(2, f"{parser.prog}: error: --cache-samples must be 0 or more and --cache-mb more than 0, got "
                       f"{args.cache_samples} and {args.cache_mb:g}\n")
    set_publisher_cache(PublisherCache(args.cache_samples, int(args.cache_mb * 2**20)))
    if args.exit_with_parent:
        _watch_parent()
    try:
        code = main(config, zconf, args)
    except BusError as error:
        logging.getLogger(f"dtpf.{layer}").error("%s", error)
        code = 2
    except DtpfError as error:  # the user's model, file or options: one line, no traceback
        parser.exit(2, f"{parser.prog}: error: {error}\n")
    except KeyboardInterrupt:
        code = 130
    except Exception:  # a bug of ours: its traceback, exit 1
        logging.getLogger(f"dtpf.{layer}").exception("failed")
        code = 1
    # The session is closed and the log finished: leave without the interpreter's teardown, where
    # Zenoh's runtime threads have kept a process from exiting.
    logging.shutdown()
    ExitWatchdog._exit(code if isinstance(code, int) else 1)
