"""A twin's messages, live in Foxglove: its Zenoh topics served over Foxglove's WebSocket protocol.

Every JSON topic of the twin (estimate, weight state, PS, statuses, the
particle cloud, the video frame, observations) becomes a Foxglove channel of
the same name with the schema a log embeds, so a live view and a log look
alike. The particle sets themselves travel in dtpf's own envelope, which
Foxglove cannot decode; ``dtpf/<twin>/entity/cloud`` shows them. The server is
``foxglove-sdk``'s::

    dtpf launch --foxglove 8765                          # the launcher serves its own run
    dtpf bridge --connect tcp/127.0.0.1:7447 --twin ungm-1 --foxglove 8765

then, in Foxglove, Open connection, ``ws://127.0.0.1:8765``.
"""
from __future__ import annotations

import argparse
import logging
import re
import sys
import threading
import time

from dtpf.messages import keys
from dtpf.messages.codec import ENVELOPE_ENCODING, message_encoding, schema_for
from dtpf.messages.models import ParticleSet
from dtpf.scripts.console import stop_on_signals
from dtpf.shell.bus import BusError, Inbox, add_zenoh_arguments, open_session, zenoh_config_from_args

__all__ = ["FoxgloveBridge", "parse_address", "register"]


def parse_address(text: str) -> tuple[str, int]:
    """``PORT`` or ``HOST:PORT`` (the host defaults to 127.0.0.1: loopback only unless told)."""
    host, sep, port = text.rpartition(":")
    try:
        number = int(port)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected PORT or HOST:PORT, got {text!r}") from None
    if not 0 <= number <= 65535:
        raise argparse.ArgumentTypeError(f"port {number} is outside 0..65535")
    return (host if sep and host else "127.0.0.1"), number


#: The WebSocket subprotocol foxglove-sdk's server speaks; a client that offers only another one (the older
#: ``foxglove.websocket.v1``) is refused with HTTP 400 (the SDK has no setting to accept it).
SUBPROTOCOL = "foxglove.sdk.v1"


class _RefusedClients(logging.Filter):
    """One line per client host instead of the SDK's 'Dropping client HOST:PORT: handshake failed' per attempt
    (a viewer retries about once a second, each time from a new port): the first says why it is refused and
    what it must offer; later attempts from that host are not logged."""

    _DROPPED = re.compile(r"^Dropping client (.+):(\d+): handshake failed")

    def __init__(self) -> None:
        super().__init__()
        self.hosts: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        dropped = self._DROPPED.match(record.getMessage())
        if dropped is None:
            return True
        host = dropped.group(1)
        if host in self.hosts:
            return False
        self.hosts.add(host)
        record.msg, record.args = ("refused a Foxglove client at %s: its WebSocket handshake failed (this server "
                                   "speaks the subprotocol %s; a client offering only foxglove.websocket.v1 gets "
                                   "HTTP 400); further attempts from %s are not logged", (host, SUBPROTOCOL, host))
        return True


_REFUSED = _RefusedClients()


class FoxgloveBridge:
    """Serves the JSON topics of ``twin`` that arrive on ``session`` to Foxglove clients."""

    def __init__(self, session, twin: str, host: str = "127.0.0.1", port: int = 8765):
        try:
            import foxglove
        except ImportError:
            raise RuntimeError("the Foxglove bridge needs foxglove-sdk: pip install 'dtpf[foxglove]'") from None

        self._foxglove = foxglove
        self.twin = twin
        self.context = foxglove.Context()  # its own: the process's other sinks (an MCAP file) are not fed
        server_log = logging.getLogger("foxglove.websocket.server")
        if _REFUSED not in server_log.filters:
            server_log.addFilter(_REFUSED)
        self.server = foxglove.start_server(name=f"dtpf {twin}", host=host, port=port, context=self.context)
        self.port = self.server.port
        self.channels: dict[str, object] = {}
        self.forwarded = 0
        # The twin's known topics are advertised at once, so a viewer can subscribe before the first step.
        for topic in keys.TOPICS.values():
            if topic.message is not ParticleSet:
                self._channel(topic.key(twin))
        self.inbox = Inbox(session, keys.twin_pattern(twin), max_items=1024)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._forward, name="foxglove", daemon=True)
        self._thread.start()

    def _channel(self, key: str):
        channel = self.channels.get(key)
        if channel is None:
            try:
                cls = keys.topic_of(key).message
            except ValueError:
                return None  # not a dtpf topic: nothing to show it with
            if message_encoding(cls) == ENVELOPE_ENCODING or len(self.channels) >= 256:
                return None
            record = schema_for(cls)
            channel = self.channels[key] = self._foxglove.Channel(
                key, message_encoding="json", context=self.context,
                schema=self._foxglove.Schema(name=record.name, encoding=record.encoding, data=record.data))
        return channel

    def _forward(self) -> None:
        while not self._stop.is_set():
            item = self.inbox.get(timeout=0.2)
            if item is None:
                continue
            channel = self._channel(item.key)
            if channel is not None and item.payload[:1] == b"{":
                channel.log(item.payload, log_time=time.time_ns())
                self.forwarded += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.inbox.close()
        self.server.stop()


def cmd_bridge(args: argparse.Namespace) -> int:
    host, port = args.foxglove
    stop = stop_on_signals()
    try:
        session = open_session(zenoh_config_from_args(args, role="viewer"))
    except BusError as error:
        print(f"dtpf bridge: error: {error}", file=sys.stderr)
        return 2
    try:
        bridge = FoxgloveBridge(session, args.twin, host, port)
    except Exception as error:  # foxglove-sdk: a port in use, mostly
        session.close()
        print(f"dtpf bridge: error: cannot serve Foxglove on {host}:{port}: {error}", file=sys.stderr)
        return 2
    print(f"dtpf bridge: twin {args.twin} for Foxglove on ws://{host}:{bridge.port} (Ctrl-C stops)", file=sys.stderr)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        bridge.close()
        session.close()
    print(f"dtpf bridge: forwarded {bridge.forwarded} messages", file=sys.stderr)
    return 0


def register(subparsers) -> None:
    """Add the ``bridge`` command to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "bridge", help="serve a running twin's topics to Foxglove over its WebSocket protocol",
        description="Subscribe to a twin on Zenoh and serve its JSON topics (estimate, weight state, PS, statuses, "
                    "the particle cloud, frames) to Foxglove over its WebSocket protocol (foxglove-sdk), with the "
                    "schemas a log embeds. In Foxglove: Open connection, ws://HOST:PORT.")
    parser.add_argument("--twin", default="ungm-1", help="twin to serve (default: %(default)s)")
    parser.add_argument("--foxglove", type=parse_address, default=("127.0.0.1", 8765), metavar="[HOST:]PORT",
                        help="where to serve (default: 127.0.0.1:8765)")
    add_zenoh_arguments(parser)
    parser.set_defaults(handler=cmd_bridge)
