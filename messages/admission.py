"""Does a valid message fit this run? The checks after decoding.

A message can be well formed and still impossible to apply: a particle set of
the wrong N or dimension, an estimate of step 4294967295 in a run of 200
steps, a status from a layer that is not one of the run's processes. The
decoder cannot know the run; :class:`RunShape` does::

    shape = RunShape(particles=1000, dim=1, obs_dim=1, steps=200)
    problem = shape.misfit(message)      # None, or a Misfit(kind, detail)

``kind`` names the rule that failed without any of the message's numbers, so
a service logs each kind once however many messages break it; ``detail``
carries the numbers for the status's last error.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import NamedTuple

from dtpf.messages.models import Control, Estimate, Message, Observation, ParticleSet, PSCommand, WeightState
from dtpf.messages.names import OWN_ARM

__all__ = ["RunShape", "Misfit", "kind_of"]

#: The largest step any run may reach when its length is not known (a live run).
MAX_STEP = 2**31 - 1

_NUMBER = re.compile(r"-?\d+(\.\d+)?([eE][-+]?\d+)?")
_QUOTED = re.compile(r"'[^']*'|\"[^\"]*\"")
#: Longest kind of rejection (it is a dictionary key in every status).
MAX_KIND_LENGTH = 120


def kind_of(reason: str) -> str:
    """The kind of a rejection reason: the reason with its numbers and quoted values blanked.

    ``"step 7: shape (1, 1), expected (1000, 1)"`` and the same at step 8 are one kind.
    """
    text = _QUOTED.sub("'…'", reason)
    text = _NUMBER.sub("#", text)
    return text[:MAX_KIND_LENGTH]


class Misfit(NamedTuple):
    """Why a valid message does not fit the run: a kind (no numbers) and the detail."""

    kind: str
    detail: str


@dataclass(frozen=True)
class RunShape:
    """The sizes every message of one run must have.

    ``steps`` is None for a run of unknown length (live): steps then only need
    to be in 1 .. MAX_STEP. ``dim`` and ``obs_dim`` None skip those checks
    (a process that did not load the model).
    """

    particles: int
    dim: int | None = None
    obs_dim: int | None = None
    steps: int | None = None
    #: Whether the run has a move of its own (a user's), which a set or a command may name as "own" (None:
    #: not checked, a process that does not apply moves).
    own_move: bool | None = None

    @classmethod
    def of(cls, config, model=None) -> "RunShape":
        """The shape of the run of ``config`` (a RunConfig) with its loaded ``model``."""
        from dtpf.messages.family import MOVES

        # A model with several sensors has observations of several widths: not checked here (the entity does).
        return cls(particles=config.particles, dim=getattr(model, "dim", None),
                   obs_dim=None if getattr(model, "sensors", None) else getattr(model, "obs_dim", None),
                   steps=config.steps,
                   own_move=config.jitter not in MOVES.builtins())

    @property
    def last_step(self) -> int:
        return self.steps if self.steps is not None else MAX_STEP

    def misfit(self, message: Message) -> Misfit | None:
        """None if ``message`` can apply to this run, else what is wrong with it."""
        if isinstance(message, (Observation, Control)):
            return None  # a sensor's (a control source's) sequence numbers are the intake's business (dtpf.entity.intake)
        step = message.step
        run_level = step == 0
        if not run_level and step > self.last_step:
            return Misfit(f"{type(message).__name__} step beyond the run's last step",
                          f"{type(message).__name__} at step {step}, the run has {self.last_step} steps")
        if isinstance(message, (ParticleSet, WeightState, PSCommand, Estimate)) and run_level:
            return Misfit(f"{type(message).__name__} at step 0",
                          f"{type(message).__name__} at step 0: filter steps start at 1")
        if isinstance(message, ParticleSet):
            return self._particle_set(message)
        if isinstance(message, WeightState) and message.n != self.particles:
            return Misfit("WeightState of another N",
                          f"WeightState with n = {message.n}, the run has N = {self.particles}")
        if isinstance(message, PSCommand) and message.arm == OWN_ARM and self.own_move is False:
            return Misfit("PSCommand naming a move the run does not have",
                          f"PSCommand at step {step} puts the arm '{OWN_ARM}' in force; the run has no move of "
                          f"its own")
        if isinstance(message, PSCommand) and message.applies_from_step > self.last_step + 1:
            return Misfit("PSCommand applying after the run's end",
                          f"PSCommand applies from step {message.applies_from_step}, the run has "
                          f"{self.last_step} steps")
        if isinstance(message, Estimate) and self.dim is not None and len(message.mean) != self.dim:
            return Misfit("Estimate of another dimension",
                          f"Estimate with d = {len(message.mean)}, the model has d = {self.dim}")
        return None

    def _particle_set(self, message: ParticleSet) -> Misfit | None:
        n, d = message.particles.shape
        if n != self.particles or (self.dim is not None and d != self.dim):
            want = f"({self.particles}, {self.dim if self.dim is not None else 'd'})"
            return Misfit("particle set of another shape",
                          f"{message.kind.value} particle set of step {message.step} has shape ({n}, {d}), "
                          f"the run has {want}")
        if message.jitter == OWN_ARM and self.own_move is False:
            return Misfit("particle set naming a move the run does not have",
                          f"particle set of step {message.step} names the move '{OWN_ARM}'; the run has no move "
                          f"of its own")
        if self.obs_dim is not None and message.observation and len(message.observation) != self.obs_dim:
            return Misfit("particle set with an observation of another length",
                          f"particle set of step {message.step} carries {len(message.observation)} observed "
                          f"values, the model has {self.obs_dim}")
        return None
