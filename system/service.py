"""System service: degradation prediction and PS control as a process.

For each weight state on ``dtpf/<twin>/information/weight_state`` it asks its
PS policy for the PS of the next step and publishes the decision, with its
reason, on ``dtpf/<twin>/system/ps``.

Run ``python -m system.service --help`` for the options.
"""
from __future__ import annotations

import argparse

import zenoh

from information.mirror import WeightSummary
from messages.bus import add_zenoh_arguments
from messages.config import RunConfig, add_run_arguments
from messages.models import PSCommand, WeightState
from messages.service import ServiceShell, add_service_arguments, run_service
from system import policy as ps_policy
from system.layer import SystemLayer

__all__ = ["main", "summary_of"]


def summary_of(state: WeightState) -> WeightSummary:
    """The mirror's summary carried by a WeightState message."""
    return WeightSummary(**{name: getattr(state, name) for name in WeightSummary.__dataclass_fields__})


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Serve PS decisions for the twin of ``config`` until SIGINT/SIGTERM."""
    layer = SystemLayer(ps_policy.get(config.policy, ps=config.ps))
    with ServiceShell("system", config, zenoh_config) as shell:
        states = shell.inbox("information", "weight_state")
        shell.running()
        while not shell.stopping:
            state = shell.receive(states.get(timeout=0.2), WeightState)
            if state is None:
                continue
            decision = layer.observe(state.step, summary_of(state))
            predicted = decision.predicted
            shell.publish(PSCommand(**shell.header(state.step), ps=decision.ps,
                                    applies_from_step=decision.applies_from_step, policy=decision.policy,
                                    reason=decision.reason,
                                    predicted_ess_ratio=predicted.get("ess_ratio"),
                                    predicted_distinct_ratio=predicted.get("distinct_ratio")))
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
