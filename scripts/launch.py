"""``dtpf launch``: the three layers and the recorder, with an embedded Zenoh.

The launcher opens a Zenoh session in router mode on a free loopback port
(nothing to install, no multicast), starts the recorder, the system, the
information and the entity services as child processes connected to it,
shows the entity's progress, and prints a summary when the run ends.
Ctrl-C (or SIGTERM) stops every child; the recorder finishes its file, so
the log stays readable.
"""
from __future__ import annotations

import argparse
import datetime as dt
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from messages import keys
from messages.bus import BusError, Inbox, free_port, open_session, zenoh_config
from messages.codec import MessageError, decode_for_key
from messages.config import RunConfig
from messages.models import Estimate, ServiceState, Status

__all__ = ["launch", "LaunchResult", "LaunchError"]

#: Start order: the recorder first (so nothing is missed), the entity last.
LAYERS = ("recorder", "system", "information", "entity")
MODULES = {"recorder": "scripts.record", "system": "system.service",
           "information": "information.service", "entity": "entity.service"}


class LaunchError(RuntimeError):
    """A service could not be started or failed; the message says which and why."""


@dataclass
class LaunchResult:
    """What the launcher saw of one run."""

    config: RunConfig
    log_path: Path
    estimates: list[Estimate] = field(default_factory=list)
    statuses: dict[str, Status] = field(default_factory=dict)
    exit_codes: dict[str, int | None] = field(default_factory=dict)
    elapsed: float = 0.0
    interrupted: bool = False

    @property
    def rmse(self) -> float:
        """RMSE against the truth the estimates carry (NaN when none does)."""
        errors = [np.subtract(e.mean, e.truth) for e in self.estimates if e.truth is not None]
        return float(np.sqrt(np.mean(np.square(errors)))) if errors else float("nan")

    @property
    def truth_steps(self) -> int:
        return sum(e.truth is not None for e in self.estimates)

    @property
    def rejected(self) -> dict[str, int]:
        return {layer: status.rejected for layer, status in self.statuses.items()}

    def summary(self) -> str:
        e = self.estimates
        c = self.config
        ps = [x.ps for x in e if x.ps is not None]
        of = f" of {c.steps}" if c.steps is not None else ""
        lines = [
            f"{'model' if c.model else 'scenario':<16}{c.model_ref} (N = {c.particles}, "
            f"{'T = ' + str(c.steps) if c.steps is not None else 'live'}, seed {c.seed}, twin {c.twin})",
            *([f"observations    {c.observations}"] if c.observations else []),
            f"steps           {len(e)}{of}{' (interrupted)' if self.interrupted else ''}",
            *judgement_lines(e),
            f"mean ESS        {np.mean([x.ess for x in e]):.1f}" if e else "mean ESS        -",
            f"resamplings     {sum(x.resampled for x in e)}",
            f"PS range        {min(ps):g} .. {max(ps):g}" if ps else "PS range        - (no preprocessed step)",
            f"degraded steps  {sum(x.degraded for x in e)}",
            "rejected        " + (", ".join(f"{k} {v}" for k, v in sorted(self.rejected.items())) or "-"),
            f"time            {self.elapsed:.2f} s",
            f"log             {self.log_path}",
        ]
        return "\n".join(lines)


def judgement_lines(estimates) -> list[str]:
    """How well the filter did: RMSE where the estimates carry the truth, else (and besides) the
    mean log predictive likelihood of the observations and the normalised innovation."""
    lines = []
    truth = [x for x in estimates if x.truth is not None]
    if truth:
        errors = np.array([np.subtract(x.mean, x.truth) for x in truth])
        rmse = float(np.sqrt(np.mean(errors ** 2)))
        lines.append(f"RMSE            {rmse:.4f}" + (f" (truth at {len(truth)} of {len(estimates)} steps)"
                                                      if len(truth) != len(estimates) else ""))
    if len(truth) != len(estimates) or not estimates:
        lp = [x.log_predictive for x in estimates if x.log_predictive is not None]
        lines.append(f"log predictive  {np.mean(lp):.4f} per step (mean of log p(z_k | z_1:k-1), "
                     f"{len(lp)} steps; no truth)" if lp else "log predictive  -")
        nis = [x.innovation for x in estimates if x.innovation is not None]
        if nis:
            m = len(estimates[-1].observation or []) or 1
            lines.append(f"innovation      {np.mean(nis):.3f} mean normalised innovation squared "
                         f"(about {m} when consistent)")
    return lines


def default_log_path(config: RunConfig) -> Path:
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{config.twin}-{config.run_id}-{stamp}.mcap"


