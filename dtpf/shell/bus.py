"""The Zenoh side of every service: configuration, session, inbox, presence.

Every dtpf process takes the same Zenoh flags (after zenoh-python's
``examples/common``)::

    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    args = parser.parse_args()
    with open_session(zenoh_config_from_args(args)) as session:
        inbox = Inbox(session, "dtpf/ungm-1/entity/particles")
        item = inbox.get(timeout=1.0)        # (key, payload bytes) or None

Defaults are safe on a shared machine: multicast and gossip scouting are off,
and a process that listens listens on loopback only unless told otherwise.
Publishers use congestion control BLOCK: the default DROP loses most of a
burst of large messages. A publisher of what a recording needs keeps its last
samples in a cache (:class:`PublisherCache`, Zenoh's advanced publisher) and
says its last sequence number on a heartbeat, so that a recorder cut off by a
partition recovers what it missed when the link comes back (:class:`Inbox`
with ``recover=True``, Zenoh's advanced subscriber), and is told what the
cache no longer held. A blocked put waits for room in the link's queue;
Zenoh closes the link (and drops what its queue holds) when none comes
within ``wait_before_close``. A router waits 5 s, Zenoh's default; every
other process waits :data:`SERVICE_WAIT_BEFORE_CLOSE` (60 s) unless its
configuration says otherwise, so that a service whose router is stalled
(a router blocked on the queue of a link that went dead, which it closes
after its own 5 s) waits for the router instead of dropping its own queue.
"""
from __future__ import annotations

import argparse
import json
import queue
import os
import re
import socket
import threading
import time
from dataclasses import dataclass, replace

import zenoh
import zenoh.ext

from dtpf.messages.errors import DtpfError
from dtpf.shell.shared_sets import SetDropped, SetLost, SetResolver
from dtpf.shell.slots import MAX_REFERENCE, SlotError, is_reference

__all__ = [
    "BusError",
    "add_zenoh_arguments",
    "zenoh_config",
    "zenoh_config_from_args",
    "open_session",
    "Inbox",
    "Doorbell",
    "Presence",
    "Claim",
    "Claims",
    "claims_alive",
    "publisher",
    "PublisherCache",
    "PUBLISHER_MAX_BYTES",
    "publisher_cache",
    "set_publisher_cache",
    "free_port",
    "flush",
]

MODES = ("peer", "client", "router")


