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

from messages import keys
from messages.bus import BusError, Inbox, Presence, Received, open_session, publisher
from messages.codec import MessageError, decode_for_key, encode
from messages.config import RunConfig
from messages.models import Layer, Message, ServiceState, Status

__all__ = ["ServiceShell", "add_service_arguments", "run_service"]

#: Seconds between two periodic status reports.
STATUS_INTERVAL = 1.0
#: Distinct reasons of rejection a service logs (each once); the rest are only counted.
_MAX_REASONS = 100
#: Longest error text a status or a log line carries.
_MAX_ERROR_TEXT = 500
#: What a status may list as a live peer (a liveliness token of any other name is not a peer).
_LAYER_NAMES = frozenset(layer.value for layer in Layer)


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


class ServiceShell:
    """Session, presence, publishers, counters and status of one layer process."""

    def __init__(self, layer: str, config: RunConfig, zenoh_config: zenoh.Config):
        self.layer = keys.check_layer(layer)
        self.config = config
        self.log = logging.getLogger(f"dtpf.{self.layer.value}")
        self.received = 0
        self.rejected = 0
        self.last_error: str | None = None
        self.state = ServiceState.STARTING
        #: What the service is doing or waiting for, in words (in its status).
        self.detail: str | None = None
        #: Returns the observation counters of a live entity for its status (None: none).
        self.observation_counts = None
        self._seen_reasons: set[str] = set()
        self._stop = threading.Event()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._inboxes: list[Inbox] = []
        self._lock = threading.Lock()
        self._config_json = config.model_dump_json()
        self.session = open_session(zenoh_config)
        self.presence = Presence(self.session, config.twin, self.layer.value)
        self._status_thread = threading.Thread(target=self._report, name="status", daemon=True)

    # --- lifecycle ---------------------------------------------------------------

    def __enter__(self) -> "ServiceShell":
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self._on_signal)
        self._status_thread.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is not None and not isinstance(exc, KeyboardInterrupt):
            self.state = ServiceState.FAILED
            self.last_error = f"{type(exc).__name__}: {exc}"
        elif self.state != ServiceState.FAILED:
            self.state = ServiceState.FINISHED
        self._stop.set()
        self._status_thread.join(timeout=2.0)
        self.publish_status()
        for inbox in self._inboxes:
            inbox.close()
        self.presence.close()
        self.session.close()

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

    # --- receive -----------------------------------------------------------------

    def inbox(self, layer: str, topic: str) -> Inbox:
        """An inbox on ``dtpf/<twin>/<layer>/<topic>`` of this twin."""
        return self.inbox_on(keys.key(self.config.twin, layer, topic))

    def inbox_on(self, key_expr: str) -> Inbox:
        """An inbox on any key expression (closed with the shell)."""
        inbox = Inbox(self.session, key_expr)
        self._inboxes.append(inbox)
        return inbox

    def receive(self, item: Received | None, expected: type[Message]) -> Message | None:
        """Decode ``item``; None if there was none, it is bad (logged once per reason,
        counted), or it belongs to another run (ignored, not counted)."""
        if item is None:
            return None
        with self._lock:
            self.received += 1
        try:
            message = decode_for_key(item.key, item.payload)
            if not isinstance(message, expected):
                raise MessageError(f"expected {expected.__name__}, got {type(message).__name__}", key=item.key)
        except MessageError as error:
            self.reject(error.reason, str(error))
            return None
        if message.run_id != self.config.run_id:
            self.log.debug("ignored a message of run %r on %s", message.run_id, item.key)
            return None
        return message

    def reject(self, reason: str, detail: str | None = None) -> None:
        """Count a rejected message; log its reason the first time it is seen.

        ``detail``: the same with this message's numbers, for the status's
        last error (the log keeps to one line per ``reason``).
        """
        with self._lock:
            self.rejected += 1
            self.last_error = (detail or reason)[:_MAX_ERROR_TEXT]
            first = reason not in self._seen_reasons and len(self._seen_reasons) <= _MAX_REASONS
            if first:
                self._seen_reasons.add(reason)
        if first and len(self._seen_reasons) > _MAX_REASONS:
            self.log.warning("rejected messages for more than %d reasons: further new reasons are counted, "
                             "not logged", _MAX_REASONS)
        elif first:
            self.log.warning("rejected a message: %s", (detail or reason)[:_MAX_ERROR_TEXT])

    # --- publish -----------------------------------------------------------------

    def publish(self, message: Message) -> None:
        """Encode ``message`` and put it on its key expression (congestion control BLOCK)."""
        key = keys.key_for(message)
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = publisher(self.session, key)
        pub.put(encode(message))

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
                          detail=self.detail, observations=counts)

    def publish_status(self) -> None:
        status = self.status()
        try:
            self.publish(status)
        except zenoh.ZError as error:  # the session may be closing
            self.log.debug("status not published: %s", error)

    def _report(self) -> None:
        while not self._stop.wait(STATUS_INTERVAL):
            self.publish_status()

    def wait_for_layers(self, layers, timeout: float) -> None:
        """Wait until ``layers`` are alive; log the ones still missing (the run goes on)."""
        missing = self.presence.wait_for(layers, timeout)
        if missing:
            self.log.warning("going on without %s: not alive after %.1f s", ", ".join(sorted(missing)), timeout)


#: glibc mallopt parameters (malloc.h) and the values a layer process uses.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_TRIM_THRESHOLD, _MMAP_THRESHOLD = 1 << 30, 256 << 20


def keep_large_blocks() -> bool:
    """Let glibc reuse freed particle-set buffers instead of returning them to the OS.

    Every message is a fresh buffer of N x (d + 1) x 8 bytes (copied out of Zenoh,
    decoded, encoded, written to MCAP); above glibc's mmap threshold each one is
    mapped and unmapped again, and its pages fault on first touch (PERF-ANCHORS.md,
    "Copy floor"). Raising the mmap and trim thresholds keeps them on the heap: the
    lockstep step at N = 1e5 went from 14.5 to 11.4 ms (bench_pipeline, 2 cores,
    with the recorder). A layer process owns its
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
    from messages.bus import zenoh_config_from_args
    from messages.config import config_from_args

    args = parser.parse_args(argv)
    # One BLAS thread per layer process. OpenBLAS's idle worker threads spin, and with the layers
    # sharing the machine they took the CPU the other layers were waiting for: at N = 1e5 on 2 cores
    # a lockstep step cost 22.8 ms with the default 2 threads and 13.9 ms with 1 (bench_pipeline).
    threadpool_limits(limits=1, user_api="blas")
    keep_large_blocks()
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format=f"%(asctime)s {layer:<11} %(levelname)s %(message)s")
    try:
        config = config_from_args(args)
        zconf = zenoh_config_from_args(args)
    except (ValueError, BusError) as error:
        parser.exit(2, f"{parser.prog}: error: {error}\n")
    if args.exit_with_parent:
        _watch_parent()
    from entity.model_ref import ModelError
    from entity.observations import ObservationError

    try:
        return main(config, zconf, args)
    except (ModelError, ObservationError) as error:  # the user's model or file: one line, no traceback
        parser.exit(2, f"{parser.prog}: error: {error}\n")
    except BusError as error:
        logging.getLogger(f"dtpf.{layer}").error("%s", error)
        return 2
    except KeyboardInterrupt:
        return 130
