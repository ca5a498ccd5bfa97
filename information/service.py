"""Information service: the mirror and the preprocessing rules as a process.

For each particle set on ``dtpf/<twin>/entity/particles`` it applies Eq. 28-30
with the PS in force and publishes the preprocessed set on
``dtpf/<twin>/information/preprocessed`` and the weight state on
``dtpf/<twin>/information/weight_state``. PS commands arrive on
``dtpf/<twin>/system/ps``; before step k it waits (up to ``--timeout``) for
the decision the system layer made at step k - 1, and keeps the last PS if
none comes.

Run ``python -m information.service --help`` for the options.
"""
from __future__ import annotations

import argparse
import time

import zenoh

from entity import sources
from information.layer import InformationLayer
from messages.admission import RunShape
from messages.bus import add_zenoh_arguments
from messages.config import RunConfig, add_run_arguments
from messages.models import ARRAYS_CHECKED, ParticleSet, ParticleSetKind, PSCommand, WeightState
from messages.service import ServiceShell, add_service_arguments, run_service

__all__ = ["main"]


class PSInbox:
    """PS commands of this run, applied to the layer in the order of their steps."""

    def __init__(self, shell: ServiceShell, layer: InformationLayer):
        self.shell = shell
        self.layer = layer
        self.inbox = shell.inbox("system", "ps")
        self.latest_step = 0  # step of the latest decision received

    def drain(self, timeout: float = 0.0) -> bool:
        """Apply every queued command; wait up to ``timeout`` for the first. True if any came."""
        got = False
        item = self.inbox.get(timeout=timeout) if timeout > 0 else self.inbox.get(timeout=0)
        while item is not None:
            command = self.shell.receive(item, PSCommand)
            if command is not None:
                self.layer.set_ps(command.ps, command.applies_from_step)
                self.latest_step = max(self.latest_step, command.step)
                got = True
            item = self.inbox.get(timeout=0)
        return got

    def wait_for_decision(self, step: int, timeout: float) -> bool:
        """Wait until the decision made at ``step`` has arrived; False on timeout."""
        deadline = time.monotonic() + timeout
        self.drain()
        while self.latest_step < step and not self.shell.stopping:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or "system" not in self.shell.presence.alive:
                return False
            self.drain(timeout=min(remaining, 0.2))
        return self.latest_step >= step


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Serve preprocessing for the twin of ``config`` until SIGINT/SIGTERM."""
    model = sources.load_model(config)
    layer = InformationLayer(model, ps=config.ps, threshold_rule=config.threshold,
                             weight_rule=config.weight_rule, seed=config.seed, twin=config.twin)
    with ServiceShell("information", config, zenoh_config) as shell:
        shell.expect(RunShape.of(config, model))
        particle_sets = shell.inbox("entity", "particles")
        commands = PSInbox(shell, layer)
        published = 0  # the last step whose weight state this process sent
        system_was_alive = True
        layer.warm_up()  # before the entity can send step 1
        shell.running()
        while not shell.stopping:
            message = shell.receive(particle_sets.get(timeout=0.2), ParticleSet)
            if message is None:
                continue
            step = message.step
            # The system decides on the weight state we sent; after a restart there is none to wait for.
            system_alive = "system" in shell.presence.alive
            if system_alive != system_was_alive:
                if system_alive:
                    shell.log.info("step %d: the system layer is alive, taking its PS decisions again", step)
                else:
                    shell.log.warning("step %d: the system layer is gone, keeping PS = %g until it is back",
                                      step, layer.ps)
                system_was_alive = system_alive
            if step - 1 == published and step > 1 and system_alive and \
                    not commands.wait_for_decision(step - 1, args.timeout):
                shell.log.warning("step %d: no PS decision of step %d within %.1f s, keeping PS = %g",
                                  step, step - 1, args.timeout, layer.ps)
            # The entity waits for the preprocessed set: it goes first, the rest of the mirror after.
            # The decoded message's arrays are validated: the layer does not scan them again.
            try:
                result = layer.preprocess(step, message.particles, message.weights, message.observation,
                                          checked=True)
            except ValueError as error:  # a set the rules cannot take: counted, the service goes on
                shell.reject("particle set the rules cannot take", f"step {step}: {error}",
                             key=particle_sets.key_expr)
                continue
            report = result.report
            counts = dict(n_large=report.n_large, n_processed=report.n_processed,
                          n_mixed=report.n_mixed, n_plain=report.n_plain)
            shell.publish(ParticleSet.model_validate(dict(
                **shell.header(step), kind=ParticleSetKind.PREPROCESSED, particles=result.particles,
                weights=result.weights, observation=message.observation, ps=report.ps,
                threshold=min(report.threshold, 1.0), **counts), context=ARRAYS_CHECKED))
            summary = layer.mirror(message.particles, message.weights, message.parents, report.threshold,
                                   checked=True)
            shell.publish(WeightState(**shell.header(step), **summary.as_dict(), ps=report.ps, **counts))
            published = step
            layer.prepare(step + 1)  # while waiting for the next set
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m information.service",
        description="dtpf information layer: mirrors the entity's particle sets, moves small-weight "
                    "particles towards large-weight ones (Eq. 28-30) with the PS in force, and reports "
                    "the weight state to the system layer.")
    add_run_arguments(parser)
    add_service_arguments(parser)
    add_zenoh_arguments(parser)
    return parser


if __name__ == "__main__":
    raise SystemExit(run_service("information", main, build_parser()))
