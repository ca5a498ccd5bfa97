"""Which live observations become filter steps: the entity's intake, without transport.

A sensor numbers its measurements 1, 2, ... (the ``step`` of an
:class:`~dtpf.messages.models.Observation`). The intake accepts an observation
only if it is newer than the last one accepted and has the model's number of
values; everything else is counted by reason and skipped, and the filter
never stops for it::

    intake = ObservationIntake(obs_dim=2, state_dim=4)
    verdict = intake.check(sequence, values, truth)   # None: accepted, else a Rejection
    intake.counts()                                   # ObservationCounts for the status

Values are finite by construction of the message (the decoder rejects NaN and
infinity); a message that fails to decode is counted with :meth:`malformed`.
"""
from __future__ import annotations

from dataclasses import dataclass

from dtpf.messages.models import ObservationCounts

__all__ = ["ObservationIntake", "Rejection"]


@dataclass(frozen=True)
class Rejection:
    """Why an observation was not filtered: ``reason`` is one of a few fixed phrases (logged once
    each), ``detail`` the same with this observation's numbers."""

    reason: str
    detail: str

    def __str__(self) -> str:
        return self.detail


class ObservationIntake:
    """Sequence and shape checks of arriving observations, with the counts of each outcome.

    Parameters
    ----------
    obs_dim : int
        m, the number of values of one observation.
    state_dim : int
        d, the length of a truth vector, when the sensor sends one.
    """

    def __init__(self, obs_dim: int, state_dim: int):
        self.obs_dim = int(obs_dim)
        self.state_dim = int(state_dim)
        self.last_sequence = 0
        self.accepted = 0
        self.duplicate = 0
        self.out_of_order = 0
        self.wrong_length = 0
        self.malformed_count = 0
        self.missed = 0
        self.ended = False

    def check(self, sequence: int, values, truth=None, end: bool = False) -> Rejection | None:
        """Accept (None) or reject the observation numbered ``sequence``.

        An accepted one moves :attr:`last_sequence` on; a gap counts the
        numbers skipped as :attr:`missed`. ``end`` closes the stream when it is
        newer than the last accepted observation (an old end is out of order).
        """
        if sequence == self.last_sequence:
            self.duplicate += 1
            return Rejection("duplicate observation (its sequence number was filtered already)",
                             f"duplicate observation {sequence} (filtered already)")
        if sequence < self.last_sequence:
            self.out_of_order += 1
            return Rejection("late or out-of-order observation (sequence number below the last filtered)",
                             f"observation {sequence} arrived after {self.last_sequence}: late or out of order")
        if end:
            self.ended = True
            return None
        if len(values) != self.obs_dim:
            self.wrong_length += 1
            return Rejection("observation with the wrong number of values",
                             f"observation {sequence} has {len(values)} values, the model observes {self.obs_dim}")
        if truth is not None and len(truth) != self.state_dim:
            self.wrong_length += 1
            return Rejection("observation whose truth has the wrong length",
                             f"observation {sequence} carries a truth of {len(truth)} values, the state has "
                             f"{self.state_dim}")
        if self.last_sequence and sequence > self.last_sequence + 1:
            self.missed += sequence - self.last_sequence - 1
        self.last_sequence = sequence
        self.accepted += 1
        return None

    def malformed(self) -> None:
        """Count a message on the observation key that did not decode."""
        self.malformed_count += 1

    @property
    def rejected(self) -> int:
        return self.duplicate + self.out_of_order + self.wrong_length + self.malformed_count

    def counts(self) -> ObservationCounts:
        """The counters, as the entity's status carries them."""
        return ObservationCounts(accepted=self.accepted, duplicate=self.duplicate, out_of_order=self.out_of_order,
                                 wrong_length=self.wrong_length, malformed=self.malformed_count,
                                 missed=self.missed, last_sequence=self.last_sequence)
