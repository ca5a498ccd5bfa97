"""``dtpf launch``: the three layers and the recorder, with an embedded Zenoh.

The launcher opens a Zenoh session in router mode on a free loopback port
(nothing to install, no multicast), starts the recorder and waits until it
listens (so the log holds every layer's first status), then the system, the
information and the entity services as child processes connected to it,
shows the entity's progress, and prints a summary when the run ends.

Only the entity's end ends the run. When the information or the system
service dies, the launcher says so, the entity runs on with plain resampling
(its estimates say ``degraded``) and the layer is started again, at most
``restarts`` times; when the recorder dies, a new recorder writes the rest of
the run into the next segment of the log (``run.1.mcap``, ``run.2.mcap``, ...).
Ctrl-C (or SIGTERM) stops every child; the recorder finishes its file, so
the log stays readable.
"""
from __future__ import annotations

import datetime as dt
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dtpf.messages import keys
from dtpf.messages.codec import MessageError, decode_for_key
from dtpf.messages.config import BLOCK_PARTICLES, RunConfig
from dtpf.messages.errors import DtpfError
from dtpf.messages.models import Estimate, Layer, ServiceState, Status
from dtpf.messages.names import REHEARSAL_WAIT
from dtpf.recording.logfile import what_it_holds
from dtpf.recording.writer import EXIT_LOG_WRITE, LogExistsError, LogWriteError, claim_log
from dtpf.shell.bus import BusError, Claims, Inbox, Presence, free_port, open_session, zenoh_config
from dtpf.shell.service import release_memory

__all__ = ["launch", "LaunchResult", "LaunchError", "EstimateTally", "Restart", "segment_path", "open_router",
           "rejected_by_layer"]

#: Start order: the recorder first (so nothing is missed), the entity last.
LAYERS = ("recorder", "system", "information", "entity")
MODULES = {"recorder": "dtpf.scripts.record", "system": "dtpf.system.service",
           "information": "dtpf.information.service", "entity": "dtpf.entity.service"}
#: How many times a dead layer is started again by default.
DEFAULT_RESTARTS = 3
#: Most messages the launcher takes from its inbox before it looks at its children again.
_BATCH = 64
#: Most competing steps an :class:`EstimateTally` names (the rest are counted).
MAX_COMPETING_STEPS = 10_000


class LaunchError(DtpfError, RuntimeError):
    """A service could not be started or failed; the message says which and why."""


@dataclass(frozen=True)
class Restart:
    """A layer process that died during the run, and what the launcher did about it."""

    layer: str
    step: int            #: the last step the launcher had seen when it noticed
    code: int | None     #: the dead process's exit code (negative: killed by that signal)
    restarted: bool      #: False once the layer's restarts were used up
    segment: Path | None = None  #: the recorder only: the file the new recorder writes
    bridge: Path | None = None   #: the recorder only: the file the launcher wrote until then

    def describe(self) -> str:
        how = _describe_code(self.code)
        then = "not started again (no restarts left)"
        if self.restarted:
            then = f"started again, writing {self.segment}" if self.segment else "started again"
        if self.bridge:
            then += f" (the launcher recorded the messages until then into {self.bridge})"
        when = f"after step {self.step}" if self.step else "before the first step"
        return f"the {self.layer} service died {when} ({how}); {then}"


def _describe_code(code: int | None) -> str:
    if code is not None and code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


