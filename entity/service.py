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

from entity import sources
from entity.cloud import FIELDS, POINT_STRIDE, cloud_points
from entity.filter import ParticleFilter, Preprocessed, PreprocessReport
from entity.intake import ObservationIntake
from messages.admission import RunShape
from messages.bus import add_zenoh_arguments
from messages.config import RunConfig, add_run_arguments
from messages.models import (ARRAYS_CHECKED, BASE64_CHECKED, Estimate, Observation, PackedElementField, ParticleSet,
                             ParticleSetKind, PointCloud, ServiceState, Time)
from messages.fleet import host_twins
from messages.service import ServiceShell, add_service_arguments, run_service

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
        # A stop does not cut the wait: the step in flight finishes with its answer (the launcher stops
        # the entity before the information layer), bounded by the timeout and the layer's liveliness.
        last_looks = None
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                # The work done while waiting may outlast the deadline (numba compiling it on a cold start
                # took seconds, with the answer already in): what the inbox holds at the deadline is
                # looked at, no more (a flood cannot hold the step), then the step is degraded.
                last_looks = len(self.answers) if last_looks is None else last_looks - 1
                if last_looks <= 0:
                    break
            answer = shell.receive(self.answers.get(timeout=min(max(remaining, 0.0), 0.05)), ParticleSet)
            if answer is None:
                if "information" not in shell.presence.alive and len(self.answers) == 0:
                    shell.log.warning("step %d: the information layer died before it answered, plain "
                                      "resampling", step)
                    self.information_was_alive = False
                    return None  # it died while we waited: no answer will come
                continue
            if answer.step != step:
                shell.log.debug("ignored a late preprocessed set of step %d at step %d", answer.step, step)
                continue
            report = PreprocessReport(answer.threshold, answer.n_large, answer.n_processed,
                                      answer.n_mixed, answer.n_plain, answer.ps)
            try:
                return Preprocessed(answer.particles, answer.weights, report, checked=True)
            except ValueError as error:  # the shell checked the shape; anything else is counted too
                shell.reject("preprocessed set the filter cannot take", f"step {step}: {error}",
                             key=self.answers.key_expr)
        shell.log.warning("step %d: no preprocessed set within %.1f s, plain resampling", step, self.timeout)
        return None


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Run the filter of ``config`` to the end (or until SIGINT/SIGTERM).

    The observations are simulated, read from a file, or (live) taken from the
    sensor one at a time, one filter step each, until the sensor ends its
    stream, ``--steps`` are done or the service is stopped.
    """
    if args.twins:
        configs = hosted_configs(config, args.twins)
        models: dict[str, object] = {}  # one model object per reference, shared by the twins of this process

        def run(shell: ServiceShell, twin_config: RunConfig) -> int:
            model = models.setdefault(twin_config.model_ref, sources.load_model(twin_config))
            return run_twin(shell, twin_config, model, sources.observations_of(twin_config, model), args)

        return host_twins("entity", configs, zenoh_config, run)
    model = sources.load_model(config)
    data = sources.observations_of(config, model)
    with ServiceShell("entity", config, zenoh_config) as shell:
        return run_twin(shell, config, model, data, args)


def hosted_configs(config: RunConfig, twins: str) -> list[RunConfig]:
    """The runs of ``--twins``: K (``<twin>-1`` .. ``<twin>-K``) or a comma-separated list of twin ids,
    each with the run options of ``config``."""
    if twins.isdigit():
        count = int(twins)
        if count < 1:
            raise ValueError(f"--twins must be at least 1, got {count}")
        names = [f"{config.twin}-{i}" for i in range(1, count + 1)]
    else:
        names = [name.strip() for name in twins.split(",") if name.strip()]
    if not names or len(set(names)) != len(names):
        raise ValueError(f"--twins takes a count or distinct twin ids, got {twins!r}")
    return [RunConfig.model_validate({**config.model_dump(), "twin": name}) for name in names]


def run_twin(shell: ServiceShell, config: RunConfig, model, data, args: argparse.Namespace) -> int:
    """One twin's filter on ``shell``, to the end (or until the shell stops)."""
    steps = config.steps if config.steps is not None or data is None else len(data.observations)
    shell.expect(RunShape(config.particles, model.dim, model.obs_dim, steps))
    wait_for = args.wait_for if args.wait_for is not None else (
        ["information", "system"] if config.preprocess else [])
    twin = ZenohTwin(shell, args.timeout) if config.preprocess else None
    live = LiveObservations(shell, model, config, args.observation_timeout) if data is None else None
    if wait_for:  # the run configuration, at once: a fleet's shared layers learn the twin from it
        shell.publish_status()
    shell.wait_for_layers(wait_for, args.startup_timeout)
    # Without truth the filter is judged by how it predicts its data: the innovation too.
    pf = ParticleFilter(model, None if data is None else data.observations, config.particles,
                        resampler=config.resampler, resample_below=config.resample_below, seed=config.seed,
                        twin=config.twin, preprocessor=twin, innovation=data is None or data.truth is None,
                        jitter=config.jitter)
    if twin is not None:
        twin.while_waiting = pf.work_ahead
    pf.warm_up()
    shell.running()
    if live is not None:
        return _run_live(shell, pf, live, config, args.cloud_points)
    return _run_batch(shell, pf, data, model, config, args)


