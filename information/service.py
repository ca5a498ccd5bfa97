"""Information service: the mirror and the preprocessing rules as a process.

For each particle set on ``dtpf/<twin>/entity/particles`` it applies Eq. 28-30
with the PS in force and publishes the preprocessed set on
``dtpf/<twin>/information/preprocessed`` and the weight state on
``dtpf/<twin>/information/weight_state``. PS commands arrive on
``dtpf/<twin>/system/ps``; before step k it waits (up to ``--timeout``) for
the decision the system layer made at step k - 1, and keeps the last PS if
none comes.

Run ``python -m dtpf.information.service --help`` for the options.
"""
from __future__ import annotations

import argparse

import zenoh

from dtpf.entity import cores, sources
from dtpf.information.layer import InformationLayer, arms_for
from dtpf.messages import family, names
from dtpf.messages.admission import RunShape
from dtpf.messages.config import RunConfig, add_run_arguments
from dtpf.messages.models import ARRAYS_CHECKED, ParticleSet, ParticleSetKind, PSCommand, WeightState
from dtpf.shell.bus import add_zenoh_arguments
from dtpf.shell.fleet import add_fleet_arguments, serve_layer
from dtpf.shell.service import ServiceShell, add_service_arguments, run_service

__all__ = ["main", "TwinInformation"]


class PSInbox:
    """PS commands of this run, applied to the layer in the order of their steps.

    A command whose arm does not fit the run (an arm from another policy than ``choose``, none from
    ``choose``, or a PS or preprocessing other than the arm's) is a counted rejection.
    """

    def __init__(self, shell: ServiceShell, layer: InformationLayer, policy: str | None = None):
        self.shell = shell
        self.layer = layer
        self.policy = policy
        self.inbox = shell.inbox("system", "ps")
        self.latest_step = 0  # step of the latest decision received

    def problem(self, command: PSCommand) -> str | None:
        """Why ``command`` does not fit this run's policy, or None."""
        choosing = family.POLICIES.trait(self.policy, "chooses_arms", False)
        if command.arm is None:
            return f"the {self.policy} policy names an arm in every decision" if choosing else None
        if not choosing:
            return f"an arm ({command.arm}) from a run whose policy is {self.policy}"
        arm = self.layer.arms.get(command.arm)
        if arm is None:
            return f"arm {command.arm} of a run without a move of its own (its arms: {', '.join(self.layer.arms)})"
        if command.policy != self.policy or command.ps != arm.ps or command.preprocess != arm.preprocess:
            return (f"arm {arm.name} with policy {command.policy}, PS {command.ps:g}, preprocess "
                    f"{command.preprocess} (the arm's: {self.policy}, PS {arm.ps:g}, preprocess {arm.preprocess})")
        return None

    def drain(self) -> bool:
        """Apply every queued command. True if any came."""
        got = False
        while (item := self.inbox.get(timeout=0)) is not None:
            command = self.shell.receive(item, PSCommand)
            if command is not None and self.policy is not None and (problem := self.problem(command)):
                self.shell.reject("PS command that does not fit the run", f"step {command.step}: {problem}",
                                  key=self.inbox.key_expr)
                command = None
            if command is not None:
                self.layer.set_ps(command.ps, command.applies_from_step, command.preprocess, command.arm)
                self.latest_step = max(self.latest_step, command.step)
                got = True
        return got