class EstimateTally:
    """The figures of the launch summary, folded from the estimates as they arrive.

    Constant memory on runs of any length (``keep`` also keeps the estimates,
    for callers that want them). Estimates must come in step order 1, 2, ...
    (the entity publishes them so); one that repeats a step, skips ahead or
    lies beyond T is counted in :attr:`ignored` and not used.
    """

    def __init__(self, steps: int | None, keep: bool = False):
        self.steps = steps
        self.estimates: list[Estimate] | None = [] if keep else None
        self.count = 0
        self.ignored = 0
        self.truth_steps = 0
        self._squared_error = 0.0
        self._squared_error_values = 0
        self._ess = 0.0
        self.resamplings = 0
        self.degraded = 0
        self.ps_min = self.ps_max = None
        self._lp_sum, self._lp_count = 0.0, 0
        self._nis_sum, self._nis_count = 0.0, 0
        self.observed_values = 0
        #: Steps of the run that had an estimate besides the one taken (a repeat, or one sent ahead of the
        #: twin): another publisher of the twin's estimates; at most MAX_COMPETING_STEPS of them.
        self.competing_steps: set[int] = set()

    def add(self, estimate: Estimate) -> bool:
        """Fold one estimate in; False (and counted as ignored) if it is not the next step."""
        if estimate.step != self.count + 1 or (self.steps is not None and estimate.step > self.steps):
            self.ignored += 1
            if (self.steps is None or estimate.step <= self.steps) and len(self.competing_steps) < MAX_COMPETING_STEPS:
                self.competing_steps.add(estimate.step)
            return False
        self.count += 1
        if self.estimates is not None:
            self.estimates.append(estimate)
        if estimate.truth is not None:
            error = np.subtract(estimate.mean, estimate.truth)
            self.truth_steps += 1
            self._squared_error += float(np.sum(error ** 2))
            self._squared_error_values += error.size
        self._ess += estimate.ess
        self.resamplings += estimate.resampled
        self.degraded += estimate.degraded
        if estimate.ps is not None:
            self.ps_min = estimate.ps if self.ps_min is None else min(self.ps_min, estimate.ps)
            self.ps_max = estimate.ps if self.ps_max is None else max(self.ps_max, estimate.ps)
        if estimate.log_predictive is not None:
            self._lp_sum += estimate.log_predictive
            self._lp_count += 1
        if estimate.innovation is not None:
            self._nis_sum += estimate.innovation
            self._nis_count += 1
        self.observed_values = len(estimate.observation or [])
        return True

    @property
    def rmse(self) -> float:
        """RMSE against the truth the estimates carry (NaN when none does)."""
        if not self._squared_error_values:
            return float("nan")
        return float(np.sqrt(self._squared_error / self._squared_error_values))

    @property
    def mean_ess(self) -> float | None:
        return self._ess / self.count if self.count else None

    def judgement_lines(self) -> list[str]:
        """How well the filter did: RMSE where the estimates carry the truth, else (and besides) the
        mean log predictive likelihood of the observations and the normalised innovation."""
        lines = []
        if self.truth_steps:
            lines.append(f"RMSE            {self.rmse:.4f}" + (
                f" (truth at {self.truth_steps} of {self.count} steps)" if self.truth_steps != self.count else ""))
        if self.truth_steps != self.count or not self.count:
            lines.append(f"log predictive  {self._lp_sum / self._lp_count:.4f} per step (mean of log "
                         f"p(z_k | z_1:k-1), {self._lp_count} steps; no truth)" if self._lp_count
                         else "log predictive  -")
            if self._nis_count:
                lines.append(f"innovation      {self._nis_sum / self._nis_count:.3f} mean normalised innovation "
                             f"squared (about {self.observed_values or 1} when consistent)")
        return lines


@dataclass
class LaunchResult:
    """What the launcher saw of one run."""

    config: RunConfig
    log_path: Path
    tally: EstimateTally = None
    #: The last status of every layer process, by process id (only the launcher's own children).
    statuses_by_pid: dict[int, Status] = field(default_factory=dict)
    exit_codes: dict[str, int | None] = field(default_factory=dict)
    restarts: list[Restart] = field(default_factory=list)
    #: The files that make up the log, in order (more than one when the recorder was restarted).
    segments: list[Path] = field(default_factory=list)
    ignored_statuses: int = 0
    #: Set when the entity did not end its run normally (what happened, in words).
    failure: str | None = None
    #: Set when the log could not be written to the end (what happened and what the log holds, in words).
    log_problem: str | None = None
    elapsed: float = 0.0
    interrupted: bool = False
    #: Other entities that claimed the run's twin during the run (:class:`~dtpf.shell.bus.Claim`, in words):
    #: one twin, one entity; any fails the launch.
    competitors: list[str] = field(default_factory=list)

    def __post_init__(self):
        if self.tally is None:
            self.tally = EstimateTally(self.config.steps, keep=True)
        if not self.segments:
            self.segments = [self.log_path]

    @property
    def estimates(self) -> list[Estimate]:
        """The estimates, in step order (empty when the launch did not keep them)."""
        return self.tally.estimates or []

    @property
    def statuses(self) -> dict[str, Status]:
        """The last status of each layer (of its latest process)."""
        latest: dict[str, Status] = {}
        for status in self.statuses_by_pid.values():
            latest[status.layer.value] = status
        return latest

    @property
    def rmse(self) -> float:
        return self.tally.rmse

    @property
    def truth_steps(self) -> int:
        return self.tally.truth_steps

    @property
    def rejected(self) -> dict[str, int]:
        """Rejected messages per layer, summed over every process the layer had."""
        return rejected_by_layer(self.statuses_by_pid.values())

    def summary(self) -> str:
        t = self.tally
        c = self.config
        of = f" of {c.steps}" if c.steps is not None else ""
        log = " + ".join(str(path) for path in self.segments)
        lines = [
            f"{'model' if c.model else 'scenario':<16}{c.model_ref} (N = {c.particles}, "
            f"{'T = ' + str(c.steps) if c.steps is not None else 'live'}, seed {c.seed}, twin {c.twin})",
            *([f"observations    {c.observations}"] if c.observations else []),
            f"steps           {t.count}{of}{' (interrupted)' if self.interrupted else ''}",
            *t.judgement_lines(),
            f"mean ESS        {t.mean_ess:.1f}" if t.count else "mean ESS        -",
            f"resamplings     {t.resamplings}",
            f"PS range        {t.ps_min:g} .. {t.ps_max:g}" if t.ps_min is not None
            else "PS range        - (no preprocessed step)",
            f"degraded steps  {t.degraded}",
            "rejected        " + (", ".join(f"{k} {v}" for k, v in sorted(self.rejected.items())) or "-"),
            *(["restarts        " + "; ".join(r.describe() for r in self.restarts)] if self.restarts else []),
            *([f"ignored         {t.ignored} estimates and {self.ignored_statuses} statuses that were not the "
               f"run's own (repeated or out-of-order steps, unknown processes)"]
              if t.ignored or self.ignored_statuses else []),
            *self.competing_lines(),
            *([f"failed          {self.failure}"] if self.failure else []),
            *([f"log ended       {self.log_problem}"] if self.log_problem else []),
            f"time            {self.elapsed:.2f} s",
            f"log             {log}",
        ]
        return "\n".join(lines)

    def competing_lines(self) -> list[str]:
        """The summary's 'competing' lines: another entity of the twin, steps that had another estimate."""
        lines = [f"competing       another entity ran this twin during the run ({who})" for who in self.competitors]
        steps = sorted(self.tally.competing_steps)
        if steps:
            from dtpf.scripts.logs.summary import format_ranges
            lines.append(f"competing       {len(steps)} steps had an estimate besides the one taken "
                         f"({format_ranges(steps[:1000])}{', ...' if len(steps) > 1000 else ''}): the launcher used "
                         f"the one in step order")
        return lines


