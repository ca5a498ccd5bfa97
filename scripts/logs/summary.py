"""``dtpf info``, ``dtpf summary`` and ``dtpf recover``: look into a recorded MCAP log.

- ``info LOG``: what the file holds, like ``mcap info``: size, complete or
  damaged (and what is missing), time range, messages per topic with their
  encoding, schema and first and last step, run and twin ids, schemas.
- ``summary LOG``: the run as the filter saw it, per twin: steps, RMSE
  against the recorded truth, ESS, resamplings, the PS trajectory, degraded
  steps, what each layer rejected, and the steps the recorder declared lost
  (missed, and no longer in its publishers' caches).
- ``recover LOG -o OUT``: rewrite a damaged log (a killed recorder, a cut
  copy) as a valid MCAP with every message that could be read.

The numbers come from :func:`log_info` and :func:`summarise` (dataclasses);
:func:`format_info` and :func:`format_summary` only print them. A damaged
file is read as far as it goes (:mod:`dtpf.recording.logfile`); the commands say
what is missing first, then report what is there.

``register(subparsers)`` adds the three commands to an argparse parser; the
module also runs on its own: ``python -m dtpf.scripts.logs.summary info run.mcap``.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dtpf.messages.codec import MessageError, class_for_schema, schema_for
from dtpf.messages.models import Estimate, Missed, PSCommand, Status
from dtpf.recording.logfile import Log, LogError, MixedRunsError, in_step_order, read_log, read_logs, write_log
from dtpf.recording.missed import lost_steps

__all__ = ["LogInfo", "TopicInfo", "SchemaInfo", "LogSummary", "TwinSummary", "Trajectory", "LayerStatus",
           "log_info", "summarise", "format_info", "format_summary", "format_ranges",
           "cmd_info", "cmd_summary", "cmd_recover", "register", "main"]


# --- info ---

@dataclass
class TopicInfo:
    """One channel of the log."""

    topic: str
    channel_id: int
    message_encoding: str
    schema_name: str | None
    count: int = 0
    first_step: int | None = None  #: step of the first decodable message, in file order
    last_step: int | None = None   #: step of the last decodable message, in file order
    undecodable: int = 0


@dataclass
class SchemaInfo:
    """One schema record of the log."""

    id: int
    name: str
    encoding: str
    size: int
    channels: int
    #: "same" as this dtpf's schema of that name, "differs", or "not dtpf"
    current: str


@dataclass
class LogInfo:
    """What :func:`log_info` finds in a log."""

    path: Path
    size: int
    complete: bool
    problems: list[str]  #: what is missing or damaged (dtpf.recording.logfile.Log.problems)
    library: str | None
    profile: str | None
    messages: int
    start_ns: int | None
    end_ns: int | None
    topics: list[TopicInfo]
    schemas: list[SchemaInfo]
    run_ids: list[str]
    twin_ids: list[str]
    undecodable: int
    first_error: str | None

    @property
    def problem(self) -> str | None:
        return "; ".join(self.problems) if self.problems else None

    @property
    def duration_s(self) -> float | None:
        return None if self.start_ns is None else (self.end_ns - self.start_ns) / 1e9


def log_info(log: Log) -> LogInfo:
    """File-level facts of ``log`` (decodes every message once for steps and ids)."""
    topics = {cid: TopicInfo(ch.topic, cid, ch.message_encoding,
                             log.schemas[ch.schema_id].name if ch.schema_id in log.schemas else None)
              for cid, ch in sorted(log.channels.items())}
    runs, twins = {}, {}
    undecodable, first_error = 0, None
    for item, message in log.decoded():
        topic = topics[item.channel_id]
        topic.count += 1
        if isinstance(message, MessageError):
            topic.undecodable += 1
            undecodable += 1
            first_error = first_error or str(message)
            continue
        if topic.first_step is None:
            topic.first_step = message.step
        topic.last_step = message.step
        runs[message.run_id] = None
        twins[message.twin_id] = None
    schemas = []
    for sid, schema in sorted(log.schemas.items()):
        cls = class_for_schema(schema.name)
        current = "not dtpf" if cls is None else "same" if schema_for(cls).data == schema.data else "differs"
        schemas.append(SchemaInfo(sid, schema.name, schema.encoding, len(schema.data),
                                  sum(ch.schema_id == sid for ch in log.channels.values()), current))
    times = [item.log_time for item in log.messages]
    return LogInfo(
        path=log.path, size=log.size, complete=log.complete, problems=list(log.problems),
        library=log.header.library if log.header else None, profile=log.header.profile if log.header else None,
        messages=len(log.messages), start_ns=min(times) if times else None, end_ns=max(times) if times else None,
        topics=list(topics.values()), schemas=schemas, run_ids=list(runs), twin_ids=list(twins),
        undecodable=undecodable, first_error=first_error)


def _time(ns: int) -> str:
    sec, nsec = divmod(ns, 1_000_000_000)
    stamp = dt.datetime.fromtimestamp(sec, tz=dt.timezone.utc)
    return f"{stamp:%Y-%m-%d %H:%M:%S}.{nsec:09d} UTC ({sec}.{nsec:09d})"


def _state(label: str, complete: bool, problems: list[str], width: int, failures: list[str] = ()) -> list[str]:
    """'state  complete', or 'state  DAMAGED' and the problems, one a line; with ``failures`` (runs whose
    entity failed), 'state  run failed at step K' and each failure, whatever the file's state."""
    file_state = "complete" if not problems else "complete (footer read), with problems" if complete else "DAMAGED"
    if failures:
        lines = [f"{label:<{width}}{failures[0]}", *(f"{'':<{width}}{line}" for line in failures[1:]),
                 f"{'':<{width}}(the file: {file_state})"]
    else:
        lines = [f"{label:<{width}}{file_state}"]
    for i, part in enumerate(problems):
        lines.append(f"{'problem' if i == 0 else '':<{width}}{part}")
    return lines