class BusError(DtpfError, RuntimeError):
    """Zenoh could not be configured or opened; the message says which endpoint or key."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """The Zenoh flags every dtpf process accepts."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", "-m", choices=MODES, default=None,
                       help="Zenoh session mode (default: client when --connect is given without "
                            "--listen, else peer)")
    group.add_argument("--connect", "-e", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    group.add_argument("--listen", "-l", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable; "
                            "default for peers and routers: tcp/127.0.0.1:0)")
    group.add_argument("--zenoh-config", metavar="FILE",
                       help="Zenoh JSON5 configuration file (TLS, access control, ...); "
                            "the flags above override its mode and endpoints")
    group.add_argument("--cfg", action="append", default=[], metavar="KEY:JSON",
                       help="set one Zenoh configuration key, e.g. "
                            "'transport/shared_memory/enabled:false' (repeatable)")
    group.add_argument("--secure", metavar="DIR",
                       help="a folder made by 'dtpf secure init' (DIR, DIR/tls or DIR/usrpwd): connect with "
                            "the role's certificate or password, through a router that enforces its access "
                            "control; --connect then gives the router's tls/ (or tcp/) endpoint")
    group.add_argument("--role", metavar="NAME",
                       help="the role of the secure folder to act as (default: this process's layer; "
                            "entity, information, system, recorder, sensor or viewer)")


#: Where Zenoh keeps how long a BLOCK put waits for room before it closes the link (microseconds).
WAIT_BEFORE_CLOSE_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"
#: Zenoh's default of that wait (5 s), which routers keep.
ZENOH_WAIT_BEFORE_CLOSE = 5_000_000
#: The wait of every process that is not a router (60 s): longer than a router's, see the module docstring.
SERVICE_WAIT_BEFORE_CLOSE = 60_000_000
#: How a process that lost a link to an endpoint it connects to tries again: every half second (Zenoh's
#: default backs off to 4 s, so a router found its peer up to 4 s after a partition ended and the shared
#: services' twins stayed degraded that long). An attempt is one TCP connect to one endpoint.
RECONNECT = {"period_init_ms": 250, "period_max_ms": 500, "period_increase_factor": 2}


def zenoh_config(*, mode: str | None = None, connect: list[str] = (), listen: list[str] = (),
                 config_file: str | None = None, cfg: list[str] = (), secure=None,
                 role: str | None = None) -> zenoh.Config:
    """A Zenoh configuration from dtpf's flags; BusError names a bad file, key or value.

    ``secure`` (a :class:`dtpf.shell.secure.SecureDir` or its path) starts from
    the configuration of ``role`` in that folder ("router" for the router's):
    its certificates or password and, for the router, its access control; the
    endpoints given here replace the file's and must use the folder's protocol.
    """
    if secure is not None:
        if config_file:
            raise BusError("--secure and --zenoh-config both give a configuration: use one")
        config, mode = _secure_config(secure, role, mode, [*connect, *listen])
    elif config_file:
        try:
            config = zenoh.Config.from_file(config_file)
        except Exception as error:  # zenoh raises ZError or OSError
            raise BusError(f"cannot read Zenoh config file {config_file!r}: {error}") from None
    else:
        config = zenoh.Config()
    if mode is None:
        mode = "client" if connect and not listen else "peer"
    if mode not in MODES:
        raise BusError(f"unknown Zenoh mode {mode!r}; expected one of {', '.join(MODES)}")
    if mode == "client" and listen:
        raise BusError("a Zenoh client does not listen: drop --listen or use --mode peer")
    settings = {
        "mode": mode,
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
    }
    if connect:
        settings["connect/endpoints"] = list(connect)
    if mode != "client" and (listen or secure is None):  # a secure router listens where its file says
        settings["listen/endpoints"] = list(listen) or ["tcp/127.0.0.1:0"]
    for item in cfg:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise BusError(f"--cfg expects KEY:JSON, got {item!r}")
        try:
            settings[key] = json.loads(value)
        except json.JSONDecodeError:
            settings[key] = value  # a bare string
    if "connect/retry" not in settings and not any(key.startswith("connect/retry/") for key in settings) \
            and config.get_json("connect/retry") == "null":
        settings["connect/retry"] = RECONNECT
    if mode != "router" and WAIT_BEFORE_CLOSE_KEY not in settings \
            and json.loads(config.get_json(WAIT_BEFORE_CLOSE_KEY)) == ZENOH_WAIT_BEFORE_CLOSE:
        settings[WAIT_BEFORE_CLOSE_KEY] = SERVICE_WAIT_BEFORE_CLOSE
    for key, value in settings.items():
        try:
            config.insert_json5(key, json.dumps(value))
        except Exception as error:
            raise BusError(f"bad Zenoh configuration {key} = {value!r}: {error}") from None
    return config


def _secure_config(secure, role: str | None, mode: str | None, endpoints: list[str]) -> tuple[zenoh.Config, str]:
    """The Zenoh configuration of ``role`` in a secure folder, and the mode it runs in."""
    from dtpf.shell.secure import SecureError, open_secure_dir, role_config

    try:
        folder = secure if hasattr(secure, "kind") else open_secure_dir(secure)
        if role is None:
            raise SecureError("--secure needs --role NAME (one of " + ", ".join(folder.roles) + ")")
        for endpoint in endpoints:
            folder.check_endpoint(endpoint)
        text = role_config(folder, role)
    except SecureError as error:
        raise BusError(str(error)) from None
    try:
        config = zenoh.Config.from_json5(text)
    except Exception as error:
        raise BusError(f"Zenoh refuses {folder.file_of(role)}: {error}") from None
    return config, mode or ("router" if role == "router" else "client")


def zenoh_config_from_args(args: argparse.Namespace, role: str | None = None) -> zenoh.Config:
    """:func:`zenoh_config` from the flags of :func:`add_zenoh_arguments`; ``role``: the default
    role of ``--secure`` (the process's layer)."""
    return zenoh_config(mode=args.mode, connect=args.connect, listen=args.listen,
                        config_file=args.zenoh_config, cfg=args.cfg, secure=getattr(args, "secure", None),
                        role=getattr(args, "role", None) or role)


#: Where Zenoh's errors name its Rust sources (`` at /.../zenoh-link-tcp/src/unicast.rs:338``).
_RUST_SOURCE = re.compile(r"\s+at \S+\.rs:\d+\.?")


def zenoh_reason(text: str) -> str:
    """Zenoh's error text without the Rust source paths it names."""
    return _RUST_SOURCE.sub("", text).strip()


def open_session(config: zenoh.Config, in_use_hint: str | None = None) -> zenoh.Session:
    """Open a Zenoh session; a busy port or a bad endpoint becomes a BusError naming it, in one line
    without Zenoh's Rust source paths. ``in_use_hint``: how the caller's user picks another port (by
    default: another port in the --listen endpoint)."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as error:
        text = zenoh_reason(str(error))
        if "Address already in use" in text or "in use" in text:
            bound = re.search(r"bound to (\S+):\s", text)
            os_error = re.search(r"Address already in use( \(os error \d+\))?", text)
            where = f" on {bound.group(1)}" if bound else ""
            reason = f" ({os_error.group(0)})" if os_error else f" ({text})"
            hint = in_use_hint or "give --listen an endpoint with another port (tcp/HOST:PORT)"
            raise BusError(f"cannot listen{where}: the port is already in use by another program{reason}; "
                           f"{hint}, or stop the program that holds it") from None
        raise BusError(f"cannot open Zenoh session: {text}") from None


@dataclass(frozen=True)
class PublisherCache:
    """How much a publisher keeps for subscribers that missed it (Zenoh's ``CacheConfig``).

    A publisher keeps its last ``samples`` samples (default 600: 30 s of a twin at 20 steps/s, 60 s at 10),
    fewer when they would weigh more than its share of the process's ``bytes`` (:meth:`samples_for`): the
    process's budget (default 256 MiB) split evenly between the twins it serves, a quarter of a twin's for
    each of its publishers (a twin has two to five), at most :data:`PUBLISHER_MAX_BYTES` (8 MiB) for one.
    One or a few twins: a particle set of N = 1000 in one dimension (16 kB) keeps about 500, one of N = 1e5
    (1.6 MB) keeps 5, the JSON topics (estimates of under a kB, statuses of 3 kB) their 600. An entity
    hosting 100 twins: 655 kB a publisher, about 40 such sets, the estimates still 600. So a process never holds
    much more than its budget, whatever the fleet; the twins it serves when a publisher is declared set that
    publisher's share. What a partition outlasts is lost to a recorder on the other side of it; the recorder
    says so. ``heartbeat``: seconds between two announcements of a publisher's last sequence number (sent only
    when it changed), by which a subscriber notices missed samples even when no new one comes. ``samples = 0``:
    plain publishers, no cache.
    """

    samples: int = 600
    bytes: int = 256 << 20
    heartbeat: float = 1.0

    def samples_for(self, payload_size: int, twins: int = 1) -> int:
        """How many samples of ``payload_size`` bytes a publisher of a process serving ``twins`` twins keeps
        (at least 1 when it keeps any)."""
        if self.samples <= 0:
            return 0
        share = min(PUBLISHER_MAX_BYTES, self.bytes // max(1, twins) // 4)
        return max(1, min(self.samples, share // max(1, payload_size)))


#: Most bytes one publisher's cache holds, however large the process's budget.
PUBLISHER_MAX_BYTES = 8 << 20


#: The cache of this process's publishers (:func:`set_publisher_cache`; the services' --cache-* options).
_CACHE = [PublisherCache()]


def publisher_cache() -> PublisherCache:
    """The cache this process's publishers keep."""
    return _CACHE[0]


def set_publisher_cache(cache: PublisherCache) -> None:
    """Set the cache of the publishers this process declares from now on."""
    _CACHE[0] = cache


def publisher(session: zenoh.Session, key: str, cache_samples: int = 0):
    """A publisher that blocks instead of dropping when the network is congested.

    ``cache_samples`` > 0: an advanced publisher keeping that many of its last samples, with sample-miss
    detection (a heartbeat every :attr:`PublisherCache.heartbeat` seconds) and publisher detection (a
    liveliness token under ``<key>/@adv/pub``, which a recorder's or a fleet service's history query follows),
    so that an :class:`Inbox` with ``recover`` or ``history`` gets what it missed.
    """
    if cache_samples <= 0:
        return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    return zenoh.ext.declare_advanced_publisher(
        session, key, congestion_control=zenoh.CongestionControl.BLOCK,
        cache=zenoh.ext.CacheConfig(max_samples=cache_samples),
        sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None,
                                                            sporadic_heartbeat=publisher_cache().heartbeat),
        publisher_detection=True)