def rejected_by_layer(statuses) -> dict[str, int]:
    """The rejected messages of ``statuses`` (the last of each process, or of each process and twin), by layer."""
    totals: dict[str, int] = {}
    for status in statuses:
        totals[status.layer.value] = totals.get(status.layer.value, 0) + status.rejected
    return totals


def bridge_patterns(config: RunConfig) -> tuple[str, ...]:
    """The key expressions a launcher's bridge records: the twin's keys and its sensor's."""
    sensor = config.observation_key()
    pattern = keys.twin_pattern(config.twin)
    return (pattern, *([sensor] if sensor and not sensor.startswith(pattern[:-2]) else []))


def watch_recorder(process: subprocess.Popen, open_inbox, early: dict[int, Inbox], stopping) -> threading.Thread:
    """A thread that waits for the recorder ``process`` to end and at once opens ``open_inbox()`` into
    ``early[pid]``, unless ``stopping()``: the launcher's bridge then holds every message from the moment the
    recorder died, not from the moment its loop next looks at its children (0.1 s idle, more under load)."""
    def wait() -> None:
        process.wait()
        if not stopping():
            try:
                early[process.pid] = open_inbox()
            except Exception:  # the router is closing: the launcher's loop makes its own bridge, if any
                pass

    thread = threading.Thread(target=wait, name=f"watch-recorder-{process.pid}", daemon=True)
    thread.start()
    return thread


class Bridge:
    """The twin's messages, recorded by the launcher between a recorder's death and its successor.

    The launcher subscribes as soon as it sees the recorder gone and writes
    what a service would accept into a segment of its own, until the new
    recorder is listening; so a recorder's death loses only what it had not
    flushed. The new recorder's first messages may also be in the bridge's
    segment: :func:`dtpf.recording.logfile.join_logs` drops such repeats.
    """

    def __init__(self, router, config: RunConfig, path: Path, patterns: tuple[str, ...] | None = None,
                 inbox: Inbox | None = None):
        from dtpf.messages.admission import RunShape
        from dtpf.recording.writer import McapRecording

        self.config = config
        self.path = path
        self.shape = RunShape(config.particles, None, None, config.steps)
        try:  # a new file, as a recorder's: no segment is ever written over
            self.recording = McapRecording(path, compression="none", exclusive=True)
        except LogExistsError as error:
            raise LaunchError(str(error)) from None
        # ``inbox``: one opened the moment the recorder died (see :func:`watch_recorder`); else one now, on
        # the twin's keys and its sensor's (a fleet passes its own patterns).
        self.inbox = inbox if inbox is not None else Inbox(router, *(patterns or bridge_patterns(config)))
        self.written = 0

    def pump(self) -> None:
        """Write what has arrived."""
        while (item := self.inbox.get(timeout=0)) is not None:
            try:
                message = decode_for_key(item.key, item.payload)
            except MessageError:
                continue
            if message.run_id == self.config.run_id and self.shape.misfit(message) is None:
                self.recording.write(item.key, item.payload)
                self.written += 1

    def close(self) -> None:
        self.inbox.close()
        self.pump()
        self.recording.close()


def pump_bridges(bridges: list[Bridge], result, notify) -> None:
    """Write what each of the launcher's bridges has received. A bridge whose log cannot be written is
    dropped, and ``result.log_problem`` says what happened and what the log holds."""
    for bridge in list(bridges):
        try:
            bridge.pump()
        except LogWriteError as error:
            bridges.remove(bridge)
            result.log_problem = f"{error}; {what_it_holds(error.path)}"
            if notify is not None:
                notify(f"{result.log_problem}; the launcher stops recording")


