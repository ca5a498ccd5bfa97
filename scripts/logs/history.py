"""The answer to a ``history`` question: the recorded messages a selector chooses, as JSON.

Each message is the object a line of ``dtpf cat --json`` holds (``{topic,
log_time, message}``, a particle set's arrays as lists), so a history answer
equals ``dtpf cat`` of the same steps and topics::

    log = read_log("run.mcap")
    body = history_answer(log, "ungm-1", queries.parse("history", "steps=3:5"))
    json.loads(body)["messages"]        # the estimates of steps 3, 4, 5 in file order

An answer that would carry more than the selector's ``limit`` messages or
``max_bytes`` bytes is refused (:class:`AnswerTooLarge`, naming the bound)
rather than cut. A service answering many questions keeps a
:class:`StepIndex`: each message is decoded once to learn its step, and a
question then decodes only the messages it chooses.
"""
from __future__ import annotations

import json
from array import array
from dataclasses import replace

from dtpf.messages.codec import MessageError
from dtpf.messages.queries import MAX_BYTES, MAX_LIMIT, HistorySelector, SelectorError
from dtpf.recording.logfile import Log
from dtpf.scripts.logs.play import topic_matcher
from dtpf.scripts.logs.select import as_json

__all__ = ["AnswerTooLarge", "StepIndex", "history_answer", "history_entries"]

#: What JSON lists of float64 weigh against the raw bytes of a particle set, at least (a bound checked before
#: a set is turned into lists).
_LIST_BYTES_PER_RAW_BYTE = 1.5


class AnswerTooLarge(SelectorError):
    """The selection holds more than one answer may carry; the text names the bound and how to narrow it."""


class StepIndex:
    """The step of each message of a log, decoded once and kept for the next questions, so that a question
    decodes only what it chooses; a log read again as it grows (a recorder's) keeps the steps of the messages
    it held before. One integer a message."""

    _UNKNOWN, _UNDECODABLE = -1, -2

    def __init__(self):
        self._steps = array("q")
        self._last: tuple | None = None  # (topic, log_time, sequence) of the last message indexed

    def _follow(self, log: Log) -> None:
        n = len(self._steps)
        if n and (n > len(log.messages) or _identity(log.messages[n - 1]) != self._last):
            self._steps = array("q")  # another log, or one that changed before its end: start again
            n = 0
        self._steps.extend([self._UNKNOWN] * (len(log.messages) - n))
        if log.messages:
            self._last = _identity(log.messages[-1])

    def steps_of(self, log: Log, indices: list[int]) -> list[int | None]:
        """The step of each message ``log.messages[i]`` (None: it does not decode)."""
        self._follow(log)
        unknown = [i for i in indices if self._steps[i] == self._UNKNOWN]
        if unknown:
            decoded = replace(log, messages=[log.messages[i] for i in unknown]).decoded()
            for i, (_, message) in zip(unknown, decoded):
                self._steps[i] = self._UNDECODABLE if isinstance(message, MessageError) else message.step
        return [None if self._steps[i] == self._UNDECODABLE else self._steps[i] for i in indices]


def _identity(item) -> tuple:
    return item.topic, item.log_time, item.sequence


def history_entries(log: Log, twin: str, selector: HistorySelector, index: StepIndex | None = None) -> list[dict]:
    """The ``{topic, log_time, message}`` objects of ``twin``'s messages that ``selector`` chooses, in file
    order (those of ``dtpf cat --twin TWIN --topics ... --steps A:B --json``); AnswerTooLarge once they pass its
    ``limit`` or ``max_bytes``. ``index``: the steps found by the questions before (a new one if None)."""
    matcher, wanted = topic_matcher(selector.topics), {}

    def chosen(topic: str) -> bool:
        if topic not in wanted:
            wanted[topic] = matcher(topic) and topic.split("/")[1:2] == [twin]
        return wanted[topic]

    candidates = [i for i, item in enumerate(log.messages) if chosen(item.topic) and selector.holds_time(item.log_time)]
    if selector.steps is not None:
        steps = (index or StepIndex()).steps_of(log, candidates)
        candidates = [i for i, step in zip(candidates, steps) if step is not None and selector.holds_step(step)]
    entries, size = [], 2
    for item, message in replace(log, messages=[log.messages[i] for i in candidates]).decoded():
        if isinstance(message, MessageError) or message.twin_id != twin:
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


def history_answer(log: Log, twin: str, selector: HistorySelector, index: StepIndex | None = None) -> bytes:
    """The JSON answer: ``{"twin", "count", "messages": [...]}`` (:func:`history_entries`)."""
    entries = history_entries(log, twin, selector, index)
    return json.dumps({"twin": twin, "count": len(entries), "messages": entries}).encode()