#: Seconds :func:`flush` waits, at most, for the router's answer.
FLUSH_TIMEOUT = 1.0


def flush(session: zenoh.Session, key: str, timeout: float = FLUSH_TIMEOUT) -> bool:
    """Wait until what this session has put has reached its router: a query on ``key`` (which no queryable
    answers) travels behind the puts on the same link and priority, and the router answers it once it has
    taken them. A process that closes its session at once after its last put could otherwise lose the puts
    still queued (seen under load: a sensor's last three observations). ``key`` must be one the session may
    query (a twin's ``.../@adv/...`` key under access control). False if no answer came within ``timeout``."""
    try:
        replies = session.get(key, timeout=timeout)
        for _ in replies:
            pass
        return True
    except zenoh.ZError:
        return False


@dataclass(frozen=True)
class Received:
    """One received sample: its key expression and a private copy of its payload.

    From an inbox with ``recover``: ``source`` names the publisher (its Zenoh entity id, None for a plain
    publisher) and ``sn`` is the sample's sequence number from it (consecutive unless samples were lost); an
    item with ``missed`` > 0 is no sample but Zenoh's news that ``missed`` samples of ``source`` could not be
    recovered (``key`` and ``payload`` empty), which may come after samples that followed the gap.
    """

    key: str
    payload: bytes
    source: str | None = None
    missed: int = 0
    sn: int | None = None