class TwinInformation:
    """The information layer of one twin in a service: its layer object and the lockstep with its system layer.

    :meth:`poll` never blocks: a particle set of step k that must wait for the
    system layer's decision of step k - 1 is held until the decision comes, the
    system layer is gone, or ``timeout`` seconds pass (then the last PS is kept).
    """

    def __init__(self, shell: ServiceShell, config: RunConfig, model, timeout: float):
        self.shell = shell
        self.timeout = timeout
        self.layer = InformationLayer(model, ps=config.ps, threshold_rule=config.threshold,
                                      weight_rule=config.weight_rule, seed=config.seed, twin=config.twin,
                                      move_rule=config.move_rule,
                                      preprocess=family.POLICIES.trait(config.policy, "initial_preprocess", True),
                                      arms=arms_for(config.jitter), block=config.block_particles,
                                      arm=(config.choose_base if config.choose_base not in (None, names.REHEARSE)
                                           else names.DEFAULT_CHOOSE_BASE)
                                      if family.POLICIES.trait(config.policy, "chooses_arms", False) else None)
        shell.expect(RunShape.of(config, model))
        self.particle_sets = shell.inbox("entity", "particles")
        self.commands = PSInbox(shell, self.layer, config.policy)
        self.published = 0  # the last step whose weight state this process sent
        #: Whether the system layer was alive at the last look (None: not looked yet).
        self.system_was_alive: bool | None = None
        #: Whether this twin's system layer has been seen alive, or waited for once. A fleet's service learns
        #: a twin while the twin's system layer may be announcing itself: its token can arrive after the
        #: first particle sets, and not waiting then would apply the old PS (and differ from the solo run).
        self.system_known = False
        self.waiting: ParticleSet | None = None  # a set waiting for the decision of the step before
        #: Whether a set waits for the decision of the step before (not for a policy that never changes PS).
        self.waits_for_decisions = not family.POLICIES.trait(config.policy, "constant", False)
        self.deadline = 0.0
        self.layer.warm_up(config.particles)  # before the entity can send step 1

    def poll(self, now: float) -> float | None:
        """Handle what has arrived; the time to look again if a set waits for its PS decision."""
        shell = self.shell
        self.commands.drain()
        while True:
            if self.waiting is None:
                message = shell.take(self.particle_sets, ParticleSet)
                if message is None:
                    return None
                system_alive = self._system_alive(message.step)
                step = message.step
                # The system decides on the weight state we sent; after a restart there is none to wait for.
                if self.waits_for_decisions and step - 1 == self.published and step > 1 and \
                        (system_alive or not self.system_known) and self.commands.latest_step < step - 1:
                    self.waiting, self.deadline = message, now + self.timeout
                    continue
            else:
                message = self.waiting
                step = message.step
                if self.commands.latest_step < step - 1:
                    expected = "system" in shell.presence.alive or not self.system_known
                    if now < self.deadline and expected and not shell.stopping:
                        return self.deadline
                    shell.log.warning("step %d: no PS decision of step %d within %.1f s, keeping PS = %g",
                                      step, step - 1, self.timeout, self.layer.ps)
                    self.system_known = True  # waited once for a layer not seen: not again until it is
                self.waiting = None
                # A decision that came shows the layer is there even when its token has not arrived yet
                # (liveliness and samples travel separately): it is known once its token is seen, and
                # until then the next step waits for its decision too.
            self._answer(message)

    def _system_alive(self, step: int) -> bool:
        system_alive = "system" in self.shell.presence.alive
        self.system_known |= system_alive
        if system_alive != self.system_was_alive:
            if system_alive and self.system_was_alive is not None:
                self.shell.log.info("step %d: the system layer is alive, taking its PS decisions", step)
            elif not system_alive and self.system_was_alive:
                self.shell.log.warning("step %d: the system layer is gone, keeping PS = %g until it is back",
                                       step, self.layer.ps)
            self.system_was_alive = system_alive
        return system_alive

    def _answer(self, message: ParticleSet) -> None:
        """Preprocess one set (Eq. 28-30) and publish it, then the weight state."""
        shell, layer, step = self.shell, self.layer, message.step
        # The entity waits for the preprocessed set: it goes first, the rest of the mirror after.
        # The decoded message's arrays are validated: the layer does not scan them again.
        try:
            result = layer.preprocess(step, message.particles, message.weights, message.observation,
                                      checked=True, sensor=message.sensor)
        except ValueError as error:  # a set the rules cannot take: counted, the service goes on
            shell.reject("particle set the rules cannot take", f"step {step}: {error}",
                         key=self.particle_sets.key_expr)
            return
        report = result.report
        counts = dict(n_large=report.n_large, n_processed=report.n_processed,
                      n_mixed=report.n_mixed, n_plain=report.n_plain)
        shell.publish(ParticleSet.model_validate(dict(
            **shell.header(step), kind=ParticleSetKind.PREPROCESSED, particles=result.particles,
            weights=result.weights, observation=message.observation, ps=report.ps,
            threshold=min(report.threshold, 1.0), jitter=layer.jitter, **counts,
            **{name: getattr(message, name) for name in ("sensor", "dt", "control")
               if getattr(message, name) is not None}), context=ARRAYS_CHECKED))
        summary = layer.mirror(message.particles, message.weights, message.parents, report.threshold,
                               checked=True)
        shell.publish(WeightState(**shell.header(step), **summary.as_dict(), ps=report.ps, **counts))
        self.published = step
        layer.prepare(step + 1)  # while waiting for the next set


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Serve preprocessing for the twin of ``config`` (or, with --twins, every twin under the pattern)
    until SIGINT/SIGTERM."""
    cores.set_threads(getattr(args, "threads", None))  # --threads: the process's, never the run's numbers
    return serve_layer("information", config, zenoh_config, args, sources.load_model,
                       lambda shell, twin_config, model: TwinInformation(shell, twin_config, model, args.timeout))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m dtpf.information.service",
        description="dtpf information layer: mirrors the entity's particle sets, moves small-weight "
                    "particles towards large-weight ones (Eq. 28-30) with the PS in force, and reports "
                    "the weight state to the system layer.")
    add_run_arguments(parser, threads=True)
    add_service_arguments(parser)
    add_fleet_arguments(parser)
    add_zenoh_arguments(parser)
    return parser


if __name__ == "__main__":
    raise SystemExit(run_service("information", main, build_parser()))