def _publish_step(shell: ServiceShell, step, truth, observation, model, config: RunConfig, cloud: int = 0) -> None:
    """The estimate of one filter step (and, in the video scenario, its frame)."""
    report = step.report
    shell.publish(Estimate(
        **shell.header(step.step), mean=step.mean.tolist(), var=step.var.tolist(),
        lower=step.lower.tolist(), upper=step.upper.tolist(), ess=step.ess,
        ess_ratio=step.ess / config.particles, resampled=step.resampled, degraded=step.degraded,
        truth=None if truth is None else [float(v) for v in truth],
        observation=[float(v) for v in observation],
        ps=report.ps if report is not None else None,
        log_predictive=step.log_predictive if np.isfinite(step.log_predictive) else None,
        innovation=step.innovation if step.innovation is not None and np.isfinite(step.innovation) else None))
    for message in model.step_messages(shell.header(step.step), step.particles, step.weights, step.mean):
        shell.publish(message)
    if cloud:  # the particle set as Foxglove draws it (entity/cloud.py says which particles)
        points = cloud_points(step.particles, step.weights, cloud)
        shell.publish(PointCloud.model_validate(dict(
            **shell.header(step.step), timestamp=Time.now(), frame_id="state", point_stride=POINT_STRIDE,
            fields=[PackedElementField(name=name, offset=offset, type=8) for name, offset in FIELDS],
            data=base64.b64encode(points.tobytes()).decode("ascii")), context=BASE64_CHECKED))


def _run_batch(shell: ServiceShell, pf: ParticleFilter, data, model, config: RunConfig,
               args: argparse.Namespace) -> int:
    """Every observation of a simulation or a file, at most ``--rate`` steps per second."""
    period = 1.0 / args.rate if args.rate else 0.0
    next_tick = time.monotonic()
    for step in pf:
        k = step.step
        _publish_step(shell, step, None if data.truth is None else data.truth[k - 1],
                      data.observations[k - 1], model, config, args.cloud_points)
        if shell.stopping:
            shell.log.info("stopped after step %d of %d", k, pf.steps)
            return 130
        if period:
            next_tick += period
            time.sleep(max(0.0, next_tick - time.monotonic()))
    shell.log.info("finished %d steps", pf.steps)
    return 0


