"""Zenoh queryables that answer off the caller's path, bounded, and the client side of a question.

A service answers a question with a :class:`Queryable`: Zenoh's callback
only checks the rate bound and puts the query in the bounded queue of a
:class:`Worker`, a thread of this module that computes the answer and replies
(JSON), so answering never runs on a service's own loop and never blocks
Zenoh's thread. A query beyond the rate bound, or one that finds the queue
full, gets an error reply saying so; an answer that fails (a bad selector, a
bound the answer would break, anything else) gets an error reply with its one
line, is logged once per kind and counted, and the service goes on::

    answers = Queryable(session, "dtpf/ungm-1/entity/state", lambda key, text: b'{...}', log=log)
    ...
    answers.close()

The client::

    replies = ask(session, "dtpf/ungm-1/entity/state", "particles=true", timeout=5.0)
    replies.first()          # the first answer's JSON (dict), or QueryError naming the error replies
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time
from dataclasses import dataclass, field

import zenoh

from dtpf.messages.errors import DtpfError

__all__ = ["Queryable", "Worker", "worker", "RateBound", "Replies", "QueryError", "ask", "MAX_ERROR_TEXT"]

#: Longest error reply (characters).
MAX_ERROR_TEXT = 500
#: Queries a worker holds waiting for it; more are refused.
QUEUE_SIZE = 32


class QueryError(DtpfError, RuntimeError):
    """A question that got no answer: the error replies, or none within the timeout."""


class RateBound:
    """At most ``rate`` queries a second on average, ``burst`` at once (a token bucket); thread-safe."""

    def __init__(self, rate: float, burst: int):
        self.rate, self.burst = float(rate), float(burst)
        self._tokens, self._last = float(burst), time.monotonic()
        self._lock = threading.Lock()

    def take(self) -> bool:
        """True if one more query is allowed now (and count it)."""
        with self._lock:
            now = time.monotonic()
            self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate)
            self._last = now
            if self._tokens < 1.0:
                return False
            self._tokens -= 1.0
            return True


class Worker:
    """A daemon thread answering the queries of its bounded queue, one at a time."""

    def __init__(self, name: str, size: int = QUEUE_SIZE):
        self.name = name
        self._queue: queue.Queue = queue.Queue(maxsize=size)
        self._thread = threading.Thread(target=self._run, name=f"answers-{name}", daemon=True)
        self._thread.start()

    def submit(self, queryable: "Queryable", query: zenoh.Query) -> bool:
        """Queue ``query`` for ``queryable``; False when the queue is full."""
        try:
            self._queue.put_nowait((queryable, query))
            return True
        except queue.Full:
            return False

    def _run(self) -> None:
        while True:
            queryable, query = self._queue.get()
            try:
                queryable.answer_now(query)
            except Exception:  # the session closed under it: nothing to reply to
                pass
            finally:
                del query


_WORKERS: dict[str, Worker] = {}
_WORKERS_LOCK = threading.Lock()


def worker(name: str) -> Worker:
    """This process's worker of that name (one thread each, made on first use): the twins of a process share
    them, so a quick question (state) never waits behind a long one (forecast) of another kind."""
    with _WORKERS_LOCK:
        found = _WORKERS.get(name)
        if found is None:
            found = _WORKERS[name] = Worker(name)
        return found


@dataclass
class Counts:
    """What a queryable did: answered, refused (rate, full queue), failed (an error reply)."""

    answered: int = 0
    refused: int = 0
    failed: int = 0
    kinds: set = field(default_factory=set)


class Queryable:
    """A Zenoh queryable on ``key`` whose answers ``answer(key, parameters) -> bytes`` (JSON) the worker
    ``on`` computes; at most ``rate`` queries a second (``burst`` at once), the rest refused with an error reply.

    ``answer`` raises :class:`~dtpf.messages.errors.DtpfError` (a ValueError or RuntimeError with one line)
    for what the question cannot have: that line is the error reply. Anything else is logged (once per
    kind) and replied as an internal error.
    """

    def __init__(self, session: zenoh.Session, key: str, answer, *, on: Worker | None = None,
                 rate: float = 50.0, burst: int = 100, log: logging.Logger | logging.LoggerAdapter | None = None):
        self.key = key
        self.answer = answer
        self.worker = on or worker("answers")
        self.bound = RateBound(rate, burst)
        self.log = log or logging.getLogger("dtpf.queries")
        self.counts = Counts()
        self._lock = threading.Lock()
        self._queryable = session.declare_queryable(key, self._on_query)

    def _on_query(self, query: zenoh.Query) -> None:
        """Zenoh's thread: the rate bound and the queue only (a refusal is an error reply, sent at once)."""
        if not self.bound.take():
            self._refuse(query, f"too many queries: {self.key} answers at most {self.bound.rate:g} a second")
        elif not self.worker.submit(self, query):
            self._refuse(query, f"busy: {self.key} has {QUEUE_SIZE} questions waiting; ask again later")

    def _refuse(self, query: zenoh.Query, text: str) -> None:
        with self._lock:
            self.counts.refused += 1
        try:
            query.reply_err(text)
        except zenoh.ZError:
            pass

    def answer_now(self, query: zenoh.Query) -> None:
        """Compute the answer of ``query`` and reply (the worker's thread)."""
        with query:
            key = str(query.key_expr)
            reply_on = key if "*" not in key else self.key
            try:
                body = self.answer(reply_on, str(query.parameters))
            except DtpfError as error:
                self._failed(query, type(error).__name__, " ".join(str(error).split()))
                return
            except Exception as error:  # a fault of ours or of a user's model: said, counted, survived
                self._failed(query, type(error).__name__, f"internal error: {type(error).__name__}: {error}",
                             internal=True)
                return
            query.reply(reply_on, body, encoding=zenoh.Encoding.APPLICATION_JSON)
            with self._lock:
                self.counts.answered += 1

    def _failed(self, query: zenoh.Query, kind: str, text: str, internal: bool = False) -> None:
        text = text[:MAX_ERROR_TEXT]
        with self._lock:
            self.counts.failed += 1
            first = kind not in self.counts.kinds and len(self.counts.kinds) < 100
            self.counts.kinds.add(kind)
        if first:
            (self.log.warning if internal else self.log.info)(
                "refused a query on %s (%s; further ones are counted): %s", self.key, kind, text)
        query.reply_err(text)

    def close(self) -> None:
        try:
            self._queryable.undeclare()
        except zenoh.ZError:
            pass