def _failures(summary: "LogSummary") -> list[str]:
    """'run failed at step K (twin T): what the entity said' for each twin whose entity's last status is
    failed: the step its error names (``step 5: ...``), else the first step without an estimate."""
    said = []
    for t in summary.twins:
        s = t.statuses.get("entity")
        if s is None or s.state != "failed":
            continue
        error = s.last_error or ""
        for name in ("FilterError: ", "ModelError: ", "ObservationError: "):
            error = error[len(name):] if error.startswith(name) else error
        named = re.match(r"step (\d+): ", error)
        step = (int(named.group(1)) if named else t.missing_steps[0] if t.missing_steps
                else t.steps[-1] + 1 if t.steps else None)
        at = f" at step {step}" if step is not None else ""
        twin = f" (twin {t.twin})" if len(summary.twins) > 1 else ""
        rest = error[named.end():] if named else error
        said.append(f"run failed{at}{twin}" + (f": {rest}" if rest else ""))
    return said


def format_info(info: LogInfo) -> str:
    """``info`` as text."""
    lines = [
        f"file        {info.path}",
        f"size        {info.size:,} bytes",
        *_state("state", info.complete, info.problems, 12),
        f"library     {info.library or '-'}" + (f" (profile {info.profile!r})" if info.profile else ""),
        f"messages    {info.messages:,}" + (f" ({info.undecodable:,} undecodable)" if info.undecodable else ""),
    ]
    if info.start_ns is not None:
        lines += [f"start       {_time(info.start_ns)}",
                  f"end         {_time(info.end_ns)}",
                  f"duration    {info.duration_s:.3f} s"]
    lines += [f"runs        {', '.join(info.run_ids) or '-'}",
              f"twins       {', '.join(info.twin_ids) or '-'}"]
    if info.first_error:
        lines.append(f"first error {info.first_error}")
    lines.append(f"channels    {len(info.topics)}")
    if info.topics:
        rows = [("topic", "messages", "encoding", "schema", "steps")]
        for t in info.topics:
            steps = "-" if t.first_step is None else f"{t.first_step}..{t.last_step}"
            if t.undecodable:
                steps += f" ({t.undecodable} undecodable)"
            rows.append((t.topic, f"{t.count:,}", t.message_encoding, t.schema_name or "-", steps))
        lines += _table(rows, right={1})
    lines.append(f"schemas     {len(info.schemas)}")
    if info.schemas:
        rows = [("id", "name", "encoding", "bytes", "channels", "this dtpf's")]
        rows += [(str(s.id), s.name, s.encoding, f"{s.size:,}", str(s.channels), s.current) for s in info.schemas]
        lines += _table(rows, right={0, 3, 4})
    return "\n".join(lines)