class LiveObservations:
    """The sensor's observations as they arrive: decoded, checked by the intake, counted."""

    def __init__(self, shell: ServiceShell, model, config: RunConfig, quiet_after: float):
        self.shell = shell
        self.key = config.observation_key()
        self.inbox = shell.inbox_on(self.key)
        self.intake = ObservationIntake(model.obs_dim, model.dim)
        self.quiet_after = quiet_after
        shell.observation_counts = self.intake.counts

    def next(self) -> Observation | None:
        """The next accepted observation (or the end of the stream); None once the service stops.

        Waits as long as it takes; after ``quiet_after`` seconds without one the
        status says so (state 'waiting'), and 'running' again when one comes.
        """
        shell = self.shell
        last = time.monotonic()
        while not shell.stopping:
            item = self.inbox.get(timeout=0.2)
            if item is None:
                quiet = time.monotonic() - last
                if quiet >= self.quiet_after and shell.state != ServiceState.WAITING:
                    shell.state = ServiceState.WAITING
                    shell.detail = (f"no observation for {quiet:.1f} s on {self.key} (last sequence "
                                    f"{self.intake.last_sequence}); waiting")
                    shell.log.warning("%s", shell.detail)
                    shell.publish_status()
                continue
            rejected = shell.rejected
            message = shell.receive(item, Observation)
            if message is None:
                if shell.rejected > rejected:
                    self.intake.malformed()
                continue
            verdict = self.intake.check(message.step, message.values, message.truth, message.end)
            if verdict is not None:
                shell.reject(verdict.reason, verdict.detail)
                continue
            if shell.state == ServiceState.WAITING:
                shell.log.info("observations again after %.1f s (sequence %d)", time.monotonic() - last,
                               message.step)
                shell.state, shell.detail = ServiceState.RUNNING, None
                shell.publish_status()
            return message
        return None


def _run_live(shell: ServiceShell, pf: ParticleFilter, live: LiveObservations, config: RunConfig,
              cloud: int = 0) -> int:
    """One filter step per accepted observation, until the stream ends, ``--steps`` or a stop."""
    shell.log.info("waiting for observations on %s", live.key)
    while config.steps is None or pf.k < config.steps:
        observation = live.next()
        if observation is None:
            shell.log.info("stopped after step %d", pf.k)
            return 130
        if observation.end:
            shell.log.info("the sensor ended its stream after %d observations", pf.k)
            break
        step = pf.update(observation.values)
        _publish_step(shell, step, observation.truth, observation.values, pf.model, config, cloud)
    shell.log.info("finished %d steps", pf.k)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m entity.service",
        description="dtpf entity layer: runs the particle filter on a scenario, an observation file or a "
                    "live sensor, publishes each step's particle set and estimate, and resamples the "
                    "preprocessed set the information layer sends back.")
    add_run_arguments(parser)
    parser.add_argument("--rate", type=float, default=None, metavar="STEPS_PER_SECOND",
                        help="run at most this many steps per second, like a sensor delivering "
                             "observations in real time (default: as fast as possible; live observations "
                             "set their own pace)")
    parser.add_argument("--cloud-points", type=int, default=1000, metavar="K",
                        help="publish each step's particle set as a foxglove.PointCloud on dtpf/<twin>/entity/cloud, "
                             "at most K particles (every ceil(N/K)-th; 0: none) (default: %(default)s)")
    parser.add_argument("--observation-timeout", type=float, default=5.0, metavar="SECONDS",
                        help="live observations: after this long without one, say so in the status and "
                             "the log and keep waiting; the filter never invents a step (default: %(default)s)")
    parser.add_argument("--twins", metavar="K|IDS", default=None,
                        help="host several twins in this process, as an edge box with several sensors: K twins "
                             "<twin>-1 .. <twin>-K, or a comma-separated list of twin ids, each with the run "
                             "options above and numbers equal to its own run (default: the one twin --twin)")
    add_service_arguments(parser)
    add_zenoh_arguments(parser)
    return parser


if __name__ == "__main__":
    raise SystemExit(run_service("entity", main, build_parser()))
