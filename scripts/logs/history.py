"""The answer to a ``history`` question: the recorded messages a selector chooses, as JSON.

Each message is the object a line of ``dtpf cat --json`` holds (``{topic,
log_time, message}``, a particle set's arrays as lists), so a history answer
equals ``dtpf cat`` of the same steps and topics::

    log = read_log("run.mcap")
    body = history_answer(log, "ungm-1", queries.parse("history", "steps=3:5"))
    json.loads(body)["messages"]        # the estimates of steps 3, 4, 5 in file order

An answer that would carry more than the selector's ``limit`` messages or
``max_bytes`` bytes is refused (:class:`AnswerTooLarge`, naming the bound)
rather than cut.
"""
from __future__ import annotations

import json

from dtpf.messages.queries import MAX_BYTES, MAX_LIMIT, HistorySelector, SelectorError
from dtpf.recording.logfile import Log
from dtpf.scripts.logs.select import as_json, choose

__all__ = ["AnswerTooLarge", "history_answer", "history_entries"]

#: What JSON lists of float64 weigh against the raw bytes of a particle set, at least (a bound checked before
#: a set is turned into lists).
_LIST_BYTES_PER_RAW_BYTE = 1.5


class AnswerTooLarge(SelectorError):
    """The selection holds more than one answer may carry; the text names the bound and how to narrow it."""


def history_entries(log: Log, twin: str, selector: HistorySelector) -> list[dict]:
    """The ``{topic, log_time, message}`` objects of ``twin``'s messages that ``selector`` chooses, in file
    order; AnswerTooLarge once they pass its ``limit`` or ``max_bytes``."""
    entries, size = [], 2
    for item, message in choose(log, topics=selector.topics, twin=twin, keep_run_level=False):
        if not selector.holds_step(message.step) or not selector.holds_time(item.log_time):
            continue
        if len(entries) >= selector.limit:
            raise AnswerTooLarge(f"the selection holds more than limit={selector.limit} messages (at most "
                                 f"{MAX_LIMIT}); narrow steps= or time=, or raise limit=")
        if len(item.data) * _LIST_BYTES_PER_RAW_BYTE > selector.max_bytes:
            raise AnswerTooLarge(f"the message of step {message.step} on {item.topic} alone is more than "
                                 f"max_bytes={selector.max_bytes} bytes as JSON (at most {MAX_BYTES})")
        entry = {"topic": item.topic, "log_time": item.log_time, "message": as_json(message)}
        size += len(json.dumps(entry)) + 1
        if size > selector.max_bytes:
            raise AnswerTooLarge(f"the selection is more than max_bytes={selector.max_bytes} bytes of JSON "
                                 f"(at most {MAX_BYTES}); narrow steps=, time= or topics=, or raise max_bytes=")
        entries.append(entry)
    return entries


def history_answer(log: Log, twin: str, selector: HistorySelector) -> bytes:
    """The JSON answer: ``{"twin", "count", "messages": [...]}`` (:func:`history_entries`)."""
    entries = history_entries(log, twin, selector)
    return json.dumps({"twin": twin, "count": len(entries), "messages": entries}).encode()
