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

A driven twin (several sensors, controls, time steps) takes its observations
and controls through :class:`DrivenIntake`: per-sensor sequence checks, then
stamp order within the reorder window, then each step's drive.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from dtpf.entity.timeline import Reorder, TimeError, Timeline
from dtpf.messages.models import ObservationCounts

__all__ = ["ObservationIntake", "Rejection", "DrivenIntake", "LiveStep"]


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


@dataclass(frozen=True)
class LiveStep:
    """An observation of a driven twin, released in stamp order: one filter step (or the end of the stream)."""

    values: list
    truth: list | None
    sensor: str | None
    #: How the step is reached from the one before (None: the first step).
    drive: object
    #: The observation's time, ns.
    stamp: int
    end: bool = False


class DrivenIntake:
    """The live intake of a driven twin: observations of several sensors and controls, in stamp order.

    Each sensor numbers its own observations (an :class:`ObservationIntake` per sensor checks them); the
    control source numbers its controls. Accepted ones wait in a :class:`~dtpf.entity.timeline.Reorder` for
    ``window`` ns of stamp time, then come out in stamp order (controls before observations of the same
    stamp, sensors in the model's order); one older than what came out already is late, counted and
    skipped. A released control is held (:class:`~dtpf.entity.timeline.Timeline`), a released observation
    becomes a :class:`LiveStep` with its drive::

        intake = DrivenIntake(ModelCalls(model), state_dim=3, window=100_000_000)
        intake.observation(message)      # None: taken, else a Rejection
        intake.control(message)
        step = intake.take()              # the next LiveStep, or None
    """

    def __init__(self, calls, state_dim: int, window: int):
        self.calls = calls
        self.intakes = {name: ObservationIntake(m, state_dim) for name, m in calls.sensors.items()}
        self.rank = {name: i + 1 for i, name in enumerate(calls.sensors)}
        self.reorder = Reorder(window)
        self.timeline = Timeline(len(calls.controls), piecewise=calls.takes_dt)
        self.late = 0
        self.unknown_sensor = 0
        self.controls = 0
        self.controls_rejected = 0
        self.control_sequence = 0
        #: The observation stream has ended; :attr:`controls_ended`: the control stream has (or has none).
        self.ended = False
        self.controls_ended = not calls.controls
        self.flushed = False
        self._steps = deque()

    def observation(self, message) -> Rejection | None:
        """Take an :class:`~dtpf.messages.models.Observation` (or the end of the stream)."""
        sensor = message.sensor
        intake = self.intakes.get(sensor)
        if intake is None:
            self.unknown_sensor += 1
            known = ", ".join(str(name) for name in self.intakes)
            return Rejection("observation from a sensor the model does not have",
                             f"observation {message.step} from sensor {sensor!r}; the model's sensors: {known}")
        verdict = intake.check(message.step, message.values, message.truth, message.end)
        if verdict is not None:
            return verdict
        if message.end:
            self.ended = True
            if self.controls_ended:
                self.finish()
            return None
        stamp = message.stamp.to_ns()
        if not self.reorder.push(stamp, self.rank[sensor], message):
            intake.accepted -= 1
            self.late += 1
            return Rejection("late observation (stamped before one filtered already, beyond the reorder window)",
                             f"observation {message.step} of {sensor or 'the sensor'} at {stamp} ns is before "
                             f"{self.reorder.released} ns, filtered already")
        self._release(self.reorder.ready())
        return None

    def control(self, message) -> Rejection | None:
        """Take a :class:`~dtpf.messages.models.Control` (or the end of the control stream)."""
        c = len(self.calls.controls)
        if message.end:
            if message.step <= self.control_sequence:
                self.controls_rejected += 1
                return Rejection("late or repeated control (sequence number not above the last)",
                                 f"the end of the controls, {message.step}, arrived after {self.control_sequence}")
            self.controls_ended = True
            if self.ended:
                self.finish()
            return None
        if len(message.control) != c:
            self.controls_rejected += 1
            return Rejection("control with the wrong number of values",
                             f"control {message.step} has {len(message.control)} values, the model's control has {c}")
        if message.step <= self.control_sequence:
            self.controls_rejected += 1
            return Rejection("late or repeated control (sequence number not above the last)",
                             f"control {message.step} arrived after {self.control_sequence}")
        if not self.reorder.push(message.stamp.to_ns(), 0, message):
            self.controls_rejected += 1
            return Rejection("late control (stamped before a step filtered already, beyond the reorder window)",
                             f"control {message.step} at {message.stamp.to_ns()} ns is before a filtered step")
        self.control_sequence = message.step
        self.controls += 1
        self._release(self.reorder.ready())
        return None

    def _release(self, items) -> None:
        for message in items:
            stamp = message.stamp.to_ns()
            if not hasattr(message, "sensor"):  # a control
                try:
                    self.timeline.control(stamp, message.control)
                except (TimeError, ValueError):
                    self.controls -= 1
                    self.controls_rejected += 1
                continue
            drive = self.timeline.step(stamp)
            self._steps.append(LiveStep(list(message.values), message.truth, message.sensor, drive, stamp))

    @property
    def ready(self) -> int:
        """Steps released in stamp order and not taken yet."""
        return len(self._steps)

    def finish(self) -> None:
        """Release everything held, in stamp order: the observations have ended (and the controls, or the
        caller waited long enough for their end)."""
        if not self.flushed:
            self.flushed = True
            self._release(self.reorder.flush())

    def take(self) -> LiveStep | None:
        """The next step in stamp order; once everything held is out after the end, a LiveStep with ``end``;
        else None."""
        if self._steps:
            return self._steps.popleft()
        if self.flushed:
            return LiveStep([], None, None, None, 0, end=True)
        return None

    def counts(self) -> ObservationCounts:
        """The counters of every sensor, summed, and the controls'."""
        intakes = self.intakes.values()
        return ObservationCounts(
            accepted=sum(i.accepted for i in intakes), duplicate=sum(i.duplicate for i in intakes),
            out_of_order=sum(i.out_of_order for i in intakes), wrong_length=sum(i.wrong_length for i in intakes),
            malformed=sum(i.malformed_count for i in intakes), missed=sum(i.missed for i in intakes),
            last_sequence=max(i.last_sequence for i in intakes), late=self.late,
            unknown_sensor=self.unknown_sensor, controls=self.controls, controls_rejected=self.controls_rejected)

    @property
    def last_sequence(self) -> int:
        """The highest sequence number any sensor had accepted."""
        return max(i.last_sequence for i in self.intakes.values())

    def malformed(self) -> None:
        """Count a message that did not decode (on the first sensor's counter)."""
        next(iter(self.intakes.values())).malformed()