def _table(rows: list[tuple[str, ...]], right: set[int] = frozenset()) -> list[str]:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  " + "  ".join(cell.rjust(w) if i in right else cell.ljust(w)
                             for i, (cell, w) in enumerate(zip(row, widths))).rstrip() for row in rows]


# --- summary ---

@dataclass
class Trajectory:
    """A PS sequence: first and last value, range and number of changes."""

    start: float
    end: float
    min: float
    max: float
    changes: int
    count: int

    @classmethod
    def of(cls, values: list[float]) -> "Trajectory | None":
        if not values:
            return None
        changes = sum(a != b for a, b in zip(values, values[1:]))
        return cls(values[0], values[-1], min(values), max(values), changes, len(values))


@dataclass
class LayerStatus:
    """The last Status a layer published in the log; received and rejected summed over every
    process the layer had (a layer the launcher restarted has several)."""

    layer: str
    state: str
    received: int
    rejected: int
    last_error: str | None
    step: int
    processes: int = 1


@dataclass
class TwinSummary:
    """One twin (and run) of a log, as its Estimate, PSCommand and Status messages tell it."""

    twin: str
    run_id: str
    config: dict | None = None          #: the RunConfig from a Status message, when recorded
    steps: list[int] = field(default_factory=list)  #: steps with an estimate, ascending
    expected_steps: int | None = None   #: T from the recorded configuration
    missing_steps: list[int] = field(default_factory=list)  #: the first MAX_LISTED missing steps
    missing_count: int = 0              #: every missing step, listed or not
    duplicate_estimates: int = 0        #: estimates beyond the one used, of steps that had several
    competing_steps: list[int] = field(default_factory=list)  #: steps with more than one estimate
    out_of_range: int = 0               #: estimates beyond the recorded T (not used)
    rmse: float | None = None           #: over the steps whose estimate records the truth
    truth_steps: int = 0
    log_predictive: float | None = None  #: mean of log p(z_k | z_1:k-1) over the steps that record it
    log_predictive_steps: int = 0
    innovation: float | None = None      #: mean normalised innovation squared, where recorded
    observed_values: int = 0             #: m, from the recorded observations
    observations: dict | None = None     #: the live entity's last observation counts
    mean_ess: float | None = None
    min_ess: float | None = None
    min_ess_step: int | None = None
    resamplings: int = 0
    ps_commanded: Trajectory | None = None  #: system/ps, in order of applies_from_step
    ps_applied: Trajectory | None = None    #: Estimate.ps, in step order
    policies: list[str] = field(default_factory=list)
    #: PS commands that turned the preprocessing off (a guard policy's "off"), of all PS commands.
    off_commands: int = 0
    last_reason: str | None = None
    degraded_steps: list[int] = field(default_factory=list)
    statuses: dict[str, LayerStatus] = field(default_factory=dict)
    #: Steps the recorder declared lost (missed, and no longer in the publishers' caches), by topic
    #: (``entity/estimate``, ...); with the messages and gaps its notes count.
    lost: dict[str, list[int]] = field(default_factory=dict)
    lost_messages: int = 0
    lost_gaps: int = 0

    @property
    def lost_steps(self) -> list[int]:
        """The steps any per-step topic of the twin lost, ascending."""
        return sorted({step for steps in self.lost.values() for step in steps})

    @property
    def degraded(self) -> int:
        return len(self.degraded_steps)


@dataclass
class LogSummary:
    """What :func:`summarise` finds: the file's state, then one summary per twin and run."""

    path: Path
    size: int
    complete: bool
    problems: list[str]                #: what is missing or damaged (dtpf.recording.logfile.Log.problems)
    messages: int
    undecodable: int
    errors: list[str]                  #: the first few decode errors
    twins: list[TwinSummary]
    segments: list[Path] = field(default_factory=list)  #: the files of a joined log (empty: one file)

    @property
    def problem(self) -> str | None:
        return "; ".join(self.problems) if self.problems else None