def close_bridges(bridges: list[Bridge], result) -> None:
    """Close the launcher's bridges; one whose log cannot be finished sets ``result.log_problem``."""
    for bridge in bridges:
        try:
            bridge.close()
        except LogWriteError as error:
            result.log_problem = f"{error}; {what_it_holds(error.path)}"


def segment_path(log_path: Path, index: int) -> Path:
    """The file of the log's segment ``index``: the log itself for 0, ``run.<index>.mcap`` after."""
    log_path = Path(log_path)
    return log_path if index == 0 else log_path.with_name(f"{log_path.stem}.{index}{log_path.suffix}")


def default_log_path(config: RunConfig) -> Path:
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{config.twin}-{config.run_id}-{stamp}.mcap"


def service_command(layer: str, config: RunConfig, endpoint: str, *, timeout: float, log_path: Path,
                    log_level: str, rate: float | None = None,
                    observation_timeout: float | None = None, cloud_points: int | None = None,
                    secure: Path | None = None, wait_for_recorder: bool = True, forecast: int = 0,
                    threads: int | None = None) -> list[str]:
    """The command line of one child service (``secure``: the secure folder; its role is the layer;
    ``wait_for_recorder``: the entity waits for its twin's recorder too; ``threads``: the layers'
    ``--threads``, None: every core, their default)."""
    # -P: the child never imports from the working directory, where a user's own messages.py or
    # entity.py may sit beside their model.
    command = [sys.executable, "-P", "-m", MODULES[layer],
               "--scenario", config.scenario, "--particles", str(config.particles),
               "--resampler", config.resampler, "--threshold", str(config.threshold),
               "--weight-rule", config.weight_rule, "--move-rule", config.move_rule, "--jitter", config.jitter,
               "--policy", config.policy, "--ps", repr(config.ps),
               "--ps-rate", repr(config.ps_rate),
               "--seed", str(config.seed), "--twin", config.twin, "--run-id", config.run_id,
               "--timeout", repr(timeout), "--log-level", log_level, "--connect", endpoint,
               "--exit-with-parent"]
    if secure is not None:
        command += ["--secure", str(secure), "--role", layer]
    if config.steps is not None:
        command += ["--steps", str(config.steps)]
    if config.model is not None:
        command += ["--model", config.model]
    if config.observations is not None:
        command += ["--observations", config.observations]
    for sensor, path in (config.sensor_files or {}).items():  # a driven twin's sensors
        command += ["--observations", f"{sensor}={path}"]
    if config.controls is not None:
        command += ["--controls", config.controls]
    if config.reorder_window != RunConfig.model_fields["reorder_window"].default:
        command += ["--reorder-window", repr(config.reorder_window)]
    if config.reader is not None:
        command += ["--reader", config.reader]
    if config.topic is not None:
        command += ["--topic", config.topic]
    if config.ros2_fields is not None:
        command += ["--ros2-fields", config.ros2_fields]
    for sensor, paths in (config.sensor_fields or {}).items():  # a driven twin's sensors on ROS 2 topics
        command += ["--ros2-fields", f"{sensor}={paths}"]
    if config.control_fields is not None:
        command += ["--ros2-control-fields", config.control_fields]
    if config.partial:
        command += ["--partial"]
    if config.resample_below is not None:
        command += ["--resample-below", repr(config.resample_below)]
    if config.choose_base is not None:
        command += ["--choose-base", config.choose_base]
    if not config.preprocess:
        command += ["--no-preprocess"]
    if config.block_particles != BLOCK_PARTICLES:
        command += ["--block-particles", "none" if config.block_particles is None else str(config.block_particles)]
    if threads is not None and layer != "recorder":
        command += ["--threads", str(threads)]
    if layer == "entity":
        wait = (["recorder"] if wait_for_recorder else []) + (["information", "system"] if config.preprocess else [])
        for other in wait:
            command += ["--wait-for", other]
        if rate:
            command += ["--rate", repr(rate)]
        if observation_timeout is not None:
            command += ["--observation-timeout", repr(observation_timeout)]
        if cloud_points is not None:
            command += ["--cloud-points", str(cloud_points)]
        if forecast:
            command += ["--forecast", str(forecast)]
    if layer == "recorder":
        command += ["--output", str(log_path)]
    return command