def service_command(layer: str, config: RunConfig, endpoint: str, *, timeout: float, log_path: Path,
                    log_level: str, rate: float | None = None,
                    observation_timeout: float | None = None) -> list[str]:
    """The command line of one child service."""
    command = [sys.executable, "-m", MODULES[layer],
               "--scenario", config.scenario, "--particles", str(config.particles),
               "--resampler", config.resampler, "--threshold", str(config.threshold),
               "--weight-rule", config.weight_rule, "--policy", config.policy, "--ps", repr(config.ps),
               "--ps-rate", repr(config.ps_rate),
               "--seed", str(config.seed), "--twin", config.twin, "--run-id", config.run_id,
               "--timeout", repr(timeout), "--log-level", log_level, "--connect", endpoint,
               "--exit-with-parent"]
    if config.steps is not None:
        command += ["--steps", str(config.steps)]
    if config.model is not None:
        command += ["--model", config.model]
    if config.observations is not None:
        command += ["--observations", config.observations]
    if config.resample_below is not None:
        command += ["--resample-below", repr(config.resample_below)]
    if not config.preprocess:
        command += ["--no-preprocess"]
    if layer == "entity":
        wait = ["recorder"] + (["information", "system"] if config.preprocess else [])
        for other in wait:
            command += ["--wait-for", other]
        if rate:
            command += ["--rate", repr(rate)]
        if observation_timeout is not None:
            command += ["--observation-timeout", repr(observation_timeout)]
    if layer == "recorder":
        command += ["--output", str(log_path)]
    return command


def launch(config: RunConfig, *, log_path: Path | None = None, port: int | None = None,
           timeout: float = 2.0, startup_timeout: float = 20.0, log_level: str = "WARNING",
           rate: float | None = None, progress=None, child_output=None,
           observation_timeout: float | None = None) -> LaunchResult:
    """Run ``config`` as four processes around an embedded Zenoh router.

    ``rate`` caps the entity's steps per second (None: as fast as it can).
    A live run (``config.live``) has no deadline: it ends when the sensor ends
    its stream, after ``config.steps`` steps, or on Ctrl-C; ``observation_timeout``
    is the entity's ``--observation-timeout``.
    ``progress(step, total)`` is called for every estimate received.
    ``child_output`` is where the children's stderr goes (default: inherited).
    Raises LaunchError when the router cannot listen or a service fails to start.
    """
    log_path = Path(log_path) if log_path else default_log_path(config)
    port = port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    try:
        router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    except BusError as error:
        raise LaunchError(f"embedded Zenoh router cannot start on {endpoint}: {error}") from None
    result = LaunchResult(config, log_path)
    children: dict[str, subprocess.Popen] = {}
    start = time.monotonic()
    try:
        # Only what the summary needs: the particle sets are not copied into this process.
        watch = Inbox(router, keys.key(config.twin, "entity", "estimate"), keys.any_layer_pattern(config.twin, "status"))
        for layer in LAYERS:
            children[layer] = subprocess.Popen(
                service_command(layer, config, endpoint, timeout=timeout, log_path=log_path, log_level=log_level,
                                rate=rate, observation_timeout=observation_timeout),
                stderr=child_output, start_new_session=True)
        entity = children["entity"]
        per_step = timeout + (1.0 / rate if rate else 0.0)
        # A live run waits for its sensor as long as it takes; a file or simulation has T steps.
        deadline = float("inf") if config.live else (
            time.monotonic() + startup_timeout + per_step * (config.steps or _rows(config)) + 60.0)
        while True:
            for layer, child in children.items():
                if layer != "entity" and child.poll() is not None:
                    raise LaunchError(f"the {layer} service exited with code {child.returncode} "
                                      f"before the run ended")
            item = watch.get(timeout=0.1)
            if item is not None:
                _take(result, item, progress)
                continue
            if entity.poll() is not None:
                break
            if time.monotonic() > deadline:
                raise LaunchError("the run did not finish in time")
        if entity.returncode != 0:
            raise LaunchError(f"the entity service exited with code {entity.returncode}")
        # Final statuses of the other services arrive when they stop.
        _stop(children, ("information", "system"), result)
        _drain(watch, result, progress, quiet=0.3)
        _stop(children, ("recorder",), result)
    except KeyboardInterrupt:
        result.interrupted = True
    finally:
        _stop(children, tuple(reversed(LAYERS)), result)
        result.elapsed = time.monotonic() - start
        router.close()
    return result


def _rows(config: RunConfig) -> int:
    """The number of rows of the run's observation file (its steps when ``--steps`` is not given)."""
    from entity.observations import read_observations
    return read_observations(config.observation_file).steps


def _take(result: LaunchResult, item, progress) -> None:
    """Fold one received message into the result."""
    try:
        message = decode_for_key(item.key, item.payload)
    except MessageError:
        return  # the services count their own rejects
    if message.run_id != result.config.run_id:
        return
    if isinstance(message, Estimate):
        result.estimates.append(message)
        if progress is not None:
            progress(message.step, result.config.steps)
    elif isinstance(message, Status):
        result.statuses[message.layer.value] = message


def _drain(watch: Inbox, result: LaunchResult, progress, quiet: float) -> None:
    while (item := watch.get(timeout=quiet)) is not None:
        _take(result, item, progress)


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