#: Decode errors kept in :attr:`LogSummary.errors`.
MAX_ERRORS = 5
_SUMMARY_TOPICS = {"estimate", "ps", "status", "missed"}


def summarise(log: Log) -> LogSummary:
    """Per-twin figures from the Estimate, PSCommand and Status messages of ``log``."""
    def wanted(topic: str) -> bool:
        return topic.rsplit("/", 1)[-1] in _SUMMARY_TOPICS

    groups: dict[tuple[str, str], dict[str, list]] = {}
    undecodable, errors = 0, []
    for _, message in log.decoded(wanted):
        if isinstance(message, MessageError):
            undecodable += 1
            if len(errors) < MAX_ERRORS:
                errors.append(str(message))
            continue
        group = groups.setdefault((message.twin_id, message.run_id),
                                  {"estimates": [], "ps": [], "status": [], "missed": []})
        if isinstance(message, Missed):
            group["missed"].append(message)
        elif isinstance(message, Estimate):
            group["estimates"].append(message)
        elif isinstance(message, PSCommand):
            group["ps"].append(message)
        elif isinstance(message, Status):
            group["status"].append(message)
    twins = [_twin_summary(twin, run, **group) for (twin, run), group in groups.items()]
    return LogSummary(log.path, log.size, log.complete, list(log.problems), len(log.messages), undecodable, errors,
                      twins, list(log.segments))


def _twin_summary(twin: str, run_id: str, estimates: list[Estimate], ps: list[PSCommand],
                  status: list[Status], missed: list[Missed] = ()) -> TwinSummary:
    out = TwinSummary(twin, run_id)
    prefix = f"dtpf/{twin}/"
    out.lost = {key[len(prefix):] if key.startswith(prefix) else key: steps
                for key, steps in lost_steps(list(missed)).items()}
    out.lost_messages = sum(note.count for note in missed)
    out.lost_gaps = len(missed)
    last_of_process: dict[tuple[str, int], Status] = {}
    for message in status:
        last_of_process[(message.layer.value, message.pid)] = message
    for (layer, _), message in last_of_process.items():  # in the order of each process's first status
        before = out.statuses.get(layer)
        out.statuses[layer] = LayerStatus(
            layer, message.state.value, message.received + (before.received if before else 0),
            message.rejected + (before.rejected if before else 0), message.last_error or (
                before.last_error if before else None), message.step, 1 + (before.processes if before else 0))
    for message in status:
        if message.layer.value == "entity" and message.observations is not None:
            out.observations = message.observations.model_dump()
        config_json = getattr(message, "config_json", None)
        if config_json and out.config is None:
            try:
                out.config = json.loads(config_json)
            except ValueError:
                pass
    out.statuses = dict(sorted(out.statuses.items()))
    if out.config is not None and isinstance(out.config.get("steps"), int):
        out.expected_steps = out.config["steps"]
    in_range = [e for e in estimates if out.expected_steps is None or e.step <= out.expected_steps]
    out.out_of_range = len(estimates) - len(in_range)
    by_step, competing = in_step_order(in_range)
    out.competing_steps = sorted(competing)
    out.duplicate_estimates = sum(competing.values()) - len(competing)
    ordered = list(by_step.values())
    out.steps = [e.step for e in ordered]
    last = max(out.expected_steps or 0, out.steps[-1] if out.steps else 0)
    out.missing_count, out.missing_steps = _missing(out.steps, last)
    with_truth = [e for e in ordered if e.truth is not None]
    out.truth_steps = len(with_truth)
    if with_truth:
        errors = np.array([e.mean for e in with_truth]) - np.array([e.truth for e in with_truth])
        out.rmse = float(np.sqrt(np.mean(errors ** 2)))
    lp = [e.log_predictive for e in ordered if e.log_predictive is not None]
    out.log_predictive_steps = len(lp)
    out.log_predictive = float(np.mean(lp)) if lp else None
    nis = [e.innovation for e in ordered if e.innovation is not None]
    out.innovation = float(np.mean(nis)) if nis else None
    out.observed_values = len(ordered[-1].observation or []) if ordered else 0
    if ordered:
        ess = np.array([e.ess for e in ordered])
        out.mean_ess = float(ess.mean())
        out.min_ess = float(ess.min())
        out.min_ess_step = ordered[int(ess.argmin())].step
    out.resamplings = sum(e.resampled for e in ordered)
    out.degraded_steps = [e.step for e in ordered if e.degraded]
    out.ps_applied = Trajectory.of([e.ps for e in ordered if e.ps is not None])
    commands = sorted(enumerate(ps), key=lambda pair: (pair[1].applies_from_step, pair[0]))
    out.ps_commanded = Trajectory.of([c.ps for _, c in commands])
    out.policies = list(dict.fromkeys(c.policy for c in ps))
    out.off_commands = sum(not c.preprocess for c in ps)
    out.last_reason = commands[-1][1].reason if commands else None
    return out


