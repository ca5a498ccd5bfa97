"""``dtpf ask TWIN state|history|forecast``: ask a twin over Zenoh, in the terminal or from Python.

::

    dtpf ask ungm-1 state --connect tcp/127.0.0.1:7447
    dtpf ask ungm-1 history --steps 10:20 --connect tcp/127.0.0.1:7447 --json
    dtpf ask ungm-1 forecast --horizon 5 --connect tcp/127.0.0.1:7447
    dtpf ask robot-1 forecast --seconds 2 --dt 0.1 --connect tcp/127.0.0.1:7447   # a driven twin, 2 s ahead

    import dtpf
    dtpf.ask("ungm-1", "forecast", connect="tcp/127.0.0.1:7447", horizon=5)["steps"]

The live entity answers ``state`` and ``forecast``, the recorder (or
``dtpf serve LOG``) ``history``; selectors and bounds are in
:mod:`dtpf.messages.queries` and docs/guides/ask.md. An error reply (a bad
selector, a bound, a twin with no estimate yet) is one line and exit code 2;
no answer within ``--timeout`` is exit code 1.
"""
from __future__ import annotations

import argparse
import json
import sys

from dtpf.messages import queries
from dtpf.shell.bus import BusError, add_zenoh_arguments, open_session, zenoh_config, zenoh_config_from_args
from dtpf.shell.queries import QueryError, ask as ask_key

__all__ = ["ask", "register", "cmd_ask", "DEFAULT_TIMEOUT"]

DEFAULT_TIMEOUT = 10.0
#: Most bytes of one answer a client takes (the service's own bound, and room for its envelope).
_MOST = queries.MAX_BYTES + (1 << 20)


def ask(twin: str, what: str = "state", *, connect=None, timeout: float = DEFAULT_TIMEOUT, session=None,
        secure=None, role: str = "viewer", **selector) -> dict:
    """Ask a twin ``what`` ("state", "history" or "forecast") and return the answer's JSON as a dict.

    ``selector``: the question's parameters (``steps="3:5"``, ``topics=["entity/estimate"]``,
    ``horizon=20``, ``particles=True``, ...; docs/guides/ask.md). ``connect``: an endpoint (or a list) of a
    router or a ``dtpf serve``; ``session``: an open Zenoh session to use instead; ``secure``/``role``: a
    folder of ``dtpf secure init`` and the role to ask as. Raises SelectorError for a selector it can tell
    is wrong before asking, QueryError for an error reply or no answer within ``timeout`` seconds.
    """
    key = queries.key(twin, what)
    text = queries.parameters_text(**selector)
    queries.parse(what, text)  # a mistake of the caller's is said here, not by the twin
    own = session is None
    if own:
        endpoints = [connect] if isinstance(connect, str) else list(connect or [])
        if not endpoints and secure is None:
            raise queries.SelectorError("ask needs connect= (the endpoint of a router or a dtpf serve), an open "
                                        "session= or secure=")
        session = open_session(zenoh_config(mode="client" if endpoints else None, connect=endpoints,
                                            secure=secure, role=role if secure else None))
    try:
        replies = ask_key(session, key, text, timeout=timeout, max_bytes=_MOST)
    finally:
        if own:
            session.close()
    if not replies.answers and not replies.errors:
        who = {"state": "its entity", "forecast": "its entity", "history": "its recorder or a dtpf serve of its log"}
        raise QueryError(f"no answer from twin {twin} within {timeout:g} s: is {who[what]} running and reachable?")
    return replies.first()


def _selector(args: argparse.Namespace) -> dict:
    if args.what == "state":
        return {"particles": args.particles, "max_bytes": args.max_bytes}
    if args.what == "forecast":
        return {"horizon": args.horizon, "horizon_s": args.seconds, "dt": args.dt, "control": args.control,
                "particles": args.particles, "max_bytes": args.max_bytes}
    return {"steps": args.steps, "time": args.time, "topics": args.topics, "particles": args.particles,
            "limit": args.limit, "max_bytes": args.max_bytes}


def cmd_ask(args: argparse.Namespace) -> int:
    """0 with the answer, 1 when none came, 2 for an error reply or a bad option."""
    if not (args.connect or args.secure or args.zenoh_config):
        print("dtpf ask: error: give --connect ENDPOINT: the router of a dtpf launch, or the --listen of a "
              "dtpf serve", file=sys.stderr)
        return 2
    try:
        queries.parse(args.what, queries.parameters_text(**_selector(args)))  # a mistake said before connecting
    except queries.SelectorError as error:
        print(f"dtpf ask: error: {error}", file=sys.stderr)
        return 2
    try:
        session = open_session(zenoh_config_from_args(args, role="viewer"))
    except BusError as error:
        print(f"dtpf ask: error: {error}", file=sys.stderr)
        return 2
    try:
        answer = ask(args.twin, args.what, session=session, timeout=args.timeout, **_selector(args))
    except queries.SelectorError as error:
        print(f"dtpf ask: error: {error}", file=sys.stderr)
        return 2
    except QueryError as error:
        print(f"dtpf ask: error: {error}", file=sys.stderr)
        return 1 if str(error).startswith("no answer") else 2
    finally:
        session.close()
    if args.json:
        print(json.dumps(answer))
    else:
        print(describe(args.what, answer))
    return 0


def _numbers(values) -> str:
    """A vector for a terminal: one value bare, a few in brackets, many summarised."""
    values = list(values or [])
    if len(values) == 1:
        return f"{values[0]:.4g}"
    if len(values) > 6:
        return "[" + ", ".join(f"{v:.4g}" for v in values[:3]) + f", ... {len(values)} values]"
    return "[" + ", ".join(f"{v:.4g}" for v in values) + "]"


