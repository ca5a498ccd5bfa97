"""``dtpf play LOG``: republish a recorded log onto Zenoh.

Every recorded message goes out again on its key expression (the MCAP
topic), bytes untouched, in log order and with its original spacing divided
by ``--rate``. With ``--topics entity/particles`` a live information layer
(and the system layer behind it) can be run against a recorded entity stream;
give the live services the run id and twin of the log.
"""
from __future__ import annotations

import argparse
import fnmatch
import sys
import time

from dtpf.recording.logfile import Log, LogError, read_log
from dtpf.shell.bus import BusError, add_zenoh_arguments, open_session, publisher, zenoh_config_from_args

__all__ = ["play", "select", "register"]


def topic_matcher(patterns):
    """A predicate on topics: a glob on the whole topic (``dtpf/*/entity/*``) or a suffix of it
    (``entity/particles``) matches; no patterns match everything."""
    if not patterns:
        return lambda topic: True
    return lambda topic: any(fnmatch.fnmatchcase(topic, p) or topic.endswith("/" + p.lstrip("/")) for p in patterns)


def select(log: Log, patterns: list[str] | None) -> list:
    """The log's messages whose topic matches one of ``patterns`` (all if none), in log-time order.

    A pattern is a glob on the whole topic (``dtpf/*/entity/*``) or a suffix
    of it (``entity/particles``).
    """
    wanted = topic_matcher(patterns)
    chosen = [m for m in log.messages if wanted(m.topic)]
    chosen.sort(key=lambda m: m.log_time)  # stable: file order among equal times
    return chosen


def play(session, messages: list, *, rate: float = 1.0, loop: bool = False, progress=None,
         stop=lambda: False, unheard=None) -> int:
    """Publish ``messages`` with their recorded spacing divided by ``rate`` (0: no waiting).

    Returns the number of messages published. ``unheard`` (a dict), if given,
    counts by topic the messages published while no subscriber matched.
    """
    if rate < 0:
        raise ValueError(f"rate must be >= 0, got {rate}")
    publishers = {}
    published = 0
    while True:
        start_wall = time.monotonic()
        first = messages[0].log_time if messages else 0
        for i, message in enumerate(messages):
            if stop():
                return published
            if rate > 0:
                due = start_wall + (message.log_time - first) / 1e9 / rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            pub = publishers.get(message.topic)
            if pub is None:
                pub = publishers[message.topic] = publisher(session, message.topic)
            if unheard is not None and not pub.matching_status.matching:
                unheard[message.topic] = unheard.get(message.topic, 0) + 1
            pub.put(message.data)
            published += 1
            if progress is not None:
                progress(i + 1, len(messages))
        if not loop or not messages:
            return published


def _first_of_step(messages: list, step: int) -> int:
    """Index of the first message whose step is at least ``step`` (len(messages) if none is)."""
    from dtpf.messages.codec import MessageError, decode_for_key

    for i, item in enumerate(messages):
        try:
            if decode_for_key(item.topic, item.data).step >= step:
                return i
        except MessageError:
            continue
    return len(messages)


def cmd_play(args: argparse.Namespace) -> int:
    from dtpf.scripts.console import ProgressBar

    try:
        log = read_log(args.log)
    except LogError as error:
        print(f"dtpf play: error: {error}", file=sys.stderr)
        return 2
    if log.problem:
        print(f"note: {log.problem}", file=sys.stderr)
    messages = select(log, args.topics)
    if args.start_step:  # from the first message of that step on, in the log's time order
        messages = messages[_first_of_step(messages, args.start_step):]
    if not messages:
        print(f"dtpf play: error: no message in {args.log} matches {args.topics}", file=sys.stderr)
        return 2
    span = (messages[-1].log_time - messages[0].log_time) / 1e9
    topics = sorted({m.topic for m in messages})
    print(f"playing {len(messages)} messages on {len(topics)} topics, {span:.2f} s of log"
          f"{f' at {args.rate:g}x' if args.rate else ' as fast as possible'}{', looping' if args.loop else ''}",
          file=sys.stderr)
    if not args.connect and not args.listen and not args.zenoh_config and not args.secure:
        print("dtpf play: warning: no --connect: multicast scouting is off, so no one can reach this session; "
              "give the endpoint of the twin's router, e.g. --connect tcp/127.0.0.1:7447", file=sys.stderr)
    unheard: dict[str, int] = {}
    try:
        with open_session(zenoh_config_from_args(args)) as session:
            time.sleep(args.wait)  # let subscribers discover this session
            published = play(session, messages, rate=args.rate, loop=args.loop,
                             progress=None if args.quiet else ProgressBar(), unheard=unheard)
    except BusError as error:
        print(f"dtpf play: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\ninterrupted", file=sys.stderr)
        return 130
    print(f"published {published} messages", file=sys.stderr)
    if unheard:
        total = sum(unheard.values())
        print(f"dtpf play: warning: {total} of them had no subscriber when they were published "
              f"({'all' if total == published else 'some'} on {', '.join(sorted(unheard)[:5])}"
              f"{', ...' if len(unheard) > 5 else ''})", file=sys.stderr)
    return 0


def register(subparsers) -> None:
    """Add the ``play`` command to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "play", help="republish a recorded log onto Zenoh with its original timing",
        description=__doc__.split("\n\n", 1)[1].replace("\n", " "))
    parser.add_argument("log", help="MCAP log written by dtpf launch or the recorder")
    parser.add_argument("--rate", "-r", type=float, default=1.0,
                        help="speed factor: 2 plays twice as fast, 0 as fast as possible (default: %(default)s)")
    parser.add_argument("--topics", "-t", nargs="+", default=None, metavar="PATTERN",
                        help="only these topics: globs on the key expression or suffixes such as "
                             "entity/particles (default: every topic)")
    parser.add_argument("--start-step", type=int, default=0, metavar="K",
                        help="start at the first message of step K (default: the beginning)")
    parser.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    parser.add_argument("--wait", type=float, default=1.0, metavar="SECONDS",
                        help="pause after connecting, before the first message (default: %(default)s)")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    add_zenoh_arguments(parser)
    parser.set_defaults(handler=cmd_play)