@dataclass
class Replies:
    """The replies to one question: JSON answers (key, dict) and error texts."""

    key: str
    answers: list[tuple[str, dict]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def first(self) -> dict:
        """The first answer; QueryError with the error replies, or saying none came."""
        if self.answers:
            return self.answers[0][1]
        if self.errors:
            raise QueryError(self.errors[0] if len(set(self.errors)) == 1 else "; ".join(sorted(set(self.errors))))
        raise QueryError(f"no answer on {self.key}")


def ask(session: zenoh.Session, key: str, parameters: str = "", timeout: float = 10.0,
        max_bytes: int | None = None) -> Replies:
    """Ask ``key`` with ``parameters``; every reply within ``timeout`` seconds (an answer that is no JSON
    object, or more than ``max_bytes``, is an error of the replies)."""
    replies = Replies(key)
    handler = session.get(f"{key}?{parameters}" if parameters else key, timeout=timeout,
                          consolidation=zenoh.ConsolidationMode.NONE)
    for reply in handler:
        if reply.ok is not None:
            data = reply.ok.payload.to_bytes()
            if max_bytes is not None and len(data) > max_bytes:
                replies.errors.append(f"an answer of {len(data)} bytes, more than {max_bytes}")
                continue
            try:
                body = json.loads(data)
            except (ValueError, UnicodeDecodeError):
                replies.errors.append(f"an answer on {reply.ok.key_expr} that is no JSON")
                continue
            if not isinstance(body, dict):
                replies.errors.append(f"an answer on {reply.ok.key_expr} that is no JSON object")
                continue
            replies.answers.append((str(reply.ok.key_expr), body))
        else:
            replies.errors.append(reply.err.payload.to_bytes().decode("utf-8", "replace")[:MAX_ERROR_TEXT])
    return replies