class interrupts_held:
    """Ctrl-C and SIGTERM, arriving inside this block, take effect when it ends.

    A KeyboardInterrupt raised between taking a message off the inbox and folding it into the tally lost
    that estimate (the summary then counted the next one as out of order). Inside the block such a signal
    is noted; at its end the handler that was installed runs (it raises KeyboardInterrupt). Outside the
    main thread, where handlers cannot be set, the block does nothing.
    """

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __enter__(self):
        self._noted: list[int] = []
        self._handlers = {}
        if threading.current_thread() is threading.main_thread():
            for signum in self._SIGNALS:
                self._handlers[signum] = signal.signal(signum, lambda signum, _frame: self._noted.append(signum))
        return self

    def __exit__(self, *exc_info):
        for signum, handler in self._handlers.items():
            signal.signal(signum, handler)
        if self._noted and exc_info[0] is None:
            handler = self._handlers[self._noted[0]]
            if callable(handler):
                handler(self._noted[0], None)
            elif handler == signal.SIG_DFL and self._noted[0] == signal.SIGINT:
                raise KeyboardInterrupt
            elif handler == signal.SIG_DFL:
                signal.raise_signal(self._noted[0])
        return False


def bridge_command(config: RunConfig, endpoint: str, options: list[str], *, log_level: str = "WARNING",
                   secure: Path | None = None) -> list[str]:
    """The command line of the ROS 2 bridge (:mod:`dtpf.scripts.ros2.bridge`) of a ``ros2:TOPIC`` run (or a
    driven twin's ``NAME=ros2:TOPIC`` sensors and ``ros2:TOPIC`` controls): its topics, field paths, model,
    twin and run id, and ``options`` (--ros2-type, --ros2-pose, ...)."""
    inputs = ["--observations", config.observations] if config.observations is not None else []
    for sensor, source in (config.sensor_files or {}).items():
        inputs += ["--observations", f"{sensor}={source}"]
    for sensor, paths in (config.sensor_fields or {}).items():
        inputs += ["--ros2-fields", f"{sensor}={paths}"]
    if config.controls is not None:
        inputs += ["--controls", config.controls]
    if config.control_fields is not None:
        inputs += ["--ros2-control-fields", config.control_fields]
    command = [sys.executable, "-P", "-m", "dtpf.scripts.ros2", *inputs,
               "--scenario", config.scenario, "--seed", str(config.seed), "--twin", config.twin,
               "--run-id", config.run_id, "--connect", endpoint, "--exit-with-parent",
               "--log-level", "INFO" if log_level == "WARNING" else log_level, *options]
    if config.model is not None:
        command += ["--model", config.model]
    if config.ros2_fields is not None:
        command += ["--ros2-fields", config.ros2_fields]
    if secure is not None:
        command += ["--secure", str(secure)]
    return command