#: Most missing steps a summary lists (a forged step 4294967295 would otherwise list billions).
MAX_LISTED = 10_000


def _missing(steps: list[int], last: int) -> tuple[int, list[int]]:
    """How many of 1..last are not in the ascending ``steps``, and the first MAX_LISTED of them;
    walks the gaps, so the cost is len(steps) + MAX_LISTED whatever ``last`` is."""
    count, listed, expected = 0, [], 1
    for step in [*steps, last + 1]:
        if step > expected:
            gap = step - expected
            count += gap
            listed.extend(range(expected, min(step, expected + MAX_LISTED - len(listed))))
        expected = max(expected, step + 1)
    return count, listed


def format_ranges(steps: list[int]) -> str:
    """Sorted integers as ranges: [1, 2, 3, 5, 7, 8] -> '1-3, 5, 7-8'."""
    parts, run = [], []
    for step in sorted(set(steps)):
        if run and step != run[-1] + 1:
            parts.append(_span(run))
            run = []
        run.append(step)
    if run:
        parts.append(_span(run))
    return ", ".join(parts)


def _span(run: list[int]) -> str:
    return str(run[0]) if len(run) == 1 else f"{run[0]}-{run[-1]}"


def _lost_steps(t: TwinSummary) -> str:
    """'steps 50-120, declared lost by the recorder (entity/estimate 50-120, ...; N messages in G gaps its
    publishers' caches no longer held)'."""
    topics = ", ".join(f"{topic} {format_ranges(steps)}" for topic, steps in t.lost.items())
    counts = (f"{t.lost_messages:,} message{'s' * (t.lost_messages != 1)} in {t.lost_gaps} "
              f"gap{'s' * (t.lost_gaps != 1)} its publishers' caches no longer held")
    head = f"steps {format_ranges(t.lost_steps)}" if t.lost_steps else "no step of a per-step topic"
    return f"{head}, declared lost by the recorder ({topics + '; ' if topics else ''}{counts})"


def _trajectory(t: Trajectory | None, what: str) -> str:
    if t is None:
        return "-"
    return (f"{t.start:g} -> {t.end:g} (min {t.min:g}, max {t.max:g}, {t.changes} change{'s' * (t.changes != 1)}, "
            f"{t.count} {what})")


