"""Messages the recorder missed and could not recover: noted as they happen, read back as steps.

Every publisher of a twin keeps its last messages in a cache (Zenoh's advanced
publisher, :func:`dtpf.shell.bus.publisher`) and numbers them; the recorder's
advanced subscriber recovers a gap in the numbers from that cache and hands on
each publisher's messages in order, with their numbers. What the cache no longer
held shows as a jump in the numbers: :class:`Gaps` follows each publisher's last
number, key and step, and turns a jump into a :class:`~dtpf.messages.models.Missed`
message naming the steps on either side. Zenoh also says so itself (a sample-miss
listener, a count per publisher, which may come after the messages that follow
the gap); a count that no jump accounts for (the publisher's last messages, with
none after them) is noted when the recording ends::

    gaps = Gaps(twin, run_id)
    for note in gaps.heard(source, sn, key, message):  # every message written, with its publisher and number
        recording.write(keys.key_for(note), encode(note))
    gaps.missed(source, count)                         # Zenoh's news of a gap
    for note in gaps.close_all(): ...                  # the recording ends

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
class _Source:
    key: str
    twin: str
    run_id: str
    step: int
    sn: int
    said: int = 0       #: messages Zenoh said were missed
    noted: int = 0      #: messages noted as missed from jumps in the numbers


class Gaps:
    """The gaps in each publisher's messages the recorder could not fill, as :class:`Missed` messages.

    ``twin`` and ``run_id``: what a note is filed under when its publisher never had a message recorded
    (none of its key or twin is known).
    """

    def __init__(self, twin: str, run_id: str):
        self.twin, self.run_id = twin, run_id
        self._sources: dict[str, _Source] = {}
        self._said_unknown: dict[str, int] = {}  # misses of publishers with no message recorded yet
        #: Gaps noted.
        self.gaps = 0

    @property
    def messages(self) -> int:
        """Messages missed in all: as Zenoh said, or as the numbers show where they show more."""
        return sum(max(known.said, known.noted) for known in self._sources.values()) + \
            sum(self._said_unknown.values())

    def heard(self, source: str | None, sn: int | None, key: str, message: Message) -> list[Missed]:
        """Note a recorded ``message`` of ``source`` (number ``sn``) on ``key``; returns the note of the gap
        before it (if its number jumps), to be written."""
        if source is None or sn is None:
            return []
        known = self._sources.pop(source, None)
        notes = []
        if known is not None and sn > known.sn + 1:
            count = sn - known.sn - 1
            known.noted += count
            self.gaps += 1
            notes.append(Missed(run_id=known.run_id, twin_id=known.twin, step=known.step + 1, key=known.key[:300],
                                source=source[:300], count=count, after_step=known.step,
                                before_step=message.step))
        if known is None:
            if len(self._sources) >= MAX_SOURCES:
                del self._sources[next(iter(self._sources))]
            known = _Source(key, message.twin_id, message.run_id, message.step, sn,
                            said=self._said_unknown.pop(source, 0))
        known.key, known.twin, known.run_id, known.step, known.sn = (key, message.twin_id, message.run_id,
                                                                     message.step, sn)
        self._sources[source] = known  # the most recent last
        return notes

    def passed(self, source: str | None, sn: int | None) -> None:
        """A message of ``source`` numbered ``sn`` that was not recorded (rejected): its number is no gap."""
        known = self._sources.get(source) if source is not None and sn is not None else None
        if known is not None and sn > known.sn:
            known.sn = sn

    def missed(self, source: str, count: int) -> None:
        """Zenoh says ``count`` messages of ``source`` could not be recovered."""
        known = self._sources.get(source)
        if known is None:
            if source in self._said_unknown or len(self._said_unknown) < MAX_SOURCES:
                self._said_unknown[source] = self._said_unknown.get(source, 0) + count
            return
        known.said += count

    def close_all(self) -> list[Missed]:
        """The notes of what Zenoh said was missed and no jump has shown: the publishers' last messages (the
        recording ends)."""
        notes = []
        for source, known in self._sources.items():
            if known.said > known.noted:
                self.gaps += 1
                notes.append(Missed(run_id=known.run_id, twin_id=known.twin, step=known.step + 1,
                                    key=known.key[:300], source=source[:300], count=known.said - known.noted,
                                    after_step=known.step, before_step=None))
                known.noted = known.said
        for source, count in self._said_unknown.items():
            self.gaps += 1
            notes.append(Missed(run_id=self.run_id, twin_id=self.twin, step=0, key="", source=source[:300],
                                count=count, after_step=None, before_step=None))
        self._said_unknown.clear()
        return notes


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