def launch(config: RunConfig, *, log_path: Path | None = None, port: int | None = None,
           timeout: float = 2.0, startup_timeout: float = 20.0, log_level: str = "WARNING",
           rate: float | None = None, progress=None, child_output=None,
           observation_timeout: float | None = None, restarts: int = DEFAULT_RESTARTS,
           keep_estimates: bool = True, notify=None, cloud_points: int | None = None,
           foxglove: tuple[str, int] | None = None, secure=None, record: bool = True,
           ros2: list[str] | None = None, overwrite: bool = False, forecast: int = 0,
           threads: int | None = None) -> LaunchResult:
    """Run ``config`` as four processes around an embedded Zenoh router.

    ``rate`` caps the entity's steps per second (None: as fast as it can).
    A live run (``config.live``) has no deadline: it ends when the sensor ends
    its stream, after ``config.steps`` steps, or on Ctrl-C; ``observation_timeout``
    is the entity's ``--observation-timeout``.
    ``progress(step, total)`` is called for every estimate received.
    ``child_output`` is where the children's stderr goes (default: inherited).
    ``restarts``: how many times a dead information, system or recorder
    process is started again (0: never; the run goes on without it).
    ``keep_estimates``: keep every Estimate in the result (False: only the
    summary's figures, constant memory on long runs).
    ``notify(text)`` is told at once when a layer dies or is started again
    (default: a line on stderr). ``cloud_points``: the entity's ``--cloud-points``
    (None: its default); ``forecast``: its ``--forecast`` (0: none). ``foxglove``: (host, port) to serve the run live to
    Foxglove from the launcher (:mod:`dtpf.scripts.foxglove_bridge`). ``secure``: a
    folder of ``dtpf secure init`` (:mod:`dtpf.shell.secure`); the router then
    listens on its protocol (``tls/`` or ``tcp/`` with passwords) and enforces
    its access control, and each service connects as the role of its layer.
    ``record``: False runs no recorder (the split alone, for benchmarks); nothing is logged.
    A log is never overwritten: when ``log_path`` or its segments (``run.1.mcap``, ...) exist, LaunchError
    before anything starts, unless ``overwrite``, which removes them (and says so through ``notify``).
    ``ros2``: options of the ROS 2 bridge (``dtpf ros2``), started beside the layers when the observations
    are ``ros2:TOPIC`` (:func:`bridge_command`); it needs rclpy in this Python. ``threads``: each layer's
    ``--threads`` (None: every core; the layers run in lockstep, rarely at the same time).
    Raises LaunchError when the router cannot listen, a service fails to start
    or refuses its configuration; the entity's failure ends the run with
    :attr:`LaunchResult.failure` set.
    """
    log_path = Path(log_path) if log_path else default_log_path(config)
    notify = notify or (lambda text: print(f"dtpf launch: {text}", file=sys.stderr, flush=True))
    if record:  # a log is never overwritten: LaunchError before anything starts (``overwrite``: replaced)
        try:
            removed = claim_log(log_path, overwrite)
        except LogExistsError as error:
            raise LaunchError(str(error)) from None
        if removed:
            notify(f"removed {', '.join(str(path) for path in removed)} (overwrite)")
    router, endpoint, secure = open_router(port, secure)
    result = LaunchResult(config, log_path, tally=EstimateTally(config.steps, keep=keep_estimates))
    children: dict[str, subprocess.Popen] = {}
    layer_of_pid: dict[int, str] = {}
    used = {layer: 0 for layer in LAYERS}
    gone: set[str] = set()  # layers that died with no restart left
    bridges: list[Bridge] = []  # the launcher's own recording while a new recorder starts
    early: dict[int, Inbox] = {}  # a dead recorder's pid -> the bridge's inbox, opened the moment it died
    watchers: dict[int, threading.Thread] = {}  # a recorder's pid -> the thread that waits for it
    stopping = threading.Event()  # set once the recorders are being stopped on purpose
    start = time.monotonic()

    def start_child(layer: str, output: Path) -> None:
        children[layer] = subprocess.Popen(
            service_command(layer, config, endpoint, timeout=timeout, log_path=output, log_level=log_level,
                            rate=rate, observation_timeout=observation_timeout, cloud_points=cloud_points,
                            secure=secure.path if secure is not None else None, wait_for_recorder=record,
                            forecast=forecast, threads=threads),
            stderr=child_output, start_new_session=True)
        layer_of_pid[children[layer].pid] = layer
        if layer == "recorder" and record:
            watchers[children[layer].pid] = watch_recorder(
                children[layer], lambda: Inbox(router, *bridge_patterns(config)), early, stopping.is_set)

    def revive(layer: str) -> None:
        code = children[layer].returncode
        inbox = None
        if layer == "recorder" and (watcher := watchers.pop(children[layer].pid, None)) is not None:
            watcher.join(timeout=2.0)  # it opens the inbox right after the process ended, which this saw
            inbox = early.pop(children[layer].pid, None)
        if inbox is not None and (code == 2 or code == EXIT_LOG_WRITE):
            inbox.close()  # no bridge follows
        if code == 2:  # the service refused its arguments or configuration: starting it again cannot help
            raise LaunchError(f"the {layer} service exited with code 2 (a configuration error; see above)")
        if layer == "recorder" and code == EXIT_LOG_WRITE:
            # The log's disk is full, over a size limit or read-only (or the file went away): a new recorder, or
            # the launcher's own bridge, would write into the same place. The run goes on unrecorded.
            gone.add(layer)
            status = result.statuses.get("recorder")
            said = status.last_error if status is not None and status.last_error else None
            result.log_problem = said or f"the recorder could not write {result.segments[-1]}; " \
                                         f"{what_it_holds(result.segments[-1])}"
            notify(f"{result.log_problem}; the run goes on without a recorder (not started again: it would "
                   f"write to the same place)")
            return
        again = used[layer] < restarts
        segment = bridge = None
        if layer == "recorder":  # the launcher records until a new recorder listens (or to the end)
            bridge = segment_path(log_path, len(result.segments))
            bridges.append(Bridge(router, config, bridge, inbox=inbox))
            result.segments.append(bridge)
        if again:
            used[layer] += 1
            if layer == "recorder":
                segment = segment_path(log_path, len(result.segments))
                result.segments.append(segment)
            start_child(layer, segment or log_path)
        else:
            gone.add(layer)
        event = Restart(layer, result.tally.count, code, again, segment, bridge)
        result.restarts.append(event)
        notify(event.describe())

    presence = watch = bridge_to_foxglove = ros2_bridge = claims = None
    try:
        if foxglove is not None:
            from dtpf.scripts.foxglove_bridge import FoxgloveBridge
            try:
                bridge_to_foxglove = FoxgloveBridge(router, config.twin, *foxglove)
            except Exception as error:  # foxglove-sdk: a port in use, mostly
                raise LaunchError(f"cannot serve Foxglove on {foxglove[0]}:{foxglove[1]}: {error}") from None
            notify(f"serving the run to Foxglove on ws://{foxglove[0]}:{bridge_to_foxglove.port}")
        # Only what the summary needs: the particle sets are not copied into this process.
        watch = Inbox(router, keys.key(config.twin, "entity", "estimate"), keys.any_layer_pattern(config.twin, "status"),
                      max_payload=1 << 20, max_items=10_000)
        presence = Presence(router, config.twin, "launcher", names=[layer.value for layer in Layer])
        claims = Claims(router, config.twin)  # every entity of the twin: the launcher's own and any other
        # The recorder first, and listening, before any layer says it is running.
        if record:
            start_child("recorder", log_path)
            _wait_for_recorder(children["recorder"], presence, startup_timeout)
        for layer in LAYERS[1:]:
            start_child(layer, log_path)
        if config.ros2_inputs:
            ros2_bridge = subprocess.Popen(
                bridge_command(config, endpoint, ros2 or [], log_level=log_level,
                               secure=secure.path if secure is not None else None),
                stderr=child_output, start_new_session=True)
        per_step = timeout + (1.0 / rate if rate else 0.0)
        # A live run waits for its sensor as long as it takes; a file or simulation has T steps.
        deadline = float("inf") if config.live else (
            time.monotonic() + startup_timeout + per_step * (config.steps or _rows(config)) + 60.0
            + (REHEARSAL_WAIT if config.rehearses else 0.0))
        next_trim = time.monotonic() + 10.0
        while True:
            # Every turn looks at the children and the deadline, whatever arrives (a flood cannot hold it).
            with interrupts_held():  # a message taken off the inbox is folded in, whatever signal comes
                item = watch.get(timeout=0.1)
                taken = 0
                while item is not None:
                    _take(result, item, progress, layer_of_pid)
                    taken += 1
                    item = watch.get(timeout=0) if taken < _BATCH else None
            pump_bridges(bridges, result, notify)
            if bridges and "recorder" not in gone and children["recorder"].pid in result.statuses_by_pid:
                bridges.pop().close()  # the new recorder listens: it said so
            if children["entity"].poll() is not None:
                break
            if ros2_bridge is not None and ros2_bridge.poll() is not None:
                raise LaunchError(f"the ROS 2 bridge ended: {_describe_code(ros2_bridge.returncode)} (see above)")
            for layer in LAYERS[:-1]:
                if layer in children and layer not in gone and children[layer].poll() is not None:
                    revive(layer)
            if time.monotonic() > deadline:
                raise LaunchError("the run did not finish in time")
            if time.monotonic() > next_trim:  # what a flood on the launcher's keys left is given back
                release_memory()
                next_trim = time.monotonic() + 10.0
        entity_code = children["entity"].returncode
        if ros2_bridge is not None:  # what the entity published last is out on ROS 2 before the bridge stops
            _stop({"ros2": ros2_bridge}, ("ros2",), result)
            result.exit_codes.pop("ros2", None)
        if entity_code != 0:
            result.failure = f"the entity service ended the run: {_describe_code(entity_code)}"
        # Final statuses of the other services arrive when they stop.
        _stop(children, ("information", "system"), result)
        _drain(watch, result, progress, layer_of_pid, quiet=0.3, entity_pid=children["entity"].pid)
        if entity_code != 0 and (said := _entity_error(result.statuses_by_pid.get(children["entity"].pid))):
            result.failure = said  # the entity's own line (a model failing at a step, say), not its exit code
        stopping.set()
        _stop(children, ("recorder",), result)
    except KeyboardInterrupt:
        result.interrupted = True
    finally:
        # The entity first, so its last step still has its answer; what it published is taken before the
        # layers and the recorder stop, so the summary and the log tell the same run.
        try:
            if result.interrupted:
                _stop(children, ("entity",), result)
                if watch is not None:
                    _drain(watch, result, progress, layer_of_pid, quiet=0.3)
                _stop(children, ("information", "system"), result)
        except KeyboardInterrupt:  # a second Ctrl-C: no more waiting for the drain
            pass
        stopping.set()
        close_bridges(bridges, result)
        _stop(children, tuple(reversed(LAYERS)), result)
        for inbox in list(early.values()):  # a recorder that died as the run ended: no bridge followed
            inbox.close()
        if ros2_bridge is not None:
            _stop({"ros2": ros2_bridge}, ("ros2",), result)
            result.exit_codes.pop("ros2", None)
        if bridge_to_foxglove is not None:
            bridge_to_foxglove.close()
        result.elapsed = time.monotonic() - start
        if presence is not None:
            presence.close()
        if claims is not None:  # one twin, one entity: another that claimed the twin fails the launch
            mine = [pid for pid, layer in layer_of_pid.items() if layer == "entity"]
            result.competitors = [claim.describe() for claim in claims.others(mine)]
            claims.close()
            if result.competitors and result.failure is None:
                result.failure = (f"another entity ran twin {config.twin} during the run "
                                  f"({'; '.join(result.competitors)}): the estimates on its keys are not one "
                                  f"twin's run")
        router.close()
    return result