def describe(what: str, answer: dict) -> str:
    """An answer in a few lines for a terminal (``--json`` gives all of it)."""
    if what == "state":
        e = answer.get("estimate", {})
        lines = [f"twin {answer.get('twin')} step {answer.get('step')} ({answer.get('service')})"
                 + (f": {answer['detail']}" if answer.get("detail") else ""),
                 f"  mean  {_numbers(e.get('mean'))}",
                 f"  var   {_numbers(e.get('var'))}",
                 f"  95%   {_numbers(e.get('lower'))} .. {_numbers(e.get('upper'))}",
                 f"  ESS   {e.get('ess', float('nan')):.1f} ({e.get('ess_ratio', float('nan')):.1%} of N)"
                 f"   PS {e.get('ps')}   degraded {'yes' if e.get('degraded') else 'no'}"]
        if "particles" in answer:
            lines.append(f"  particles: {len(answer['particles'])} with their weights (--json)")
        return "\n".join(lines)
    if what == "forecast":
        lines = [f"twin {answer.get('twin')}: forecast from step {answer.get('from_step')}, "
                 f"{answer.get('horizon')} steps (seed {answer.get('seed')}; band: the 2.5% and 97.5% quantiles)",
                 f"  {'step':>6}  {'mean':>10}  {'sd':>10}  95% band"]
        for entry in answer.get("steps", []):
            sd = [v ** 0.5 for v in entry.get("var", [])]
            ahead = f" (+{entry['seconds']:.3g} s)" if "seconds" in entry else ""
            lines.append(f"  {entry.get('step'):>6}  {_numbers(entry.get('mean')):>10}  {_numbers(sd):>10}  "
                         f"{_numbers(entry.get('lower'))} .. {_numbers(entry.get('upper'))}{ahead}")
        return "\n".join(lines)
    lines = [f"twin {answer.get('twin')}: {answer.get('count')} messages"]
    for entry in answer.get("messages", []):
        message = entry.get("message", {})
        fields = " ".join(f"{name}={_numbers(message[name])}" for name in ("mean", "var") if name in message)
        if "particles" in message:
            fields = f"{len(message['particles'])} particles"
        lines.append(f"{entry.get('log_time', 0) / 1e9:.6f} {entry.get('topic')} step {message.get('step')}"
                     + (f"  {fields}" if fields else ""))
    return "\n".join(lines)


def _control(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--control takes numbers separated by commas, got {text!r}") from None


def register(subparsers) -> None:
    """Add ``ask`` to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "ask", help="ask a twin over Zenoh: its state now, its history, its forecast",
        description="Ask a running twin (or a dtpf serve of its log) over Zenoh queries: 'state' (the latest "
                    "estimate, from its entity, also while it waits for an observation), 'history' (the "
                    "recorded messages of steps, times and topics, from its recorder or dtpf serve, as 'dtpf cat "
                    "--json' gives them) or 'forecast' (its particle set propagated --horizon steps by its own "
                    "model, mean, variance and 95%% band a step). Exit code 0 with an answer, 1 when none came "
                    "within --timeout, 2 for an error reply or a bad option. Selectors and bounds: "
                    "docs/guides/ask.md.")
    parser.add_argument("twin", metavar="TWIN", help="the twin's id")
    parser.add_argument("what", choices=list(queries.KINDS), help="the question")
    parser.add_argument("--json", action="store_true", help="the whole answer as one JSON object")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, metavar="SECONDS",
                        help="wait at most this long for the answer (default: %(default)s)")
    parser.add_argument("--particles", action="store_true",
                        help="state: with the particle set and weights; forecast: with the last propagated set; "
                             "history: the particle sets too")
    parser.add_argument("--max-bytes", type=int, default=None, metavar="BYTES",
                        help=f"at most this much JSON in the answer (default: {queries.DEFAULT_MAX_BYTES}; at most "
                             f"{queries.MAX_BYTES})")
    group = parser.add_argument_group("history")
    group.add_argument("--steps", default=None, metavar="A:B", help="steps A .. B (both included; A: or :B open)")
    group.add_argument("--time", default=None, metavar="T0:T1",
                       help="log times T0 .. T1, seconds since the Unix epoch (either end open)")
    group.add_argument("--topics", "-t", nargs="+", default=None, metavar="PATTERN",
                       help="topics: globs or suffixes such as entity/estimate (default: entity/estimate)")
    group.add_argument("--limit", type=int, default=None, metavar="N",
                       help=f"at most N messages (default: {queries.DEFAULT_LIMIT}; at most {queries.MAX_LIMIT})")
    group = parser.add_argument_group("forecast")
    group.add_argument("--horizon", type=int, default=None, metavar="H",
                       help=f"steps ahead (default: {queries.ForecastSelector.horizon}; at most {queries.MAX_HORIZON})")
    group.add_argument("--seconds", type=float, default=None, metavar="S",
                       help="a driven twin: a horizon of S seconds instead of --horizon steps, in steps of --dt "
                            "(the last one shorter)")
    group.add_argument("--dt", type=float, default=None, metavar="SECONDS",
                       help="a driven twin: seconds a forecast step")
    group.add_argument("--control", type=_control, default=None,
                       metavar="U1,U2,...", help="a driven twin: the control held over the horizon (a what-if)")
    add_zenoh_arguments(parser)
    parser.set_defaults(handler=cmd_ask)
