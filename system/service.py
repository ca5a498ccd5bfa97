"""System service: degradation prediction and PS control as a process.

For each weight state on ``dtpf/<twin>/information/weight_state`` it predicts
degradation, asks its PS policy for the PS of the next step and publishes the
decision, with its reason and predicted figures, on ``dtpf/<twin>/system/ps``.
A policy that simulates (``rule``, ``predictive``) also needs the particle
set: the service then subscribes to ``dtpf/<twin>/information/preprocessed``
and waits (up to ``--timeout``) for the set of the same step; without it the
decision rests on the weight state alone, and the log says so.

Run ``python -m dtpf.system.service --help`` for the options.
"""
from __future__ import annotations

import argparse
import time

import zenoh

from dtpf.entity import cores, sources
from dtpf.entity.timeline import Drive
from dtpf.information.mirror import WeightSummary
from dtpf.messages.admission import RunShape
from dtpf.messages.config import RunConfig, add_run_arguments
from dtpf.messages.models import ParticleSet, PSCommand, WeightState
from dtpf.shell.bus import add_zenoh_arguments
from dtpf.shell.fleet import add_fleet_arguments, serve_layer
from dtpf.shell.service import ServiceShell, add_service_arguments, run_service
from dtpf.system.layer import SystemLayer, warm_up
from dtpf.system.predict import Snapshot

__all__ = ["main", "summary_of", "ParticleSets", "TwinSystem"]


def summary_of(state: WeightState) -> WeightSummary:
    """The mirror's summary carried by a WeightState message."""
    return WeightSummary(**{name: getattr(state, name) for name in WeightSummary.__dataclass_fields__})


#: How many steps ahead of the one it decides on the service keeps a particle set.
MAX_AHEAD = 4
#: Seconds a stopped service waits for the weight state of a run's last step when it has decided every
#: step before it (the launcher stops the layers as soon as the entity has finished; the last decision
#: should be in the log whichever of the two processes the machine ran first).
FINAL_WAIT = 0.5


class ParticleSets:
    """Preprocessed sets of this run by step, for the simulating policies."""

    def __init__(self, shell: ServiceShell):
        self.shell = shell
        self.inbox = shell.inbox("information", "preprocessed")
        self.pending: dict[int, ParticleSet] = {}
        self.driven: dict = {}

    def take(self, step: int) -> None:
        """Keep what has arrived for steps ``step`` .. ``step + MAX_AHEAD``."""
        while (item := self.inbox.get(timeout=0)) is not None:
            message = self.shell.receive(item, ParticleSet)
            if message is not None and step <= message.step <= step + MAX_AHEAD:
                self.pending[message.step] = message

    def snapshot(self, step: int) -> Snapshot | None:
        """The snapshot of ``step`` if its set has arrived (older ones are dropped)."""
        for old in [s for s in self.pending if s < step]:
            del self.pending[old]
        message = self.pending.pop(step, None)
        if message is None:
            return None
        #: A driven twin's step: its sensor and drive, as the set carries them (observe takes them).
        self.driven = {} if message.sensor is None and message.dt is None else dict(
            sensor=message.sensor, drive=Drive.from_fields(message.dt, message.control))
        return Snapshot.of(message.particles, message.weights, message.observation)


class TwinSystem:
    """The system layer of one twin in a service: weight state in, PS decision out.

    :meth:`poll` never blocks: a policy that simulates waits for the
    preprocessed set of the weight state's step, at most ``timeout`` seconds,
    and then decides from the weight state alone (and says so).
    """

    def __init__(self, shell: ServiceShell, config: RunConfig, model, timeout: float):
        self.shell = shell
        self.timeout = timeout
        # The service keeps only what the policies look back on, not the run's whole history.
        self.layer = SystemLayer.from_config(config, model=model, keep=16)
        warm_up(config, model)  # before the entity can send step 1
        shell.expect(RunShape.of(config, model))
        self.states = shell.inbox("information", "weight_state")
        self.sets = ParticleSets(shell) if self.layer.needs_particles else None
        self.waiting: WeightState | None = None
        self.deadline = 0.0
        self.steps = config.steps
        self.decided = 0  #: the last step decided on

    def poll(self, now: float) -> float | None:
        """Handle what has arrived; the time to look again if a weight state waits for its set."""
        shell = self.shell
        while True:
            if self.waiting is None:
                state = shell.take(self.states, WeightState)
                if state is None:
                    return None
                self.waiting, self.deadline = state, now + self.timeout
            state = self.waiting
            snapshot = None
            if self.sets is not None:
                self.sets.take(state.step)
                snapshot = self.sets.snapshot(state.step)
                if snapshot is None:
                    if now < self.deadline and not shell.stopping:
                        return self.deadline
                    shell.log.warning("step %d: no preprocessed set within %.1f s, deciding from the weight "
                                      "state alone", state.step, self.timeout)
            self.waiting = None
            self._decide(state, snapshot)

    def finish(self, doorbell) -> None:
        """After the stop: decide on what has arrived, and wait up to :data:`FINAL_WAIT` seconds for the
        weight state of the run's last step when it is the only one missing."""
        end = time.monotonic() + FINAL_WAIT
        self.poll(time.monotonic())
        while (self.steps is not None and self.decided == self.steps - 1
               and (left := end - time.monotonic()) > 0):
            doorbell.wait(left)
            self.poll(time.monotonic())

    def _decide(self, state: WeightState, snapshot: Snapshot | None) -> None:
        self.decided = max(self.decided, state.step)
        try:
            driven = self.sets.driven if snapshot is not None else {}
            decision = self.layer.observe(state.step, summary_of(state), snapshot, **driven)
        except ValueError as error:  # a state the predictor cannot take: counted, the service goes on
            self.shell.reject("weight state the predictor cannot take", f"step {state.step}: {error}",
                              key=self.states.key_expr)
            return
        self.shell.publish(PSCommand(**self.shell.header(state.step), **decision.command_fields()))


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Serve PS decisions for the twin of ``config`` (or, with --twins, every twin under the pattern)
    until SIGINT/SIGTERM."""
    cores.set_threads(getattr(args, "threads", None))  # --threads: the process's, never the run's numbers
    return serve_layer("system", config, zenoh_config, args, sources.load_model,
                       lambda shell, twin_config, model: TwinSystem(shell, twin_config, model, args.timeout))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m dtpf.system.service",
        description="dtpf system layer: predicts particle degradation from the mirrored weight state and "
                    "publishes the preprocessing degree PS for the next step, with its reason.")
    add_run_arguments(parser, threads=True)
    add_service_arguments(parser)
    add_fleet_arguments(parser)
    add_zenoh_arguments(parser)
    return parser


if __name__ == "__main__":
    raise SystemExit(run_service("system", main, build_parser()))