def open_router(port: int | None, secure=None):
    """The launcher's Zenoh router on 127.0.0.1 (``port`` or a free one): (session, endpoint, secure
    folder or None). With ``secure`` (a folder of ``dtpf secure init``) it listens on the folder's
    protocol and enforces its access control. LaunchError names what went wrong."""
    port = port or free_port()
    if secure is not None:
        from dtpf.shell.secure import SecureError, open_secure_dir
        try:
            secure = open_secure_dir(secure)
        except SecureError as error:
            raise LaunchError(str(error)) from None
    endpoint = secure.endpoint("127.0.0.1", port) if secure is not None else f"tcp/127.0.0.1:{port}"
    try:
        router = open_session(zenoh_config(mode="router", listen=[endpoint], secure=secure,
                                           role="router" if secure is not None else None),
                              in_use_hint="give --port another port, or leave --port out for a free one")
    except BusError as error:
        said = str(error).removeprefix(f"cannot listen on {endpoint}: ")
        raise LaunchError(f"embedded Zenoh router cannot start on {endpoint}: {said}") from None
    return router, endpoint, secure


def _wait_for_recorder(recorder: subprocess.Popen, presence: Presence, timeout: float) -> None:
    """Until the recorder's liveliness token is up (it declares it once it is subscribed)."""
    deadline = time.monotonic() + timeout
    while "recorder" in presence.wait_for(["recorder"], 0.1):
        if recorder.poll() is not None:
            raise LaunchError(f"the recorder exited with code {recorder.returncode} before it started")
        if time.monotonic() > deadline:
            raise LaunchError(f"the recorder did not come up within {timeout:g} s")


