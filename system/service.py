"""System service: degradation prediction and PS control as a process.

For each weight state on ``dtpf/<twin>/information/weight_state`` it predicts
degradation, asks its PS policy for the PS of the next step and publishes the
decision, with its reason and predicted figures, on ``dtpf/<twin>/system/ps``.
A policy that simulates (``rule``, ``predictive``) also needs the particle
set: the service then subscribes to ``dtpf/<twin>/information/preprocessed``
and waits (up to ``--timeout``) for the set of the same step; without it the
decision rests on the weight state alone, and the log says so.

Run ``python -m system.service --help`` for the options.
"""
from __future__ import annotations

import argparse
import time

import zenoh

from entity import sources
from information.mirror import WeightSummary
from messages.admission import RunShape
from messages.bus import add_zenoh_arguments
from messages.config import RunConfig, add_run_arguments
from messages.models import ParticleSet, PSCommand, WeightState
from messages.service import ServiceShell, add_service_arguments, run_service
from system.layer import SystemLayer
from system.predict import Snapshot

__all__ = ["main", "summary_of", "ParticleSets"]


def summary_of(state: WeightState) -> WeightSummary:
    """The mirror's summary carried by a WeightState message."""
    return WeightSummary(**{name: getattr(state, name) for name in WeightSummary.__dataclass_fields__})


#: How many steps ahead of the one it decides on the service keeps a particle set.
MAX_AHEAD = 4


class ParticleSets:
    """Preprocessed sets of this run by step, for the simulating policies."""

    def __init__(self, shell: ServiceShell):
        self.shell = shell
        self.inbox = shell.inbox("information", "preprocessed")
        self.pending: dict[int, ParticleSet] = {}

    def wait_for(self, step: int, timeout: float) -> Snapshot | None:
        """The snapshot of ``step``, waiting up to ``timeout`` for it; None if it does not come."""
        deadline = time.monotonic() + timeout
        while step not in self.pending and not self.shell.stopping:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            message = self.shell.receive(self.inbox.get(timeout=min(remaining, 0.2)), ParticleSet)
            if message is not None and step <= message.step <= step + MAX_AHEAD:
                self.pending[message.step] = message
        for old in [s for s in self.pending if s < step]:
            del self.pending[old]
        message = self.pending.pop(step, None)
        if message is None:
            return None
        return Snapshot.of(message.particles, message.weights, message.observation)


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Serve PS decisions for the twin of ``config`` until SIGINT/SIGTERM."""
    model = sources.load_model(config)
    # The service keeps only what the policies look back on, not the run's whole history.
    layer = SystemLayer.from_config(config, model=model, keep=16)
    with ServiceShell("system", config, zenoh_config) as shell:
        shell.expect(RunShape.of(config, model))
        states = shell.inbox("information", "weight_state")
        sets = ParticleSets(shell) if layer.needs_particles else None
        shell.running()
        while not shell.stopping:
            state = shell.receive(states.get(timeout=0.2), WeightState)
            if state is None:
                continue
            snapshot = None
            if sets is not None:
                snapshot = sets.wait_for(state.step, args.timeout)
                if snapshot is None:
                    shell.log.warning("step %d: no preprocessed set within %.1f s, deciding from the weight "
                                      "state alone", state.step, args.timeout)
            try:
                decision = layer.observe(state.step, summary_of(state), snapshot)
            except ValueError as error:  # a state the predictor cannot take: counted, the service goes on
                shell.reject("weight state the predictor cannot take", f"step {state.step}: {error}",
                             key=states.key_expr)
                continue
            shell.publish(PSCommand(**shell.header(state.step), **decision.command_fields()))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m system.service",
        description="dtpf system layer: predicts particle degradation from the mirrored weight state and "
                    "publishes the preprocessing degree PS for the next step, with its reason.")
    add_run_arguments(parser)
    add_service_arguments(parser)
    add_zenoh_arguments(parser)
    return parser


if __name__ == "__main__":
    raise SystemExit(run_service("system", main, build_parser()))