def format_summary(summary: LogSummary) -> str:
    """``summary`` as text: the file's state first, then each twin."""
    lines = [f"log           {summary.path} ({summary.size:,} bytes)",
             *([f"segments      {' + '.join(str(path) for path in summary.segments)}"] if summary.segments else []),
             *_state("state", summary.complete, summary.problems, 14, _failures(summary)),
             f"messages      {summary.messages:,}"
             + (f" ({summary.undecodable:,} undecodable)" if summary.undecodable else "")]
    lines += [f"  undecodable: {error}" for error in summary.errors]
    if not summary.twins:
        lines.append("no estimate, PS or status message of any twin in the log")
    for t in summary.twins:
        if not t.steps and not t.ps_commanded and set(t.statuses) == {"recorder"}:  # a fleet's recorder
            s = t.statuses["recorder"]
            lines += ["", f"recorder of the fleet (twin {t.twin}, run {t.run_id}): {s.rejected} of {s.received} "
                          f"received rejected ({s.state})" + (f", last error: {s.last_error}" if s.last_error else "")]
            continue
        lines += ["", f"twin {t.twin}, run {t.run_id}"]
        c = t.config
        if c:
            lines.append(f"  config        {c.get('model') or c.get('scenario')}, N = {c.get('particles')}, "
                         f"T = {c.get('steps') if c.get('steps') is not None else 'live'}, "
                         f"seed {c.get('seed')}, {c.get('resampler')}, "
                         f"{'DT preprocessing' if c.get('preprocess') else 'no preprocessing'}, "
                         f"policy {c.get('policy')}")
        count = f"{len(t.steps)}" + (f" of {t.expected_steps}" if t.expected_steps else "")
        span = f" ({format_ranges(t.steps)})" if t.steps else ""
        lines.append(f"  steps         {count}{span}")
        if t.missing_steps:
            more = f" ... ({t.missing_count} in all)" if t.missing_count > len(t.missing_steps) else ""
            lines.append(f"  missing       {format_ranges(t.missing_steps)}{more}")
        if t.lost_gaps:
            lines.append(f"  lost          {_lost_steps(t)}")
        if t.out_of_range:
            lines.append(f"  out of range  {t.out_of_range} estimates beyond step {t.expected_steps} (not used)")
        if t.competing_steps:
            lines.append(f"  competing     {len(t.competing_steps)} steps had more than one estimate "
                         f"({format_ranges(t.competing_steps)}; {t.duplicate_estimates} more): each uses the "
                         f"one received in step order, as the twin's entity publishes them")
        if t.rmse is not None:
            lines.append(f"  RMSE          {t.rmse:.4f} (truth at {t.truth_steps} steps)")
        if t.rmse is None or t.truth_steps < len(t.steps):
            if t.log_predictive is None:
                lines.append("  RMSE          - (no truth recorded)")
            else:
                lines.append(f"  log predictive {t.log_predictive:.4f} per step (mean of log p(z_k | z_1:k-1) "
                             f"over {t.log_predictive_steps} steps; no truth recorded)")
            if t.innovation is not None:
                lines.append(f"  innovation    {t.innovation:.3f} mean normalised innovation squared "
                             f"(about {t.observed_values or 1} when consistent)")
        if t.observations:
            o = t.observations
            rejected = {name: o.get(name, 0) for name in ("duplicate", "out_of_order", "wrong_length", "malformed")}
            lines.append(f"  observations  {o.get('accepted', 0)} accepted, last sequence {o.get('last_sequence', 0)}"
                         f", {o.get('missed', 0)} missed; rejected " +
                         ", ".join(f"{name.replace('_', ' ')} {n}" for name, n in rejected.items()))
        if t.mean_ess is not None:
            lines.append(f"  ESS           mean {t.mean_ess:.1f}, min {t.min_ess:.1f} at step {t.min_ess_step}")
        lines.append(f"  resamplings   {t.resamplings}")
        policy = f", policy {', '.join(t.policies)}" if t.policies else ""
        lines.append(f"  PS commanded  {_trajectory(t.ps_commanded, 'commands')}{policy}")
        lines.append(f"  PS applied    {_trajectory(t.ps_applied, 'steps')}")
        if t.off_commands:
            total = t.ps_commanded.count if t.ps_commanded is not None else t.off_commands
            lines.append(f"  preprocessing off in {t.off_commands} of {total} commands (the system layer's "
                         f"decision; the entity resampled its own set)")
        lines.append(f"  degraded      {t.degraded}" + (f" (steps {format_ranges(t.degraded_steps)})"
                                                        if t.degraded_steps else ""))
        if not t.statuses:
            lines.append("  rejected      - (no status recorded)")
        for i, s in enumerate(t.statuses.values()):
            error = f", last error: {s.last_error}" if s.last_error else ""
            processes = f", {s.processes} processes" if s.processes > 1 else ""
            lines.append(f"  {'rejected' if i == 0 else '':<13} {s.layer:<12} {s.rejected} of {s.received} "
                         f"received ({s.state}{processes}){error}")
    return "\n".join(lines)


