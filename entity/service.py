"""Entity service: the particle filter as a process of its own.

Each step it publishes the propagated particle set on
``dtpf/<twin>/entity/particles``, waits (up to ``--timeout``) for the
preprocessed set of the same run and step on
``dtpf/<twin>/information/preprocessed``, resamples, and publishes the
estimate on ``dtpf/<twin>/entity/estimate`` (and, in the video scenario, the
frame as a JPEG on ``dtpf/<twin>/entity/frame``). A missing or late answer never
stalls the filter: that step falls back to plain resampling and its estimate
says ``degraded``. While it waits, it does what the answer does not change:
it resamples with its own weights (used if the answer keeps them, as the
default "inherit" rule does) and draws the next step's propagation noise
(:meth:`entity.filter.ParticleFilter.work_ahead`; the same numbers as doing it
in order), so that work is off the lockstep's critical path.

Run ``python -m entity.service --help`` for the options.
"""
from __future__ import annotations

import argparse
import base64
import time

import numpy as np
import zenoh

from entity import models
from entity.filter import ParticleFilter, Preprocessed
from entity.tracking import VideoTrackingModel, encode_jpeg
from information.rules import PreprocessReport
from messages.bus import add_zenoh_arguments
from messages.config import RunConfig, add_run_arguments
from messages.models import ARRAYS_CHECKED, CompressedImage, Estimate, ParticleSet, ParticleSetKind, Time
from messages.service import ServiceShell, add_service_arguments, run_service
from messages.streams import stream

__all__ = ["ZenohTwin", "main"]


class ZenohTwin:
    """The filter's preprocessor hook over Zenoh: publish the set, wait for the answer."""

    def __init__(self, shell: ServiceShell, timeout: float):
        self.shell = shell
        self.timeout = timeout
        self.answers = shell.inbox("information", "preprocessed")
        self.information_was_alive = True
        #: Called once the particle set is out, before waiting for the answer: work that
        #: does not depend on it (the service sets the filter's work_ahead).
        self.while_waiting = None

    def __call__(self, step, particles, weights, observation, parents=None) -> Preprocessed | None:
        shell = self.shell
        alive = "information" in shell.presence.alive
        if not alive and self.information_was_alive:
            shell.log.warning("step %d: the information layer is gone, plain resampling until it is back", step)
        elif alive and not self.information_was_alive:
            shell.log.info("step %d: the information layer is alive, preprocessing again", step)
        self.information_was_alive = alive
        # The filter checked both arrays (propagate's output, normalised weights): not scanned again here.
        shell.publish(ParticleSet.model_validate(dict(
            **shell.header(step), kind=ParticleSetKind.PROPAGATED, particles=particles, weights=weights,
            observation=[float(v) for v in observation], parents=parents), context=ARRAYS_CHECKED))
        if not alive:
            return None  # nobody to wait for: do not stall the filter
        deadline = time.monotonic() + self.timeout
        if self.while_waiting is not None:
            self.while_waiting()
        while not shell.stopping:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            answer = shell.receive(self.answers.get(timeout=min(remaining, 0.2)), ParticleSet)
            if answer is None:
                continue
            if answer.step != step:
                shell.log.debug("ignored a late preprocessed set of step %d at step %d", answer.step, step)
                continue
            report = PreprocessReport(answer.threshold, answer.n_large, answer.n_processed,
                                      answer.n_mixed, answer.n_plain, answer.ps)
            return Preprocessed(answer.particles, answer.weights, report, checked=True)
        shell.log.warning("step %d: no preprocessed set within %.1f s, plain resampling", step, self.timeout)
        return None


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Run the filter of ``config`` to the end (or until SIGINT/SIGTERM)."""
    model = models.get(config.scenario)
    truth, observations = model.simulate(config.steps, stream(config.seed, config.twin, 0, "scenario"))
    with ServiceShell("entity", config, zenoh_config) as shell:
        wait_for = args.wait_for if args.wait_for is not None else (
            ["information", "system"] if config.preprocess else [])
        shell.wait_for_layers(wait_for, args.startup_timeout)
        twin = ZenohTwin(shell, args.timeout) if config.preprocess else None
        pf = ParticleFilter(model, observations, config.particles, resampler=config.resampler,
                            resample_below=config.resample_below, seed=config.seed, twin=config.twin,
                            preprocessor=twin)
        if twin is not None:
            twin.while_waiting = pf.work_ahead
        shell.running()
        period = 1.0 / args.rate if args.rate else 0.0
        next_tick = time.monotonic()
        for step in pf:
            report = step.report
            shell.publish(Estimate(
                **shell.header(step.step), mean=step.mean.tolist(), var=step.var.tolist(),
                lower=step.lower.tolist(), upper=step.upper.tolist(), ess=step.ess,
                ess_ratio=step.ess / config.particles, resampled=step.resampled, degraded=step.degraded,
                truth=truth[step.step - 1].tolist(), observation=observations[step.step - 1].tolist(),
                ps=report.ps if report is not None else None))
            if isinstance(model, VideoTrackingModel):  # the frame, so the log plays as a video in Foxglove
                shell.publish(CompressedImage(
                    **shell.header(step.step), timestamp=Time.now(), frame_id="camera", format="jpeg",
                    data=base64.b64encode(encode_jpeg(model.video.frame(step.step))).decode("ascii")))
            if shell.stopping:
                shell.log.info("stopped after step %d of %d", step.step, pf.steps)
                return 130
            if period:
                next_tick += period
                time.sleep(max(0.0, next_tick - time.monotonic()))
        shell.log.info("finished %d steps", pf.steps)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m entity.service",
        description="dtpf entity layer: runs the particle filter on a scenario, publishes each step's "
                    "particle set and estimate, and resamples the preprocessed set the information layer "
                    "sends back.")
    add_run_arguments(parser)
    parser.add_argument("--rate", type=float, default=None, metavar="STEPS_PER_SECOND",
                        help="run at most this many steps per second, like a sensor delivering "
                             "observations in real time (default: as fast as possible)")
    add_service_arguments(parser)
    add_zenoh_arguments(parser)
    return parser


if __name__ == "__main__":
    raise SystemExit(run_service("entity", main, build_parser()))
