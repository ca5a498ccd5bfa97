"""What the recorder writes: each message a service would take, as received; a bounded sample of the rest.

A message is decoded and checked as a service would (:func:`~dtpf.messages.codec.decode_for_key`: the
topic's class, the twin and layer of its key), belongs to the run being recorded (unless every twin is),
and fits the run's shape (N, d, T); then its payload is written unchanged. Without access control a forger
can publish a well-formed estimate of any step: every copy is kept in the order received, up to MAX_COPIES
of one (key, step). A rejected message is counted in the recorder's status, and a sample of it (its first
bytes, base64) written as a ``Rejected`` message, at most MAX_SAMPLES in all and MAX_SAMPLES_PER_KIND of one
kind of reason.

What the recorder missed and its publishers' caches could no longer give back (a partition longer than the
cache) is noted as a ``Missed`` message of the twin (:mod:`dtpf.recording.missed`) when the publisher's next
message, or the end of the recording, closes the gap.
"""
from __future__ import annotations

import base64

from dtpf.messages import keys
from dtpf.messages.admission import kind_of
from dtpf.messages.codec import MessageError, decode_for_key, encode
from dtpf.messages.models import MAX_REJECTED_SAMPLE, Estimate, Rejected
from dtpf.recording.missed import Gaps

__all__ = ["MAX_COPIES", "MAX_SAMPLES", "MAX_SAMPLES_PER_KIND", "MAX_TRACKED_STEPS", "Admission"]

#: Rejected payloads the recorder keeps a sample of: in all, and of one kind of reason.
MAX_SAMPLES, MAX_SAMPLES_PER_KIND = 1000, 10
#: Estimates of one (key, step) the recorder keeps; the (key, step) pairs it counts them for, newest kept.
MAX_COPIES, MAX_TRACKED_STEPS = 8, 1 << 16
#: Gaps the recorder's log names one by one; later ones are summed up when the recording ends.
MAX_GAPS_LOGGED = 20


class Admission:
    """What the recorder writes: the run's valid messages; a bounded sample of the rest.

    ``shell`` is the recorder's :class:`~dtpf.shell.service.ServiceShell` (its ``received`` count,
    ``reject``, ``shape``, ``config`` and ``header``); ``silences`` its
    :class:`~dtpf.scripts.record.Silences`, told of every message written, or None.
    """

    def __init__(self, shell, all_twins: bool, silences=None):
        self.shell = shell
        self.all_twins = all_twins
        self.silences = silences
        self.samples = 0
        self.samples_of: dict[str, int] = {}
        self.estimate_copies: dict[tuple[str, int], int] = {}  # by (key, step), oldest first
        #: The gaps in each publisher's messages that could not be recovered.
        config = getattr(shell, "config", None)  # notes of an unknown publisher go to the recorder's twin
        self.gaps = Gaps(getattr(config, "twin", "recorder"), getattr(config, "run_id", "recorder"))

    def record(self, recording, item) -> bool:
        """Write ``item`` if a service would take it (True); else count it and maybe sample it. An item that
        says messages were missed (``item.missed``) opens a gap of its publisher."""
        shell = self.shell
        missed = getattr(item, "missed", 0)  # items of a plain inbox, or a replay, have none of these
        if missed:  # Zenoh's word: the steps are noted when the numbers show the gap (or at the end)
            self.gaps.missed(item.source, missed)
            return False
        shell.received += 1
        try:
            message = decode_for_key(item.key, item.payload)
        except MessageError as error:
            return self._reject(recording, item, error.reason, str(error))
        if not self.all_twins and message.run_id != shell.config.run_id:
            return self._reject(recording, item, "message of another run",
                                f"a message of run {message.run_id!r} on {item.key}, recording run "
                                f"{shell.config.run_id!r}")
        misfit = shell.shape.misfit(message) if shell.shape is not None else None
        if misfit is not None:
            return self._reject(recording, item, misfit.kind, misfit.detail)
        if isinstance(message, Estimate):
            # Without access control a forger can publish a well-formed estimate of any step, early or
            # twice. Every one is kept, in the order received, so a forgery never costs the real estimate
            # its place; the log tools say which steps had more than one (scripts.logs). Only copies past
            # MAX_COPIES of one step are refused, so a flood of one step cannot grow the log without bound.
            copies = self.estimate_copies.get((item.key, message.step), 0)
            if copies >= MAX_COPIES:
                return self._reject(recording, item, "too many estimates of one step",
                                    f"estimate {copies + 1} of step {message.step} on {item.key}")
            if len(self.estimate_copies) >= MAX_TRACKED_STEPS:
                del self.estimate_copies[next(iter(self.estimate_copies))]
            self.estimate_copies[item.key, message.step] = copies + 1
        recording.write(item.key, item.payload)
        for note in self.gaps.heard(getattr(item, "source", None), getattr(item, "sn", None), item.key, message):
            self._note(recording, note)
        if self.silences is not None:
            self.silences.heard(message)
        return True

    def _note(self, recording, note) -> None:
        recording.write(keys.key_for(note), encode(note))
        if self.gaps.gaps <= MAX_GAPS_LOGGED:
            span = f"after step {note.after_step}" if note.after_step is not None else "before any recorded"
            span += f", before step {note.before_step}" if note.before_step is not None else ", to the end"
            self.shell.log.warning("twin %s: %d messages on %s lost (%s)", note.twin_id, note.count,
                                   note.key or "an unknown key", span)

    def finish(self, recording) -> None:
        """Note the gaps still open: the recording ends before their publishers' next messages."""
        for note in self.gaps.close_all():
            self._note(recording, note)
        if self.gaps.gaps > MAX_GAPS_LOGGED:
            self.shell.log.warning("missed %d messages in %d gaps in all that the publishers' caches no longer "
                                   "held", self.gaps.messages, self.gaps.gaps)
        elif self.gaps.gaps:
            self.shell.log.info("missed %d messages in %d gaps that the publishers' caches no longer held; the "
                                "log notes them on the twins' recorder/missed topics", self.gaps.messages,
                                self.gaps.gaps)

    def _reject(self, recording, item, reason: str, detail: str) -> bool:
        shell = self.shell
        self.gaps.passed(getattr(item, "source", None), getattr(item, "sn", None))
        shell.reject(reason, detail, key=item.key)
        kind = kind_of(reason)
        if self.samples < MAX_SAMPLES and self.samples_of.get(kind, 0) < MAX_SAMPLES_PER_KIND:
            self.samples += 1
            self.samples_of[kind] = self.samples_of.get(kind, 0) + 1
            sample = Rejected(**shell.header(0), key=item.key[:300], reason=detail[:500], size=len(item.payload),
                              sample=base64.b64encode(item.payload[:MAX_REJECTED_SAMPLE]).decode("ascii"))
            recording.write(keys.key_for(sample), encode(sample))
        return False
