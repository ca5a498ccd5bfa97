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

__all__ = ["StepRange", "choose", "as_json", "as_text", "register"]

#: Header fields every message has; the text form shows the step and leaves the rest to --json.
_HEADER = frozenset({"run_id", "twin_id", "step", "stamp", "layer"})
#: Fields that carry base64 bytes (a point cloud's or an image's data, a rejected payload's sample).
_BINARY = frozenset({"data", "sample"})
#: Lists longer than this are summarised (count, first values, range) in the text form.
_LIST_SHOWN = 6
#: Strings longer than this are cut in the text form.
_TEXT_SHOWN = 80


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


def as_text(message: Message) -> str:
    """The main fields of a message as ``name=value`` pairs for a terminal: numbers to 4 significant digits,
    long lists and particle arrays summarised (size and range), long texts cut; header fields (run, twin,
    stamp, layer) and the run configuration JSON left out (``dtpf cat --json`` has them)."""
    parts = []
    for name in type(message).model_fields:
        if name in _HEADER or name == "config_json":
            continue
        value = getattr(message, name)
        if value is None or (isinstance(value, list) and not value and name != "values"):
            continue
        if name in _BINARY and isinstance(value, str):
            parts.append(f"{name}=({len(value) * 3 // 4 - value[-2:].count('=')} bytes)")
            continue
        parts.append(f"{name}={_value_text(value)}")
    return " ".join(parts)


def _value_text(value) -> str:
    """One field's value, short."""
    if isinstance(value, np.ndarray):
        if value.size == 0:
            return f"({'x'.join(map(str, value.shape))})"
        return (f"({'x'.join(map(str, value.shape))} array, {_number(float(np.min(value)))} .. "
                f"{_number(float(np.max(value)))})")
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return _number(value)
    if isinstance(value, (list, tuple)):
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            if len(value) <= _LIST_SHOWN:
                return "[" + ", ".join(_number(v) for v in value) + "]"
            head = ", ".join(_number(v) for v in value[:3])
            return f"[{head}, ... {len(value)} values, {_number(min(value))} .. {_number(max(value))}]"
        shown = [_value_text(v) for v in value[:_LIST_SHOWN]]
        more = f", ... {len(value)} in all" if len(value) > _LIST_SHOWN else ""
        return "[" + ", ".join(shown) + more + "]"
    if hasattr(value, "model_fields"):  # a nested record: its fields that are set
        inner = {k: getattr(value, k) for k in type(value).model_fields}
        if set(inner) == {"name", "count"}:
            return f"{_cut(str(inner['name']))}:{inner['count']}"
        return "{" + " ".join(f"{k}={_value_text(v)}" for k, v in inner.items() if v is not None) + "}"
    if hasattr(value, "value") and isinstance(getattr(value, "value"), str):  # an enum
        return value.value
    if isinstance(value, str):
        text = _cut(value)
        return text if text and all(c.isalnum() or c in "._-/:" for c in text) else repr(text)
    return str(value)


def _number(v) -> str:
    return str(v) if isinstance(v, int) else f"{v:.4g}"


def _cut(text: str) -> str:
    text = " ".join(text.split())
    return text if len(text) <= _TEXT_SHOWN else text[:_TEXT_SHOWN - 3] + "..."


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
            fields = as_text(message)
            out.write(f"{item.log_time / 1e9:.6f} {item.topic} step {message.step} [{kind}{shape}]"
                      f"{'  ' + fields if fields else ''}\n")
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
                        help="MCAP log written by dtpf (several: the segments of one run; files of different "
                             "runs are refused, exit code 2)")
    parser.add_argument("--topics", "-t", nargs="+", default=None, metavar="PATTERN",
                        help="only these topics: globs on the key expression or suffixes such as entity/estimate")
    parser.add_argument("--steps", type=StepRange, default=None, metavar="A:B",
                        help="only the steps A .. B (both included; A: or :B leave one end open)")
    parser.add_argument("--twin", default=None, help="only this twin")


def register(subparsers) -> None:
    """Add ``cat`` and ``filter`` to an argparse subparsers object."""
    cat = subparsers.add_parser(
        "cat", help="print the messages of a log, one a line (--json: JSON lines, particle sets as arrays)",
        description="Print the messages of an MCAP log in file order, one a line: time, topic, step, kind and "
                    "the message's fields (numbers to 4 significant digits, long lists and particle arrays "
                    "summarised by size and range); "
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