# --- commands ---

def read_for_command(args: argparse.Namespace, command: str) -> Log | None:
    """The log (or segments) of ``args.log``; None after one error line naming the file. Files of different
    runs raise :class:`~dtpf.recording.logfile.MixedRunsError` (the command's one line, exit code 2)."""
    try:
        return read_logs(args.log) if isinstance(args.log, list) else read_log(args.log)
    except MixedRunsError:
        raise
    except LogError as error:
        print(f"dtpf {command}: error: {error}", file=sys.stderr)
        return None


def cmd_info(args: argparse.Namespace) -> int:
    """``dtpf info LOG``: 0 when the file could be read (even damaged), 1 when it is no MCAP log."""
    log = read_for_command(args, "info")
    if log is None:
        return 1
    info = log_info(log)
    print(json.dumps(info_json(info), indent=2) if getattr(args, "json", False) else format_info(info))
    return 0


def info_json(info: LogInfo) -> dict:
    """:class:`LogInfo` as plain JSON values (``dtpf info --json``, like ``mcap info --json``)."""
    from dataclasses import asdict

    out = asdict(info)
    out["path"] = str(info.path)
    out["duration_s"] = info.duration_s
    return out


def cmd_summary(args: argparse.Namespace) -> int:
    """``dtpf summary LOG``: 0 when the file could be read (even damaged), 1 when it is no MCAP log."""
    log = read_for_command(args, "summary")
    if log is None:
        return 1
    summary = summarise(log)
    print(format_summary(summary))
    if getattr(args, "config_out", None) is not None:
        from dtpf.messages.config import write_config_file

        configs = [t for t in summary.twins if t.config is not None]
        if len(configs) != 1:
            print(f"dtpf summary: error: --config-out needs one twin with a recorded configuration, the log has "
                  f"{len(configs)}", file=sys.stderr)
            return 1
        write_config_file(configs[0].config, args.config_out)
        print(f"wrote the run configuration to {args.config_out} (dtpf launch --config {args.config_out} "
              f"runs it again)", file=sys.stderr)
    return 0


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or (b.exists() and a.samefile(b))
    except OSError:
        return False


def cmd_recover(args: argparse.Namespace) -> int:
    """``dtpf recover LOG -o OUT``: 0 when OUT was written (even if data was lost), 1 when nothing could
    be read, 2 when OUT is LOG."""
    source, out = Path(args.log), Path(args.output)
    if _same_file(source, out):
        print(f"dtpf recover: error: {out} is the log being recovered; choose another output file",
              file=sys.stderr)
        return 2
    log = read_for_command(args, "recover")
    if log is None:
        return 1
    if not log.messages:
        print(f"dtpf recover: error: nothing to recover from {source}: {log.problem or 'the log holds no message'}",
              file=sys.stderr)
        return 1
    try:
        written = write_log(log, out)
    except LogError as error:
        print(f"dtpf recover: error: {error}", file=sys.stderr)
        return 1
    last = _last_estimates(log)
    lines = [f"read          {source} ({log.size:,} bytes)", *_state("state", log.complete, log.problems, 14),
             f"wrote         {out}: {written:,} messages on {len(log.channels)} channels, "
             f"{len(log.schemas)} schemas (a finished MCAP, lz4 chunks)"]
    if last:
        lines.append("last estimate " + ", ".join(f"step {step} ({twin})" for twin, step in last.items()))
    lines.append(f"lost          {_lost(log)}")
    print("\n".join(lines))
    return 0