def _rows(config: RunConfig) -> int:
    """The number of rows of the run's observation file (its steps when ``--steps`` is not given)."""
    from dtpf.entity.sources import read_table
    if config.sensor_files:  # a driven twin's sensors: every row of every file
        from dtpf.entity import stamped
        return stamped.rows(config)
    return read_table(config).steps


def _take(result: LaunchResult, item, progress, layer_of_pid: dict[int, str]) -> bool:
    """Fold one received message into the result: estimates of this run in step order, and
    statuses of the launcher's own children (one that claims a child's layer from another
    process is counted as ignored; a sensor's is none of the launcher's business). True when the
    message was the run's own and taken."""
    try:
        message = decode_for_key(item.key, item.payload)
    except MessageError:
        return False  # the services count their own rejects
    if message.run_id != result.config.run_id:
        return False
    if isinstance(message, Estimate):
        taken = result.tally.add(message)
        if taken and progress is not None:
            progress(message.step, result.config.steps)
        return taken
    if isinstance(message, Status):
        if message.layer.value not in LAYERS:
            return False  # a sensor, a viewer: not a process of the launcher, and not its business
        if layer_of_pid.get(message.pid) != message.layer.value:
            result.ignored_statuses += 1
            return False
        result.statuses_by_pid[message.pid] = message
        return True
    return False


def _entity_error(status: Status | None) -> str | None:
    """The one line a failed entity's final status gives (``step 5: the model's propagate raised ...``, as
    ``dtpf run`` says it), without the exception's class name for the errors dtpf words itself; None when it
    said nothing."""
    if status is None or status.state != ServiceState.FAILED or not status.last_error:
        return None
    text = status.last_error
    for name in ("FilterError: ", "ModelError: ", "ObservationError: "):
        if text.startswith(name):
            return text[len(name):]
    return text


def _drain(watch: Inbox, result: LaunchResult, progress, layer_of_pid, quiet: float, entity_pid=None) -> None:
    """Take what is still in flight until none of the run's own messages came for ``quiet`` seconds (what
    others publish meanwhile, a flood of statuses say, does not hold the launcher), at most 5 s; with
    ``entity_pid``, not before that entity's final status (its last message: what it published before has
    arrived by then, however far behind a loaded machine left this process)."""
    deadline = time.monotonic() + 5.0
    last_taken = time.monotonic()

    def entity_done() -> bool:
        status = result.statuses_by_pid.get(entity_pid)
        return status is not None and status.state in (ServiceState.FINISHED, ServiceState.FAILED)

    while (now := time.monotonic()) < deadline:
        if now - last_taken >= quiet and (entity_pid is None or entity_done()):
            break
        with interrupts_held():
            item = watch.get(timeout=max(0.01, quiet - (now - last_taken)))
            if item is not None and _take(result, item, progress, layer_of_pid):
                last_taken = time.monotonic()


def _stop(children: dict[str, subprocess.Popen], layers, result: LaunchResult, grace: float = 10.0) -> None:
    """SIGINT to each running child, then wait; SIGKILL after ``grace`` seconds."""
    running = [layer for layer in layers if layer in children and children[layer].poll() is None]
    for layer in running:
        children[layer].send_signal(signal.SIGINT)
    for layer in running:
        try:
            children[layer].wait(timeout=grace)
        except subprocess.TimeoutExpired:
            children[layer].kill()
            children[layer].wait()
    for layer in layers:
        if layer in children:
            result.exit_codes[layer] = children[layer].returncode
