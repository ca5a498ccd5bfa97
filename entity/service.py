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
(:meth:`dtpf.entity.filter.ParticleFilter.work_ahead`; the same numbers as doing it
in order), so that work is off the lockstep's critical path.

Run ``python -m dtpf.entity.service --help`` for the options.
"""
from __future__ import annotations

import argparse
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import zenoh

from dtpf.entity import cores, sources
from dtpf.entity.answers import live_answers
from dtpf.entity.cloud import FIELDS, POINT_STRIDE, cloud_points
from dtpf.entity.filter import ParticleFilter, PendingStep, Preprocessed
from dtpf.entity.calls import ModelCalls
from dtpf.entity.intake import DrivenIntake, ObservationIntake
from dtpf.messages.admission import RunShape
from dtpf.messages.codec import encode_with_base64
from dtpf.messages.config import RunConfig, add_run_arguments
from dtpf.messages.foxglove import PackedElementField, PointCloud
from dtpf.messages.models import (ARRAYS_CHECKED, Control, Estimate, Observation, ParticleSet, ParticleSetKind,
                                  ServiceState, Time)
from dtpf.messages.names import REHEARSAL_WAIT
from dtpf.shell.bus import Doorbell, add_zenoh_arguments, open_session
from dtpf.shell.fleet import host_twins, serve_run
from dtpf.shell.service import TAKE_BUDGET, ServiceShell, add_service_arguments, refuse_taken_twins, run_service

__all__ = ["ZenohTwin", "TwinRun", "LiveObservations", "main"]


class ZenohTwin:
    """The lockstep with the information layer, without blocking: publish the set, then look for the answer.

    :meth:`ask` publishes step k's particle set and starts the wait;
    :meth:`look` takes what the inbox holds and says whether to go on
    waiting. A missing or late answer never stalls the filter: the step is
    degraded once the deadline has passed, or at once when the information
    layer is gone. The answer that is in the inbox when the deadline passes
    is still taken (the work done meanwhile can outlast the deadline: numba
    compiling it on a cold start took seconds), and only what the inbox held
    at the deadline is looked at, so a flood cannot hold the step.
    """

    def __init__(self, shell: ServiceShell, timeout: float):
        self.shell = shell
        self.timeout = timeout
        self.answers = shell.inbox("information", "preprocessed")
        self.information_was_alive = True
        self.step = 0
        self.deadline = 0.0
        self._looks_left: int | None = None

    def ask(self, pending: PendingStep, now: float) -> bool:
        """Publish the set of ``pending``; True if an answer is to be waited for (the layer is alive)."""
        shell = self.shell
        step = pending.step
        alive = "information" in shell.presence.alive
        if not alive and self.information_was_alive:
            shell.log.warning("step %d: the information layer is gone, plain resampling until it is back", step)
        elif alive and not self.information_was_alive:
            shell.log.info("step %d: the information layer is alive, preprocessing again", step)
        self.information_was_alive = alive
        # The filter checked both arrays (propagate's output, normalised weights): not scanned again here.
        shell.publish(ParticleSet.model_validate(dict(
            **shell.header(step), kind=ParticleSetKind.PROPAGATED, particles=pending.particles,
            weights=pending.weights, observation=[float(v) for v in pending.observation],
            parents=pending.parents, **drive_fields(pending.sensor, pending.drive)), context=ARRAYS_CHECKED))
        self.step, self.deadline, self._looks_left = step, now + self.timeout, None
        return alive  # nobody to wait for: do not stall the filter

    def look(self, now: float) -> tuple[Preprocessed | None, bool]:
        """(the answer, False) once it is in; (None, True) to wait on; (None, False): the step goes on
        without one. A stop does not cut the wait: the step in flight finishes with its answer (the
        launcher stops the entity before the information layer), bounded by the timeout and the
        layer's liveliness."""
        shell, step = self.shell, self.step
        for _ in range(TAKE_BUDGET):
            if now >= self.deadline:
                self._looks_left = len(self.answers) if self._looks_left is None else self._looks_left - 1
                if self._looks_left <= 0:
                    break
            answer = shell.receive(self.answers.get(timeout=0), ParticleSet)
            if answer is None:
                if len(self.answers):
                    continue  # a bad one, counted
                if "information" not in shell.presence.alive:
                    shell.log.warning("step %d: the information layer died before it answered, plain "
                                      "resampling", step)
                    self.information_was_alive = False
                    return None, False  # it died while we waited: no answer will come
                break
            if answer.step != step:
                shell.log.debug("ignored a late preprocessed set of step %d at step %d", answer.step, step)
                continue
            try:
                # The report: the message, which carries its fields (threshold, n_large, n_processed, n_mixed,
                # n_plain, ps); the filter keeps it without reading it, the estimate takes its PS.
                return Preprocessed(answer.particles, answer.weights, answer, checked=True,
                                    jitter=answer.jitter), False
            except ValueError as error:  # the shell checked the shape; anything else is counted too
                shell.reject("preprocessed set the filter cannot take", f"step {step}: {error}",
                             key=self.answers.key_expr)
        else:
            self.answers.ring()  # more waits: the other twins first, then this one again
            return None, True
        if now < self.deadline:
            return None, True
        shell.log.warning("step %d: no preprocessed set within %.1f s, plain resampling", step, self.timeout)
        return None, False


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Run the filter of ``config`` to the end (or until SIGINT/SIGTERM).

    The observations are simulated, read from a file, or (live) taken from the
    sensor one at a time, one filter step each, until the sensor ends its
    stream, ``--steps`` are done or the service is stopped. With ``--twins``
    the process hosts several twins, all in one event loop.
    """
    cores.set_threads(getattr(args, "threads", None))  # --threads: the process's, never the run's numbers
    models: dict[str, object] = {}  # one model object per reference, shared by the twins of this process

    def make(shell: ServiceShell, twin_config: RunConfig) -> TwinRun:
        shell.presence.claim(twin_config.run_id)  # checked with the others below, before anything is published
        model = models.get(twin_config.model_ref)
        if model is None:
            model = models[twin_config.model_ref] = sources.load_model(twin_config)
        return TwinRun(shell, twin_config, model, sources.observations_of(twin_config, model), args)

    if args.twins:
        configs = hosted_configs(config, args.twins)
        # One twin, one entity: the process starts none of its twins if another entity runs any of them (an
        # operator who asked for a set of twins gets that set or a line naming the twins taken, exit 2).
        session = open_session(zenoh_config)
        try:
            refuse_taken_twins(session, [c.twin for c in configs])
        finally:
            session.close()
        return host_twins("entity", configs, zenoh_config, make)
    model = sources.load_model(config)
    data = sources.observations_of(config, model)  # a wrong file stops the service before its session opens
    doorbell = Doorbell()
    # claim: refused (TwinTaken, exit 2) while another entity runs the twin, before anything is published.
    with ServiceShell("entity", config, zenoh_config, doorbell=doorbell, claim=True) as shell:
        return serve_run(TwinRun(shell, config, model, data, args), doorbell)


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


def startup_wait(config: RunConfig, timeout: float, wait_for) -> float:
    """Seconds the entity waits for the layers of ``wait_for`` before its first step: ``timeout``, and
    :data:`~dtpf.messages.names.REHEARSAL_WAIT` more for a system layer that rehearses the model first (it is
    alive once it has its base, seconds to minutes later)."""
    return float(timeout) + (REHEARSAL_WAIT if config.rehearses and "system" in wait_for else 0.0)


class TwinRun:
    """One twin's filter on ``shell`` as a state machine that never blocks: :meth:`poll` does what can be done.

    Starting: it publishes the twin's status (how a fleet's shared layers
    learn it) and waits, up to ``--startup-timeout``, for the layers it talks
    to. Then, one filter step at a time: the next observation (the next of a
    simulation or a file, at most ``--rate`` a second; or the sensor's next
    accepted one), the step up to the preprocessor's question
    (:meth:`dtpf.entity.filter.ParticleFilter.begin_step`), the set out to the
    information layer, and, while the answer is awaited, what the answer does
    not change (:meth:`~dtpf.entity.filter.ParticleFilter.work_ahead`: resampling
    with its own weights, the next step's propagation noise); with the answer
    or without it, the rest of the step and its estimate. :attr:`code` is the
    exit code once it has ended (0 done, 130 stopped).
    """

    def __init__(self, shell: ServiceShell, config: RunConfig, model, data, args: argparse.Namespace):
        self.shell = shell
        self.config = config
        self.model = model
        self.data = data
        self.cloud = args.cloud_points
        self.steps = config.steps if config.steps is not None or data is None else len(data.observations)
        named = bool(getattr(model, "sensors", None))  # observations of several widths: checked per sensor
        shell.expect(RunShape(config.particles, model.dim, None if named else model.obs_dim, self.steps,
                              own_move=RunShape.of(config).own_move))
        self.wait_for = set(args.wait_for if args.wait_for is not None else (
            ["information", "system"] if config.preprocess else []))
        self.twin = ZenohTwin(shell, args.timeout) if config.preprocess else None
        self.live = LiveObservations(shell, model, config, args.observation_timeout) if data is None else None
        #: What the twin answers over Zenoh queries (its state, its forecast): dtpf.entity.answers.
        self.queries = live_answers(shell, config, model, getattr(args, "forecast", 0) or 0)
        self.period = 1.0 / args.rate if args.rate and data is not None else 0.0
        if self.wait_for:  # the run configuration, at once: a fleet's shared layers learn the twin from it
            shell.publish_status()
        self.startup_timeout = startup_wait(config, args.startup_timeout, self.wait_for)
        self.startup_deadline = time.monotonic() + self.startup_timeout
        self.pf: ParticleFilter | None = None
        self.pending: PendingStep | None = None
        self.truth = None
        #: Finished steps whose outputs wait for the next step's set to go out (:meth:`_publish_done`).
        self.done: deque[StepOutputs] = deque()
        self.next_tick = 0.0
        #: The exit code once the run has ended (None while it runs).
        self.code: int | None = None

    def poll(self, now: float) -> float | None:
        """Do what can be done now: at most one filter step. Returns when to look again at the latest
        (None: when something arrives), ``now`` if there is more to do at once."""
        if self.code is not None:
            return None
        if self.pf is None:
            if self.shell.stopping:
                self._end(130, "stopped before the first step")
                return None
            missing = self.wait_for - self.shell.presence.alive
            if missing and now < self.startup_deadline:
                return self.startup_deadline
            if missing:
                self.shell.log.warning("going on without %s: not alive after %.1f s", ", ".join(sorted(missing)),
                                       self.startup_timeout)
            self._start()
            return now
        if self.pending is None:
            try:
                wake = self._begin(now)
            finally:  # the last step's estimate, once the next step's set is out (or none is due, or it failed)
                self._publish_done()
            if self.pending is None:
                return wake
        if self.pending.asks:  # asked only with a twin to ask
            answer, waiting = self.twin.look(now)
            if waiting:
                return self.twin.deadline
        else:
            answer = None
        self._finish(answer)
        return now

    def _start(self) -> None:
        config, data = self.config, self.data
        # Without truth the filter is judged by how it predicts its data: the innovation too.
        self.pf = ParticleFilter(self.model, None if data is None else data.observations, config.particles,
                                 resampler=config.resampler, resample_below=config.resample_below,
                                 seed=config.seed, twin=config.twin, innovation=data is None or data.truth is None,
                                 jitter=config.jitter, sensors=None if data is None else data.sensors,
                                 drives=None if data is None else data.drives, block=config.block_particles)
        self.pf.warm_up()
        self.shell.running()
        if self.live is not None:
            self.shell.log.info("waiting for observations on %s", self.live.key)
        self.next_tick = time.monotonic()

    def _end(self, code: int, message: str, *values) -> None:
        self.shell.log.info(message, *values)
        self.code = code

    def _begin(self, now: float) -> float | None:
        """Begin the next step if its observation is there; else when to look again."""
        pf, shell = self.pf, self.shell
        if self.live is None:
            if pf.k >= pf.steps:
                self._end(0, "finished %d steps", pf.steps)
                return None
            if shell.stopping:
                self._end(130, "stopped after step %d of %d", pf.k, pf.steps)
                return None
            if self.period and now < self.next_tick:
                return self.next_tick
            observation = self.data.observations[pf.k]
            sensor = None if self.data.sensors is None else self.data.sensors[pf.k]
            drive = None if self.data.drives is None else self.data.drives[pf.k]
            self.truth = None if self.data.truth is None else self.data.truth[pf.k]
        else:
            if self.steps is not None and pf.k >= self.steps:
                self._end(0, "finished %d steps", pf.k)
                return None
            if shell.stopping:
                self._end(130, "stopped after step %d", pf.k)
                return None
            message = self.live.take(now)
            if message is None:
                return now if self.live.more else None  # a flood: the rest at once; else when one comes
            if message.end:
                self._end(0, "the sensor ended its stream after %d observations", pf.k)
                return None
            observation, self.truth = message.values, message.truth
            sensor, drive = message.sensor, getattr(message, "drive", None)
        self.pending = pending = pf.begin_step(observation, ask=self.twin is not None, sensor=sensor, drive=drive)
        if pending.asks:
            if self.twin.ask(pending, now):
                pf.work_ahead()  # off the lockstep's critical path; the same numbers
            else:
                self._finish(None)  # nobody to wait for: do not stall the filter
        return now

    def _finish(self, answer: Preprocessed | None) -> None:
        pending, self.pending = self.pending, None
        step = self.pf.finish_step(pending, answer)
        stamps = None if self.data is None else self.data.stamps
        stamp = None if stamps is None else int(stamps[step.step - 1])
        if self.live is not None and self.live.stamp is not None:
            stamp = self.live.stamp  # a driven twin's step is at its observation's time
        self.done.append(StepOutputs.of(self.shell, step, self.truth, pending.observation, self.model, self.config,
                                        self.cloud, stamp))
        self.queries.keep(step, self.done[-1].estimate)
        if self.period:
            self.next_tick += self.period

    def _publish_done(self) -> None:
        """Publish the outputs of the finished steps, in step order. :meth:`poll` calls it once the next
        step's particle set is out: the information layer then works on that set while this process
        encodes the estimate and the cloud (a lockstep step no longer waits for them)."""
        while self.done:
            self.done.popleft().publish(self.shell)


@dataclass
class StepOutputs:
    """What one finished filter step publishes, taken from the step at once (nothing in it shares memory
    with the filter's arrays, which the next step overwrites), and encoded when :meth:`publish` runs."""

    estimate: dict
    model_messages: list
    points: np.ndarray | None

    @classmethod
    def of(cls, shell: ServiceShell, step, truth, observation, model, config: RunConfig,
           cloud: int = 0, stamp: int | None = None) -> "StepOutputs":
        """``stamp``: the step's time (ns since the Unix epoch) when its observation file gives one (a
        rosbag2 log), the estimate's stamp; None: the estimate is stamped when it is made."""
        report = step.report
        estimate = dict(
            **shell.header(step.step), mean=step.mean.tolist(), var=step.var.tolist(),
            lower=step.lower.tolist(), upper=step.upper.tolist(), ess=step.ess,
            ess_ratio=step.ess / config.particles, resampled=step.resampled, degraded=step.degraded,
            truth=None if truth is None else [float(v) for v in truth],
            observation=[float(v) for v in observation],
            ps=report.ps if report is not None else None,
            log_predictive=step.log_predictive if np.isfinite(step.log_predictive) else None,
            innovation=step.innovation if step.innovation is not None and np.isfinite(step.innovation) else None,
            covariance=None if step.covariance is None else step.covariance.tolist())
        if step.sensor is not None:
            estimate["sensor"] = step.sensor
        if stamp is not None:
            estimate["stamp"] = Time.from_ns(stamp)
        # In the video scenario, its frame; the particle set as Foxglove draws it (entity/cloud.py says which
        # particles: a new array).
        return cls(estimate, list(model.step_messages(shell.header(step.step), step.particles, step.weights,
                                                      step.mean)),
                   cloud_points(step.particles, step.weights, cloud) if cloud else None)

    def publish(self, shell: ServiceShell) -> None:
        """The estimate, the model's messages, then the cloud."""
        shell.publish(Estimate(**self.estimate))
        for message in self.model_messages:
            shell.publish(message)
        if self.points is not None:
            cloud = PointCloud(**shell.header(self.estimate["step"]), timestamp=Time.now(), frame_id="state",
                               point_stride=POINT_STRIDE, data="",
                               fields=[PackedElementField(name=name, offset=offset, type=8) for name, offset in FIELDS])
            shell.publish(cloud, encode_with_base64(cloud, self.points.tobytes()))


#: Seconds a driven twin whose observations have ended waits for the end of its controls (a control source
#: that never says it ended: the twin goes on without what is still on the way).
CONTROL_END_WAIT = 2.0


def window_ns(seconds: float) -> int:
    """The reorder window of the run configuration (seconds) in integer nanoseconds, from its decimal text."""
    from decimal import Decimal

    return int(Decimal(repr(float(seconds))) * 1_000_000_000)


def drive_fields(sensor, drive) -> dict:
    """The fields a particle set carries of a driven step: its sensor, each piece's dt and control (none for a
    step that is not driven)."""
    fields = {}
    if sensor is not None:
        fields["sensor"] = sensor
    if drive is not None:
        fields["dt"] = drive.pieces[:, 0].tolist()
        if drive.pieces.shape[1] > 1:
            fields["control"] = drive.pieces[:, 1:].ravel().tolist()
    return fields


class LiveObservations:
    """The sensor's observations as they arrive: decoded, checked by the intake, counted; never blocks."""

    def __init__(self, shell: ServiceShell, model, config: RunConfig, quiet_after: float):
        self.shell = shell
        self.key = config.observation_key()
        calls = ModelCalls(model)
        #: A driven twin's intake (several sensors, controls, stamp order), or None.
        self.driven = DrivenIntake(calls, model.dim, window_ns(config.reorder_window)) if calls.driven else None
        #: The key of a driven twin's controls: one inbox with the observations keeps their arrival order.
        self.control_key = self.key.rpartition("/")[0] + "/control" if self.driven and calls.controls else None
        self.inbox = shell.inbox_on(self.key, *([self.control_key] if self.control_key else []))
        self.intake = self.driven if self.driven is not None else ObservationIntake(model.obs_dim, model.dim)
        self.quiet_after = quiet_after
        self.last = time.monotonic()
        #: Whether the last :meth:`take` left samples in the inbox (a flood: look again at once).
        self.more = False
        #: The stamp (ns) of the last observation taken, for a driven twin (None: estimates carry their own time).
        self.stamp = None
        #: When a driven twin's observations ended (its controls' end is awaited up to CONTROL_END_WAIT).
        self.ended_at: float | None = None
        shell.observation_counts = self.intake.counts

    def take(self, now: float) -> Observation | None:
        """The next accepted observation (or the end of the stream), None if none is in.

        After ``quiet_after`` seconds without one the status says so (state
        'waiting'), and 'running' again when one comes.
        """
        if self.driven is not None:
            return self._take_driven(now)
        shell = self.shell
        self.more = True
        for _ in range(TAKE_BUDGET):
            item = self.inbox.get(timeout=0)
            if item is None:
                break
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
                shell.log.info("observations again after %.1f s (sequence %d)", now - self.last, message.step)
                shell.state, shell.detail = ServiceState.RUNNING, None
                shell.publish_status()
            self.last = now
            return message
        else:
            self.inbox.ring()
            return None
        self.more = False
        self._quiet(now)
        return None

    def _take_driven(self, now: float):
        """:meth:`take` for a driven twin: controls and observations into its intake, the next step in stamp
        order out (a :class:`~dtpf.entity.intake.LiveStep`)."""
        shell, intake = self.shell, self.driven
        self.more = False
        for _ in range(TAKE_BUDGET):
            item = self.inbox.get(timeout=0)
            if item is None:
                break
            control = str(item.key) == self.control_key
            rejected = shell.rejected
            message = shell.receive(item, Control if control else Observation)
            if message is None:
                if shell.rejected > rejected and not control:
                    intake.malformed()
                continue
            verdict = intake.control(message) if control else intake.observation(message)
            if verdict is not None:
                shell.reject(verdict.reason, verdict.detail)
        else:
            self.inbox.ring()
            self.more = True
        if intake.ended and not intake.flushed:  # the observations ended: the controls' end, or a while
            self.ended_at = now if self.ended_at is None else self.ended_at
            if now - self.ended_at >= CONTROL_END_WAIT:
                shell.log.warning("the controls did not end within %.1f s of the observations: going on without "
                                  "the rest", CONTROL_END_WAIT)
                intake.finish()
            else:
                self.more = True
        step = intake.take()
        if step is None:
            self._quiet(now)
            return None
        if shell.state == ServiceState.WAITING:
            shell.log.info("observations again after %.1f s", now - self.last)
            shell.state, shell.detail = ServiceState.RUNNING, None
            shell.publish_status()
        self.last = now
        self.stamp = None if step.end else step.stamp
        self.more = self.more or bool(intake.ready)
        return step

    def _quiet(self, now: float) -> None:
        """Say in the status and the log when no observation has come for ``quiet_after`` seconds."""
        shell = self.shell
        quiet = now - self.last
        if quiet >= self.quiet_after and shell.state != ServiceState.WAITING:
            shell.state = ServiceState.WAITING
            shell.detail = (f"no observation for {quiet:.1f} s on {self.key} (last sequence "
                            f"{self.intake.last_sequence}); waiting")
            shell.log.warning("%s", shell.detail)
            shell.publish_status()


def forecast_horizon(text: str) -> int:
    """``--forecast H``: 0 (none) .. the most steps a published forecast carries."""
    from dtpf.messages.models import MAX_FORECAST_HORIZON

    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_FORECAST_HORIZON:
        raise argparse.ArgumentTypeError(f"--forecast takes 0 .. {MAX_FORECAST_HORIZON} steps, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m dtpf.entity.service",
        description="dtpf entity layer: runs the particle filter on a scenario, an observation file or a "
                    "live sensor, publishes each step's particle set and estimate, and resamples the "
                    "preprocessed set the information layer sends back.")
    add_run_arguments(parser, threads=True)
    parser.add_argument("--rate", type=float, default=None, metavar="STEPS_PER_SECOND",
                        help="run at most this many steps per second, like a sensor delivering "
                             "observations in real time (default: as fast as possible; live observations "
                             "set their own pace)")
    parser.add_argument("--cloud-points", type=int, default=1000, metavar="K",
                        help="publish each step's particle set as a foxglove.PointCloud on dtpf/<twin>/entity/cloud, "
                             "at most K particles (every ceil(N/K)-th; 0: none) (default: %(default)s)")
    parser.add_argument("--forecast", type=forecast_horizon, default=0, metavar="H",
                        help="also publish each step's forecast H steps ahead (mean, variance, 95%% band) on "
                             "dtpf/<twin>/entity/forecast_band, off the filter's path: a step that finds the "
                             "last one's forecast still being made is skipped (default: 0, none)")
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
