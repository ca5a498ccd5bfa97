"""``dtpf router``: a Zenoh router alone, for twins whose layers run on several machines.

There is no ``zenohd`` to install: a Python session in router mode routes
between clients. With ``--secure DIR`` it is the router of a
secure folder: it listens on the folder's protocol, checks every client's
certificate or password and enforces the access control of
``dtpf secure init``; the services then connect with ``--secure DIR``::

    dtpf router --secure deploy/tls --listen tls/10.0.0.1:7447
    python3 -m dtpf.entity.service --secure deploy/tls --connect tls/10.0.0.1:7447 ...
"""
from __future__ import annotations

import argparse
import json
import sys

from dtpf.scripts.console import stop_on_signals
from dtpf.shell.bus import BusError, open_session, zenoh_config

__all__ = ["register", "cmd_router"]


def _file_endpoints(folder) -> list[str]:
    """The listen endpoints of a secure folder's router.json5."""
    from dtpf.shell.secure import open_secure_dir, role_config

    data = json.loads(role_config(open_secure_dir(folder), "router"))
    return list(data.get("listen", {}).get("endpoints", []))


def cmd_router(args: argparse.Namespace) -> int:
    listen = args.listen or ([] if args.secure else ["tcp/127.0.0.1:7447"])
    stop = stop_on_signals()  # before the router listens: a client may stop it at once
    try:
        session = open_session(zenoh_config(mode="router", listen=listen, connect=args.connect, secure=args.secure,
                                            role="router" if args.secure else None))
    except BusError as error:
        print(f"dtpf router: error: {error}", file=sys.stderr)
        return 2
    where = listen or _file_endpoints(args.secure)
    how = f"secure folder {args.secure}" if args.secure else "no authentication, no access control"
    joined = f", joined to {', '.join(args.connect)}" if args.connect else ""
    print(f"dtpf router: routing on {', '.join(where)}{joined} ({how}); Ctrl-C stops", file=sys.stderr, flush=True)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
    return 0


def register(subparsers) -> None:
    """``dtpf router``."""
    router = subparsers.add_parser(
        "router", help="run a Zenoh router alone (the layers of a twin on several machines connect to it)",
        description="Route between the layers of twins that run as separate services (there is no zenohd to "
                    "install). With --secure DIR: the router of a 'dtpf secure init' folder, which checks each "
                    "client's certificate or password and lets each role put only on its own keys.")
    router.add_argument("--listen", "-l", action="append", default=[], metavar="ENDPOINT",
                        help="where to listen, e.g. tls/10.0.0.1:7447 (repeatable; default: tcp/127.0.0.1:7447, "
                             "or with --secure the endpoint of the folder's router.json5)")
    router.add_argument("--connect", "-e", action="append", default=[], metavar="ENDPOINT",
                        help="another router to join, e.g. tcp/10.0.0.2:7447: the routers then route between "
                             "their clients (repeatable)")
    router.add_argument("--secure", metavar="DIR", help="a folder made by 'dtpf secure init' (DIR, DIR/tls or "
                                                        "DIR/usrpwd)")
    router.set_defaults(handler=cmd_router)