def _lost(log: Log) -> str:
    """What recovering ``log`` cannot bring back, in words."""
    if log.problem is None:
        return "nothing"
    cut = log.cut
    if log.complete:
        return "nothing recorded after the footer; see the problems above for damage inside the file"
    rebuilt = "the summary and footer are rebuilt"
    if cut is not None and log.data_end:
        return f"no message (the file ends in its summary section); {rebuilt}"
    if cut is not None and cut.compression is not None:
        missing = cut.chunk_data_length - cut.chunk_data_available
        return (f"the part of the chunk at byte {cut.offset:,} past its last complete message ({missing:,} of its "
                f"{cut.chunk_data_length:,} bytes of records are not in the file) and anything recorded after it, "
                f"which the file cannot count; {rebuilt}")
    if cut is not None and cut.name == "MESSAGE_INDEX":
        return (f"no message of the file (it ends in a message index), but whatever the recorder had not yet "
                f"written; {rebuilt}")
    return f"everything after byte {log.read_to:,}, which the file cannot count; {rebuilt}"


def _last_estimates(log: Log) -> dict[str, int]:
    last: dict[str, int] = {}
    for _, message in log.decoded(lambda topic: topic.endswith("/entity/estimate")):
        if isinstance(message, Estimate):
            last[message.twin_id] = max(last.get(message.twin_id, 0), message.step)
    return last


def register(subparsers) -> None:
    """Add ``info``, ``summary`` and ``recover`` to ``subparsers`` (from ``parser.add_subparsers()``).

    Each subcommand sets ``handler``: a function of the parsed arguments that returns the exit code.
    """
    info = subparsers.add_parser(
        "info", help="what an MCAP log holds: size, state, time range, topics, schemas",
        description="Describe an MCAP log like 'mcap info': file size, complete or damaged (and what is missing), "
                    "time range, message count, per topic the count, message encoding, schema and first and last "
                    "step, the run and twin ids in the messages, and the schemas. A damaged file is read as far "
                    "as it goes. Exit code 0 when the file could be read, 1 when it is not an MCAP log.")
    info.add_argument("log", type=Path, metavar="LOG", help="MCAP file written by dtpf")
    info.add_argument("--json", action="store_true", help="print the same as one JSON object")
    info.set_defaults(handler=cmd_info)

    summary = subparsers.add_parser(
        "summary", help="per twin: steps, RMSE, ESS, resamplings, PS, degraded steps, rejected messages",
        description="Summarise the run recorded in an MCAP log, per twin: steps, RMSE against the recorded "
                    "truth, mean and minimum ESS, resamplings, the PS trajectory (commanded by the system layer "
                    "and applied by the entity), degraded steps, and the last status of each layer (messages "
                    "received and rejected, last error). On a damaged file it says first what is missing. "
                    "Exit code 0 when the file could be read, 1 when it is not an MCAP log, 2 when the files "
                    "are not of one run.")
    summary.add_argument("log", type=Path, nargs="+", metavar="LOG",
                         help="MCAP file written by dtpf; several: the segments of one run, in any order (dtpf "
                              "launch names them when its recorder was restarted); files of different runs (run "
                              "id, configuration or entity process) are refused")
    summary.add_argument("--config-out", type=Path, default=None, metavar="FILE",
                         help="also write the run's configuration as TOML, for 'dtpf launch --config FILE'")
    summary.set_defaults(handler=cmd_summary)

    recover = subparsers.add_parser(
        "recover", help="rewrite a damaged MCAP log as a valid file with every message that can be read",
        description="Read a damaged MCAP log (no footer, a cut last chunk) as far as it goes, including the "
                    "complete messages inside a cut chunk, and write them to a new, finished MCAP file (same "
                    "schemas, channels and messages, lz4 chunks). Exit code 0 when OUT was written, even if "
                    "data was lost; 1 when nothing could be read; 2 when OUT is LOG.")
    recover.add_argument("log", type=Path, metavar="LOG", help="MCAP file to recover (never modified)")
    recover.add_argument("--output", "-o", type=Path, required=True, metavar="OUT",
                         help="file to write (replaced if it exists; must not be LOG)")
    recover.set_defaults(handler=cmd_recover)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.logs.summary",
                                     description="Inspect and recover dtpf MCAP logs.")
    register(parser.add_subparsers(dest="command", metavar="COMMAND", required=True))
    args = parser.parse_args(argv)
    from dtpf.scripts.console import run_command
    return run_command(parser, args)


if __name__ == "__main__":
    sys.exit(main())