#: Largest payload an inbox takes by default (a particle set of 1e6 particles in 16 dimensions fits).
DEFAULT_MAX_PAYLOAD = 256 << 20
#: Most samples and bytes an inbox holds by default before it drops what arrives.
DEFAULT_MAX_ITEMS = 4096
DEFAULT_MAX_BYTES = 1 << 30


class Doorbell:
    """Rung by inboxes when a sample arrives, so one thread can wait on many inboxes (a fleet's twins).

    :meth:`wait` returns the names rung since the last call (an inbox rings with
    its ``name``), at once if any; the set holds each name once, so a flood
    cannot grow it beyond the number of inboxes.
    """

    def __init__(self):
        self._rung: set[str] = set()
        self._lock = threading.Lock()
        self._event = threading.Event()

    def ring(self, name: str) -> None:
        with self._lock:
            self._rung.add(name)
        if not self._event.is_set():  # Event.set takes a lock and notifies even when nobody waits
            self._event.set()

    def wait(self, timeout: float) -> set[str]:
        """The names rung since the last call, waiting up to ``timeout`` seconds for one."""
        self._event.wait(timeout)
        with self._lock:
            self._event.clear()
            rung, self._rung = self._rung, set()
        return rung


class Inbox:
    """Subscribers (one per key expression) whose samples wait in one queue until :meth:`get` takes them.

    Zenoh calls the callback on its own thread; the callback only copies the
    payload and enqueues it (nothing blocking or published in a callback).

    The queue is bounded: a payload above ``max_payload`` bytes, or one that
    arrives while ``max_items`` samples or ``max_bytes`` bytes wait, is dropped
    (a flood cannot grow the process without bound) and reported to
    ``on_drop(key, reason, detail)`` if given; :attr:`dropped` counts them.
    A ``doorbell`` (:class:`Doorbell`) is rung with ``name`` for every sample queued.

    ``history`` (a count) and ``recover`` make the subscribers Zenoh's advanced subscribers, which work
    with the cache of :func:`publisher`: ``history`` asks every publisher found (at the start, and when
    one appears again after a partition or a restart) for its last ``history`` samples; ``recover``
    asks every publisher for the whole of its cache when it appears, recovers the samples missed in a
    gap of its sequence numbers (seen on its next sample or heartbeat) and queues, for what its cache no
    longer held, a :class:`Received` with ``missed`` set. Samples of one publisher are queued in the
    order it published them, recovered or not, with their sequence numbers.

    A particle set by reference (:mod:`dtpf.shell.shared_sets`) of this host waits in its slot, to be
    read where it lies, until its publisher's next set arrives; then it is copied out, so that a reader
    that falls behind, or whose loop is stuck, holds a publisher up by two sets at most, and drops sets
    once full.
    With ``back_pressure`` (the recorder, which must lose nothing) a set that finds the inbox full stays
    in its slot instead, and its writer waits.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, *more_key_exprs: str,
                 max_payload: int = DEFAULT_MAX_PAYLOAD, max_items: int = DEFAULT_MAX_ITEMS,
                 max_bytes: int = DEFAULT_MAX_BYTES, on_drop=None, doorbell: Doorbell | None = None,
                 name: str = "", history: int | None = None, recover: bool = False, views: bool = False,
                 back_pressure: bool = False):
        self.key_expr = key_expr
        self.views = views
        self.back_pressure = back_pressure
        self._sets = SetResolver(session)
        self.doorbell = doorbell
        self.name = name
        self.max_payload = max_payload
        self.max_items = max_items
        self.max_bytes = max_bytes
        self.on_drop = on_drop
        self.dropped = 0
        self._queued_bytes = 0
        self._lock = threading.Lock()
        # queue.Queue, not SimpleQueue: CPython 3.11's SimpleQueue.get(timeout) waits for the next item, past its
        # timeout, when a signal handler runs beyond the timeout's end during the wait (a stopped service's main
        # loop then hung until the exit watchdog ended it with code 130); Queue's wait keeps its deadline.
        self._queue: queue.Queue[Received] = queue.Queue()
        self.recover = recover
        self._misses = []
        self._subscribers = [self._subscribe(session, k, history, recover) for k in (key_expr, *more_key_exprs)]

    def _subscribe(self, session: zenoh.Session, key_expr: str, history: int | None, recover: bool):
        if history is None and not recover:
            return session.declare_subscriber(key_expr, self._on_sample)
        subscriber = zenoh.ext.declare_advanced_subscriber(
            session, key_expr, self._on_sample,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=None if recover else history),
            recovery=zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True) if recover else None)
        if recover:
            self._misses.append(subscriber.sample_miss_listener(self._on_miss))
        return subscriber

    def _on_miss(self, miss) -> None:
        """Samples of a publisher that its cache no longer held: queued as news, never dropped for room
        (one item per gap, not per sample)."""
        self._queue.put(Received("", b"", str(miss.source), int(miss.nb)))
        if self.doorbell is not None:
            self.doorbell.ring(self.name)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        size = len(sample.payload)
        key = str(sample.key_expr)
        if size > self.max_payload:
            self._drop(key, "payload larger than the inbox takes",
                       f"a payload of {size} bytes on {key[:200]}, at most {self.max_payload} are taken")
            return
        payload = sample.payload.to_bytes()
        reference = self._sets.local(payload) if size <= MAX_REFERENCE and is_reference(payload) else None
        if not self._reserve(size):
            if reference is not None:
                self._sets.skip(reference)
            self._drop_full(key)
            return
        if reference is not None:
            self._sets.arrive(reference, payload, self._room, self.back_pressure, lambda: self._drop_full(key))
        source = sn = None
        if self.recover:
            info = sample.source_info
            if info is not None:
                source, sn = str(info.source_id), int(info.source_sn)
        self._queue.put(Received(key, payload, source, 0, sn))
        if self.doorbell is not None:
            self.doorbell.ring(self.name)

    def _reserve(self, size: int) -> bool:
        """Room for one more item of ``size`` bytes (taken if there is)."""
        with self._lock:
            if self._queue.qsize() >= self.max_items or not self._room(size):
                return False
            self._queued_bytes += size
            return True

    def _room(self, size: int) -> bool:
        """Whether ``size`` more bytes fit with what waits (sets copied out of their slots included)."""
        return self._queued_bytes + self._sets.copied_bytes + size <= self.max_bytes

    def _drop_full(self, key: str) -> None:
        self._drop(key, "inbox full", f"inbox of {self.key_expr} full ({self.max_items} samples or "
                                      f"{self.max_bytes} bytes waiting): dropped a sample on {key[:200]}")

    def _drop(self, key: str, reason: str, detail: str) -> None:
        with self._lock:
            self.dropped += 1
        if self.on_drop is not None:
            self.on_drop(key, reason, detail)

    def ring(self) -> None:
        """Ring the doorbell (if any) as if a sample had arrived: there is more to take."""
        if self.doorbell is not None and len(self):
            self.doorbell.ring(self.name)

    def get(self, timeout: float | None = None) -> Received | None:
        """The next sample, waiting up to ``timeout`` seconds (None: forever); None on timeout.

        A particle set sent by reference (:mod:`dtpf.shell.shared_sets`) comes as its payload: with
        ``views``, a read-only view of the publisher's shared memory, valid until the next :meth:`get`
        (whoever keeps its arrays longer copies them); without, bytes. One that cannot be had is reported
        to ``on_drop`` (and, with ``recover``, comes as a :class:`Received` with ``missed`` = 1)."""
        self._sets.release()
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                item = self._queue.get(timeout=None if deadline is None else max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return None
            with self._lock:
                self._queued_bytes -= len(item.payload)
            if item.missed or not is_reference(item.payload):
                return item
            try:
                return replace(item, payload=self._sets.resolve(item.key, item.payload, self.views))
            except SetDropped:
                continue
            except (SlotError, SetLost) as error:
                self._drop(item.key, "particle set by reference not had", f"on {item.key[:200]}: {error}")
                if self.recover and isinstance(error, SetLost):
                    return Received("", b"", item.source, 1, item.sn)

    def __len__(self) -> int:
        return self._queue.qsize()

    def close(self) -> None:
        for handle in (*self._misses, *self._subscribers):
            try:
                handle.undeclare()
            except zenoh.ZError:
                pass
        self._sets.close()


class Presence:
    """This process's liveliness token (declared by :meth:`announce`), and the live peers of its twin.

    Tokens are ``dtpf/<twin>/<layer>/alive``; a peer that dies (even SIGKILL)
    disappears within a few milliseconds.
    """

    def __init__(self, session: zenoh.Session, twin: str, layer: str, names=None, doorbell: Doorbell | None = None):
        self.twin = twin
        self.layer = layer
        #: Rung with the twin's id when a peer comes or goes (a thread that waits on inboxes sees it).
        self.doorbell = doorbell
        #: The layer names that count (None: any); a token of another name is ignored, so a flood of
        #: made-up names cannot grow the set.
        self.names = None if names is None else frozenset(names)
        self._alive: set[str] = set()
        self._seen: set[str] = set()
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._session = session
        self._token = None
        self._claim = None
        self._watch = session.liveliness().declare_subscriber(f"dtpf/{twin}/*/alive", self._on_token,
                                                              history=True)

    def announce(self) -> None:
        """Declare this process alive. Call it after declaring the subscribers, so that a peer
        that waits for this token never publishes before this process listens."""
        if self._token is None:
            self._token = self._session.liveliness().declare_token(f"dtpf/{self.twin}/{self.layer}/alive")

    def _on_token(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        if len(parts) != 4 or (self.names is not None and parts[2] not in self.names):
            return
        with self._changed:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(parts[2])
                self._seen.add(parts[2])
            else:
                self._alive.discard(parts[2])
            self._changed.notify_all()
        if self.doorbell is not None:
            self.doorbell.ring(self.twin)

    @property
    def alive(self) -> set[str]:
        """Layers of this twin with a live token (this process's own included)."""
        with self._lock:
            return set(self._alive)

    @property
    def seen(self) -> set[str]:
        """Layers of this twin that have had a live token at some time, gone since or not: a peer that came
        and went between two looks at :attr:`alive` is still known to have been there."""
        with self._lock:
            return set(self._seen)

    def wait_for(self, layers, timeout: float) -> set[str]:
        """Wait until every layer in ``layers`` is alive; returns those still missing."""
        wanted = set(layers)
        with self._changed:
            self._changed.wait_for(lambda: wanted <= self._alive, timeout=timeout)
            return wanted - self._alive

    def claim(self, run_id: str) -> None:
        """Declare this process's claim on the twin (:class:`Claim`): an entity does it as soon as it has
        found no other entity of its twin alive (:func:`claims_alive`), before it publishes anything."""
        if self._claim is None:
            self._claim = self._session.liveliness().declare_token(Claim.mine(self.twin, run_id).key)

    def close(self) -> None:
        for handle in (self._watch, self._token, self._claim):
            if handle is None:
                continue
            try:
                handle.undeclare()
            except zenoh.ZError:
                pass


#: Characters a key chunk cannot hold (a host name is put in one).
_NOT_IN_CHUNK = re.compile(r"[^A-Za-z0-9_.-]")
#: Seconds an entity waits, at most, for the answer to its liveliness query at start-up (the router answers at
#: once; the bound is for a router that does not answer).
CLAIM_QUERY_TIMEOUT = 2.0
#: Seconds a twin found alive is looked at again before the entity refuses to start: the token of a
#: predecessor that has just died goes when its router has seen the connection close.
CLAIM_GRACE = 1.0
#: Most claims a :class:`Claims` keeps (a flood of made-up tokens cannot grow it).
MAX_CLAIMS = 100


def _this_host() -> str:
    """This machine's name as a key chunk."""
    return _NOT_IN_CHUNK.sub("_", socket.gethostname())[:64] or "host"


@dataclass(frozen=True)
class Claim:
    """An entity's claim on its twin: the liveliness token ``dtpf/<twin>/entity/claim/<run>/<host>/<pid>``.

    One twin, one entity: an entity declares it from its start to its end, and refuses to start while another
    entity of its twin has one (or an ``entity/alive`` token, which carries no run or process: then
    ``run_id``, ``host`` and ``pid`` are None).
    """

    twin: str
    run_id: str | None = None
    host: str | None = None
    pid: int | None = None

    @classmethod
    def mine(cls, twin: str, run_id: str) -> "Claim":
        return cls(twin, run_id, _this_host(), os.getpid())

    @property
    def key(self) -> str:
        return f"dtpf/{self.twin}/entity/claim/{self.run_id}/{self.host}/{self.pid}"

    @classmethod
    def of_key(cls, key: str) -> "Claim | None":
        """The claim a token's key says, None if it is none (an ``entity/alive`` token is a claim without a
        run or process)."""
        parts = str(key).split("/")
        if len(parts) == 4 and parts[0] == "dtpf" and parts[2:] == ["entity", "alive"]:
            return cls(parts[1])
        if len(parts) == 7 and parts[0] == "dtpf" and parts[2:4] == ["entity", "claim"] and parts[6].isdigit():
            return cls(parts[1], parts[4], parts[5], int(parts[6]))
        return None

    def describe(self) -> str:
        """'twin T: run R, process P on H' (or 'twin T: an entity alive' for a token without a claim)."""
        if self.pid is None:
            return f"twin {self.twin}: an entity alive"
        return f"twin {self.twin}: run {self.run_id}, process {self.pid} on {self.host}"


def claims_alive(session: zenoh.Session, twins, timeout: float = CLAIM_QUERY_TIMEOUT,
                 grace: float = CLAIM_GRACE) -> list[Claim]:
    """The claims of other entities on ``twins`` alive on the bus, found by a liveliness query of each twin
    (answered by the router from what it knows, in about a millisecond; at most ``timeout`` seconds).

    A twin found alive is asked again for up to ``grace`` seconds: a predecessor that has just died (a
    restarted entity's) leaves its token until its router has seen its connection close. What the session
    cannot reach (a peer not yet connected, the other side of a partition) is not found: a competitor that
    appears later is for the launcher to see (:class:`Claims`).
    """
    deadline = time.monotonic() + grace
    wanted = list(dict.fromkeys(twins))
    while True:
        found = _query_claims(session, wanted, timeout)
        if not found or time.monotonic() >= deadline:
            return found
        time.sleep(0.05)
        wanted = sorted({claim.twin for claim in found})


def _query_claims(session: zenoh.Session, twins: list[str], timeout: float) -> list[Claim]:
    pending = [session.liveliness().get(f"dtpf/{twin}/entity/**", timeout=timeout) for twin in twins]
    found: set[Claim] = set()
    for replies in pending:  # every query is under way: the waits overlap
        for reply in replies:
            if reply.ok is not None:
                claim = Claim.of_key(reply.ok.key_expr)
                if claim is not None and claim.twin in twins:
                    found.add(claim)
    # A claim of this process is not another's.
    others = {claim for claim in found if claim.pid != os.getpid() or claim.host != _this_host()}
    # An entity/alive token beside a claim of the same twin is that entity's: named once, by its claim.
    claimed = {claim.twin for claim in others if claim.pid is not None}
    return sorted((c for c in others if c.pid is not None or c.twin not in claimed),
                  key=lambda c: (c.twin, c.run_id or "", c.host or "", c.pid or 0))


class Claims:
    """The claims on a twin as they come and go (a liveliness subscriber, with the tokens already there):
    a launcher sees every entity of its twin, its own and any other, through the run.

    ``twin`` may be a key chunk pattern (``line-1-*``, a fleet's twins); ``twins`` then names the twins
    whose claims are kept.
    """

    def __init__(self, session: zenoh.Session, twin: str, twins=None):
        self.twin = twin
        self.twins = None if twins is None else frozenset(twins)
        self._lock = threading.Lock()
        #: Every claim seen during the run, gone since or not (at most MAX_CLAIMS).
        self.seen: list[Claim] = []
        self._watch = session.liveliness().declare_subscriber(f"dtpf/{twin}/entity/claim/**", self._on_token,
                                                              history=True)

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        claim = Claim.of_key(sample.key_expr)
        if claim is None or claim.twin != self.twin and (self.twins is None or claim.twin not in self.twins):
            return
        with self._lock:
            if claim not in self.seen and len(self.seen) < MAX_CLAIMS:
                self.seen.append(claim)

    def others(self, pids) -> list[Claim]:
        """The claims seen that are not of the processes ``pids`` of this host."""
        host = _this_host()
        with self._lock:
            return [claim for claim in self.seen if claim.host != host or claim.pid not in set(pids)]

    def close(self) -> None:
        try:
            self._watch.undeclare()
        except zenoh.ZError:
            pass
