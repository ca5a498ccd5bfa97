"""``dtpf cat`` and ``dtpf filter``: the messages of a log, chosen by twin, topic and step.

The habits of ``mcap cat`` and ``ros2 bag filter``::

    dtpf cat run.mcap --topics entity/estimate --steps 10:20 --json   # JSON lines
    dtpf filter run.mcap -o part.mcap --steps 1:50                    # a smaller, valid log

A selection keeps the run-level messages (step 0: the statuses, which carry
the configuration) so that ``dtpf verify`` and ``dtpf summary`` still work on
what ``filter`` writes. Topics are globs on the key expression or suffixes
such as ``entity/estimate``; ``--steps A:B`` is inclusive at both ends, either
end may be left out.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from dtpf.messages.codec import MessageError
from dtpf.messages.models import Message, ParticleSet
from dtpf.recording.logfile import Log, write_log
from dtpf.scripts.logs.play import topic_matcher
from dtpf.scripts.logs.summary import read_for_command

__all__ = ["StepRange", "choose", "as_json", "register"]


class StepRange:
    """``A:B``, ``A:``, ``:B`` or ``K``: the steps A .. B, both included."""

    def __init__(self, text: str):
        first, sep, last = text.partition(":")
        try:
            self.first = int(first) if first else 0
            self.last = (int(last) if last else None) if sep else self.first
        except ValueError:
            raise argparse.ArgumentTypeError(f"steps must be A:B, A:, :B or K (integers), got {text!r}") from None
        if self.first < 0 or (self.last is not None and self.last < self.first):
            raise argparse.ArgumentTypeError(f"steps {text!r}: need 0 <= A <= B")

    def __contains__(self, step: int) -> bool:
        return self.first <= step and (self.last is None or step <= self.last)


def choose(log: Log, *, topics=None, steps: StepRange | None = None, twin: str | None = None,
           keep_run_level: bool = True):
    """The (record, message) pairs of ``log`` on ``topics``, at ``steps``, of ``twin``, in file order.

    A message that does not decode is left out; run-level messages (step 0) are kept whatever
    ``steps`` says when ``keep_run_level``.
    """
    for item, message in log.decoded(topic_matcher(topics) if topics else None):
        if isinstance(message, MessageError):
            continue
        if twin is not None and message.twin_id != twin:
            continue
        if steps is not None and message.step not in steps and not (keep_run_level and message.step == 0):
            continue
        yield item, message


def as_json(message: Message) -> dict:
    """A message as plain JSON values; a particle set's arrays as nested lists."""
    fields = json.loads(message.model_dump_json(exclude={"particles", "weights"} if isinstance(message, ParticleSet)
                                                else None, exclude_none=True))
    if isinstance(message, ParticleSet):
        fields["particles"] = np.asarray(message.particles).tolist()
        fields["weights"] = np.asarray(message.weights).tolist()
    return fields


def _read(args, command: str) -> Log | None:
    log = read_for_command(args, command)
    if log is not None and log.problem:
        print(f"note: {log.problem}", file=sys.stderr)
    return log


def cmd_cat(args: argparse.Namespace) -> int:
    """``dtpf cat LOG``: 0 when the log could be read, 1 when it is no MCAP log."""
    log = _read(args, "cat")
    if log is None:
        return 1
    out = sys.stdout
    for item, message in choose(log, topics=args.topics, steps=args.steps, twin=args.twin,
                                keep_run_level=False):
        if args.json:
            out.write(json.dumps({"topic": item.topic, "log_time": item.log_time, "message": as_json(message)}) + "\n")
        else:
            kind = type(message).__name__
            shape = f" {message.particles.shape[0]}x{message.particles.shape[1]}" if isinstance(message, ParticleSet) else ""
            out.write(f"{item.log_time / 1e9:.6f} {item.topic} step {message.step} [{kind}{shape}]\n")
    return 0


def cmd_filter(args: argparse.Namespace) -> int:
    """``dtpf filter LOG -o OUT``: 0 when OUT was written, 1 when LOG could not be read, 2 when OUT is LOG."""
    if any(Path(path).resolve() == Path(args.output).resolve() for path in args.log):
        print("dtpf filter: error: OUT must not be one of the logs read", file=sys.stderr)
        return 2
    log = _read(args, "filter")
    if log is None:
        return 1
    kept = [item for item, _ in choose(log, topics=args.topics, steps=args.steps, twin=args.twin)]
    used = {item.channel_id for item in kept}
    channels = {cid: channel for cid, channel in log.channels.items() if cid in used}
    schemas = {sid: schema for sid, schema in log.schemas.items()
               if any(channel.schema_id == sid for channel in channels.values())}
    part = Log(path=log.path, size=0, header=log.header, schemas=schemas, channels=channels, messages=kept,
               complete=True)
    written = write_log(part, args.output)
    print(f"wrote {args.output}: {written} of {len(log.messages)} messages on {len(channels)} channels",
          file=sys.stderr)
    return 0


def _selection_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", type=Path, nargs="+", metavar="LOG",
                        help="MCAP log written by dtpf (several: the segments of one run)")
    parser.add_argument("--topics", "-t", nargs="+", default=None, metavar="PATTERN",
                        help="only these topics: globs on the key expression or suffixes such as entity/estimate")
    parser.add_argument("--steps", type=StepRange, default=None, metavar="A:B",
                        help="only the steps A .. B (both included; A: or :B leave one end open)")
    parser.add_argument("--twin", default=None, help="only this twin")


def register(subparsers) -> None:
    """Add ``cat`` and ``filter`` to an argparse subparsers object."""
    cat = subparsers.add_parser(
        "cat", help="print the messages of a log, one a line (--json: JSON lines, particle sets as arrays)",
        description="Print the messages of an MCAP log in file order, one a line: time, topic, step and kind; "
                    "--json prints each as a JSON object {topic, log_time, message} with a particle set's "
                    "particles and weights as arrays (like 'mcap cat --json').")
    _selection_arguments(cat)
    cat.add_argument("--json", action="store_true", help="JSON lines instead of one summary line a message")
    cat.set_defaults(handler=cmd_cat)
    filtered = subparsers.add_parser(
        "filter", help="write the chosen messages of a log as a new, valid log (like 'ros2 bag filter')",
        description="Write the messages of LOG chosen by twin, topics and steps into OUT, a finished MCAP log "
                    "with the same schemas and channels. The run-level messages (statuses, which carry the run "
                    "configuration) are kept, so 'dtpf verify OUT' and 'dtpf summary OUT' work on the steps "
                    "kept. Exit code 0 when OUT was written, 1 when LOG cannot be read, 2 when OUT is LOG.")
    _selection_arguments(filtered)
    filtered.add_argument("--output", "-o", type=Path, required=True, metavar="OUT", help="file to write")
    filtered.set_defaults(handler=cmd_filter)
