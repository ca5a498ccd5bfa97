"""Messages the recorder missed and could not recover: noted as they happen, read back as steps.

Every publisher of a twin keeps its last messages in a cache (Zenoh's advanced
publisher, :func:`dtpf.shell.bus.publisher`) and numbers them; the recorder's
advanced subscriber recovers a gap in the numbers from that cache, and is told
of what the cache no longer held (a partition longer than the cache). That news
names the publisher and a count only: :class:`Gaps` follows which key and step
each publisher's last recorded message had, and turns each gap into a
:class:`~dtpf.messages.models.Missed` message once the publisher's next message
(or the end of the recording) closes it::

    gaps = Gaps()
    gaps.heard(source, key, message)          # every message written, with its publisher
    gaps.missed(source, count)                # a gap the cache could not fill
    for note in gaps.closed(source, message): # the gaps the next message of that publisher closes
        recording.write(keys.key_for(note), encode(note))

:func:`lost_steps` reads the notes of a log back as the steps of each topic that
the recorder declared lost.
"""
from __future__ import annotations

from dataclasses import dataclass

from dtpf.messages.models import Message, Missed

__all__ = ["Gaps", "lost_steps", "MAX_SOURCES", "MAX_LISTED"]

#: Publishers :class:`Gaps` follows (the oldest forgotten first): a fleet's twins have a handful each.
MAX_SOURCES = 1 << 16
#: Most steps :func:`lost_steps` lists per topic (a forged count of 4294967295 would list billions).
MAX_LISTED = 100_000


@dataclass
class _Last:
    key: str
    twin: str
    run_id: str
    step: int


class Gaps:
    """The gaps in each publisher's messages the recorder could not fill, as :class:`Missed` messages.

    ``twin`` and ``run_id``: what a note is filed under when its publisher never had a message recorded
    (none of its key or twin is known).
    """

    def __init__(self, twin: str, run_id: str):
        self.twin, self.run_id = twin, run_id
        self._last: dict[str, _Last] = {}
        self._open: dict[str, int] = {}  # source -> messages missed since its last recorded one
        #: Messages missed in all, and gaps.
        self.messages = 0
        self.gaps = 0

    def heard(self, source: str | None, key: str, message: Message) -> list[Missed]:
        """Note a recorded ``message`` of ``source`` on ``key``; returns the note of the gap it closes (if any),
        to be written."""
        if source is None:
            return []
        notes = self.closed(source, message.step)
        if source not in self._last and len(self._last) >= MAX_SOURCES:
            del self._last[next(iter(self._last))]
        self._last.pop(source, None)
        self._last[source] = _Last(key, message.twin_id, message.run_id, message.step)
        return notes

    def missed(self, source: str, count: int) -> None:
        """``count`` messages of ``source`` could not be recovered (before its next one)."""
        self.messages += count
        if source not in self._open:
            self.gaps += 1
            if len(self._open) >= MAX_SOURCES:
                del self._open[next(iter(self._open))]
        self._open[source] = self._open.get(source, 0) + count

    def closed(self, source: str, before_step: int | None) -> list[Missed]:
        """The note of ``source``'s open gap, closed by a message of ``before_step`` (None: by the end)."""
        count = self._open.pop(source, None)
        if count is None:
            return []
        last = self._last.get(source)
        if last is None:
            return [Missed(run_id=self.run_id, twin_id=self.twin, step=0, key="", source=source[:300],
                           count=count, after_step=None, before_step=before_step)]
        return [Missed(run_id=last.run_id, twin_id=last.twin, step=last.step + 1, key=last.key[:300],
                       source=source[:300], count=count, after_step=last.step, before_step=before_step)]

    def close_all(self) -> list[Missed]:
        """The notes of every gap still open (the recording ends)."""
        return [note for source in list(self._open) for note in self.closed(source, None)]


def lost_steps(notes: list[Missed]) -> dict[str, list[int]]:
    """The steps each key lost, by key, from the recorder's :class:`Missed` notes of one twin.

    A note's steps are those after ``after_step`` and before ``before_step``; with no later message
    (``before_step`` None), the ``count`` steps after ``after_step``. Status topics (many messages a step, or
    none) are left out, as are notes without a key; at most :data:`MAX_LISTED` steps a key.
    """
    lost: dict[str, set[int]] = {}
    for note in notes:
        if not note.key or note.key.endswith("/status") or note.after_step is None:
            continue
        end = note.before_step if note.before_step is not None else note.after_step + note.count + 1
        steps = lost.setdefault(note.key, set())
        first = note.after_step + 1
        steps.update(range(first, min(end, first + max(0, MAX_LISTED - len(steps)))))
    return {key: sorted(steps) for key, steps in sorted(lost.items()) if steps}
