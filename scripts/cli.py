"""The ``dtpf`` command.

``dtpf run`` runs the three layers in one process on a scenario and prints a
summary. ``dtpf --help`` and ``dtpf run --help`` explain every option.
"""
from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from dtpf.entity import sources
from dtpf.messages import family
from dtpf.messages.config import add_run_arguments, config_from_args
from dtpf.scripts.console import ProgressBar, run_command
from dtpf.scripts.sensor import sensor_command
from dtpf.shell.bus import free_port

__all__ = ["main", "kernels_cold"]

#: The modules whose numba kernels every launch compiles (cache=True: once, then from the on-disk cache).
KERNEL_MODULES = ("dtpf.entity._merge", "dtpf.information.mirror", "dtpf.information.rules",
                  "dtpf.messages._seedseq")
#: The growth models' kernels, compiled by a run of the ungm scenarios.
GROWTH_KERNELS = "dtpf.entity._growth"



def resolved_config(args: argparse.Namespace):
    """The RunConfig of the arguments, with T fixed to the observation file's rows when --steps is
    not given (so every process and the progress bar know T)."""
    from dtpf.entity.sources import read_table

    config = config_from_args(args, choose_by_default=True)
    if config.observation_file is not None and config.steps is None:
        config = config.model_copy(update={"steps": read_table(config).steps})
    if config.sensor_files and config.steps is None and not config.live:  # a driven twin's files: every row
        from dtpf.entity import stamped
        config = config.model_copy(update={"steps": stamped.rows(config)})
    return fit_simulation(config, args)


def fit_simulation(config, args: argparse.Namespace):
    """A simulated run of a model with a most number of steps (the video's 50 frames) takes that many
    when --steps is not given; more than that is a clear error here, before any process starts."""
    if not config.simulated:
        return config
    most = getattr(sources.load_model(config, check=False), "max_steps", None)
    if most is None or config.steps <= most:
        return config
    if args.steps is None:
        return config.model_copy(update={"steps": most})
    raise ValueError(f"--steps: the {config.model_ref} scenario can simulate at most {most} steps, got {config.steps}")


#: What a run whose system layer rehearses the model says before its first step.
REHEARSING = ("dtpf: rehearsing the model (--choose-base rehearse: every arm on 200 to 1,600 simulated runs), "
              "seconds to a minute or two, once per model, N and T (then kept in ~/.cache/dtpf/rehearsals)")


def rehearse_first(config, model=None, *, for_services: bool = False) -> None:
    """Make the rehearsal of ``config``'s system layer here and say its base (``dtpf run``; ``dtpf launch`` before
    any service starts, ``for_services``: the system service then reads it from the cache,
    :func:`dtpf.system.rehearse.cache_folder`, and starts at once). A model whose rehearsal is not kept on disk is
    left to the system service, with the notice that it rehearses. Where it is kept already, one line says so; a
    model that cannot be rehearsed says nothing (its system layer logs why); nor does one that fails to load or to
    rehearse (the run says what is wrong)."""
    import threading
    import time

    from dtpf.system import rehearse
    from dtpf.system.layer import SystemLayer

    if for_services and model is not None and not rehearse.kept_on_disk(model):
        print(REHEARSING, file=sys.stderr, flush=True)
        return
    start = time.perf_counter()
    notice = threading.Timer(1.0, lambda: print(REHEARSING, file=sys.stderr, flush=True))  # a rehearsal being made
    notice.daemon = True
    notice.start()
    try:
        model = model if model is not None else sources.load_model(config, check=False)
        rehearsal = getattr(SystemLayer.from_config(config, model=model).policy, "rehearsal", None)
    except Exception:  # noqa: BLE001 - a model or setting that fails here fails the run, which says it in one line
        return
    finally:
        notice.cancel()
    if rehearsal is None:
        return
    how = "kept from an earlier run" if rehearse.last_kept else f"made in {time.perf_counter() - start:.1f} s"
    print(f"dtpf: rehearsal: base {rehearsal.arm} ({rehearsal.runs:,} simulated runs, T = {rehearsal.steps}, "
          f"{rehearsal.particles} particles an arm, {how})", file=sys.stderr, flush=True)


def _model_or_none(config):
    """The run's model, or None when it does not load (the run then says why, in one line)."""
    try:
        return sources.load_model(config, check=False)
    except Exception:  # noqa: BLE001 - a user's model may fail to load in any way
        return None


def settle_rehearsal(config, args: argparse.Namespace, model=None):
    """The run's config once its model is known: a rehearsal the command line chose by default (no --choose-base)
    for a model that cannot be rehearsed (:func:`dtpf.system.rehearse.why_not`: no sample_observation, driven, several
    sensors) gives way to the default base, roughening, without a word. A model that does not load is left to the
    run, which says what is wrong."""
    if not config.rehearses:
        return config
    from dtpf.system.rehearse import why_not

    model = model if model is not None else _model_or_none(config)
    if model is None:
        return config
    reason = why_not(model)
    if reason is not None and getattr(args, "choose_base", None) is None:
        return config.model_copy(update={"choose_base": None})
    return config


def cmd_run(args: argparse.Namespace) -> int:
    from dtpf.entity import cores
    from dtpf.scripts.inprocess import run

    cores.set_threads(args.threads)
    # run() reads the file once; T is its rows unless --steps is smaller
    config = fit_simulation(config_from_args(args, choose_by_default=True), args)
    if config.rehearses:  # the model, loaded once for both (run() loads and checks it again, as for any run)
        model = _model_or_none(config)
        config = settle_rehearsal(config, args, model)
        if config.rehearses and not args.quiet and model is not None:
            rehearse_first(config, model)
    result = run(config, progress=None if args.quiet else ProgressBar(),
                 note=lambda problem: print(f"dtpf: note: {problem}", file=sys.stderr))
    ps = result.ps
    ps_text = "off" if not config.preprocess else f"{np.nanmin(ps):g} .. {np.nanmax(ps):g}"
    lines = [
        f"{'model' if config.model else 'scenario':<16}{config.model_ref} (N = {config.particles}, "
        f"T = {len(result.steps)}, seed {config.seed})",
        *([f"observations    {config.observations}"] if config.observations else []),
        f"resampling      {config.resampler}, with the move of the arm in force (below)" if result.arms else
        f"resampling      {'DT preprocessing + ' if config.preprocess else ''}{config.resampler}"
        f"{'' if config.jitter == 'none' else ', then the move ' + config.jitter}",
    ]
    if result.has_truth:
        covered = ""
        if result.partial_truth:
            covered = (f" over {', '.join(f'x[{c}]' for c in result.components)} of the state's "
                       f"{len(result.steps[0].mean)} components (truth columns {', '.join(result.truth_columns)})")
        lines.append(f"RMSE            {result.rmse:.4f}{covered}")
    else:
        lines.append(f"log predictive  {np.mean(result.log_predictive):.4f} per step (mean of log p(z_k | z_1:k-1); "
                     f"no truth)")
        nis = result.innovations
        if np.isfinite(nis).any():
            lines.append(f"innovation      {np.nanmean(nis):.3f} mean normalised innovation squared (about "
                         f"{result.observations.shape[1]} when consistent)")
    lines += [
        f"mean ESS        {result.mean_ess:.1f} ({result.mean_ess / config.particles:.1%} of N)",
        f"resamplings     {result.resamplings}",
        f"PS range        {ps_text}",
        *([f"preprocessed    {sum(s.report is not None and s.report.n_processed > 0 for s in result.steps)} of "
           f"{len(result.steps)} steps moved particles (policy {config.policy}: off elsewhere)"]
          if config.preprocess and not family.POLICIES.trait(config.policy, "initial_preprocess", True) else []),
        *([f"arms in force   {', '.join(f'{arm} {count}' for arm, count in result.arms.items())} steps "
           f"(policy {config.policy}; base {result.base[0]}: {_base_reached(result.base[1])})"] if result.arms else []),
        f"degraded steps  {result.degraded}",
        f"time            {result.elapsed:.3f} s ({1e3 * result.elapsed / max(1, len(result.steps)):.3f} ms/step)",
    ]
    print("\n".join(lines))
    return 0


def _base_reached(how: str) -> str:
    """How a choosing run's base was reached, for its summary: "named", "the default", or "from a rehearsal ..."."""
    return how if how in ("named", "the default") else f"from {how}"


def kernels_cold(config=None) -> list[str]:
    """The kernel modules of a run of ``config`` whose numba on-disk cache is missing or older than the
    source, so that the first launch compiles them (about 30 s on 2 cores); empty when the cache is warm.

    Looks where numba keeps it: ``$NUMBA_CACHE_DIR`` when set, else the ``__pycache__`` beside each
    module, then the user-wide cache (``~/.cache/numba``); numba itself is not imported.
    """
    import importlib.util
    import os

    modules = list(KERNEL_MODULES)
    if config is None or (config.model is None and config.scenario.startswith("ungm")):
        modules.append(GROWTH_KERNELS)
    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    custom = os.environ.get("NUMBA_CACHE_DIR")
    cold = []
    for module in modules:
        spec = importlib.util.find_spec(module)
        if spec is None or spec.origin is None:
            continue
        source = Path(spec.origin)
        pattern = f"{source.stem}.*.{tag}.nbi"
        if custom:
            found = list(Path(custom).glob(f"*/{pattern}"))
        else:
            found = list((source.parent / "__pycache__").glob(pattern)) or \
                list((Path.home() / ".cache" / "numba").glob(f"*/{pattern}"))
        try:
            stamp = source.stat().st_mtime
            if not found or min(path.stat().st_mtime for path in found) < stamp:
                cold.append(module)
        except OSError:
            cold.append(module)
    return cold


def cmd_launch(args: argparse.Namespace) -> int:
    from dtpf.scripts.launch import LaunchError, launch

    config = resolved_config(args)
    if getattr(args, "ros2_params", None) and config.simulated:  # a driven twin's topics from the file
        from dtpf.scripts.ros2.preflight import with_param_topics
        config = with_param_topics(config, args.ros2_params, args.steps)
    model = sources.load_model(config)  # a wrong model or file: one line here, before any process starts
    config = settle_rehearsal(config, args, model)
    if not _claim_log(args):
        return 2
    _note_partial_truth(config, model)
    signal.signal(signal.SIGTERM, _interrupt)
    # SIGINT stops the launch even when it was started in the background of a script (a non-interactive
    # shell starts such a job with SIGINT ignored, and Python then installs no handler of its own).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    ros2_words = None
    if config.ros2_inputs:
        from dtpf.scripts.ros2 import Ros2Error, require_rclpy
        if args.twins is not None:
            raise Ros2Error("--observations ros2:TOPIC feeds one twin; for a fleet, start 'dtpf ros2 --twin NAME "
                            "--topic TOPIC' per twin with --observations live")
        require_rclpy()
        from dtpf.scripts.ros2.preflight import check_before_start
        ros2_words = check_before_start(config, args, model)  # every field path checked before anything starts
    source = f", observations from {config.observations}" if config.observations else ""
    how = "embedded Zenoh on 127.0.0.1"
    # The router's port is chosen here, so that a live run can print the sensor's --connect.
    port = args.port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    if args.secure:
        from dtpf.shell.secure import SecureError, open_secure_dir
        try:
            folder = open_secure_dir(args.secure)
        except SecureError as error:
            print(f"dtpf launch: error: {error}", file=sys.stderr)
            return 2
        how += " secured by " + ("mutual TLS" if folder.kind == "tls" else "user/password") + " and access control"
        endpoint = folder.endpoint("127.0.0.1", port)
    who = f"twin {config.twin}" if args.twins is None else \
        f"{args.twins} twins {config.twin}-1 .. {config.twin}-{args.twins}"
    print(f"dtpf: launching recorder, system, information and entity for {who} "
          f"({how}{source})", file=sys.stderr)
    if kernels_cold(config):
        print("dtpf: compiling numba kernels on first use (once per install), this can take about 30 s",
              file=sys.stderr, flush=True)
    if config.rehearses:
        rehearse_first(config, model, for_services=True)
    if config.live and args.twins is not None:
        first = sensor_command(config.model_copy(update={"twin": f"{config.twin}-1", "observations": None}),
                               endpoint, args.secure)
        print(f"dtpf: each twin filters what arrives on dtpf/{config.twin}-<i>/sensor/observation (start a "
              f"sensor per twin, e.g. {first}); Ctrl-C ends the run", file=sys.stderr)
    elif config.ros2_inputs:
        what = config.ros2_topic or ", ".join([*config.ros2_sensors.values(), *filter(None, [config.ros2_control])])
        print(f"dtpf: the entity filters each message of the ROS 2 topic{'' if config.ros2_topic else 's'} {what} "
              f"(a bridge process, dtpf ros2); its estimate goes out under /dtpf/<twin>/; Ctrl-C ends the run",
              file=sys.stderr)
    elif config.live:
        print(f"dtpf: the entity filters what arrives on {config.observation_key()}; start a sensor, e.g. in "
              f"another terminal: {sensor_command(config, endpoint, args.secure)}", file=sys.stderr)
        print("dtpf: Ctrl-C ends the run", file=sys.stderr)
    if args.twins is not None:
        if args.forecast:
            print("dtpf launch: error: --forecast publishes one twin's forecasts; it does not go with --twins",
                  file=sys.stderr)
            return 2
        return _launch_fleet(config, args, port)
    try:
        result = launch(config, log_path=args.log, port=port, timeout=args.timeout,
                        startup_timeout=args.startup_timeout, log_level=args.log_level, rate=args.rate,
                        progress=None if args.quiet else ProgressBar(),
                        observation_timeout=args.observation_timeout,
                        restarts=0 if args.no_restart else args.restarts, keep_estimates=False,
                        notify=lambda text: print(f"\ndtpf launch: {text}", file=sys.stderr, flush=True),
                        cloud_points=args.cloud_points, foxglove=args.foxglove, secure=args.secure,
                        ros2=ros2_words, forecast=args.forecast, threads=args.threads)
    except LaunchError as error:
        print(f"dtpf launch: error: {error}", file=sys.stderr)
        return 1
    return _finish(result.summary(), result.failure or _log_failure(result.log_problem), result.interrupted)


def _claim_log(args: argparse.Namespace) -> bool:
    """A log is never overwritten: -o of an existing file, or of a name whose segments (NAME.1.mcap, ...)
    exist, is one line and False; --overwrite removes them and says so."""
    if args.log is None:  # the default name is new (a date and time in it); launch() checks it all the same
        return True
    from dtpf.recording.writer import LogExistsError, claim_log
    try:
        removed = claim_log(args.log, args.overwrite)
    except LogExistsError as error:
        print(f"dtpf launch: error: {error}", file=sys.stderr)
        return False
    if removed:
        print(f"dtpf launch: --overwrite: removed {', '.join(str(path) for path in removed)}", file=sys.stderr)
    return True


def _note_partial_truth(config, model) -> None:
    """Say on stderr when the observation file's truth covers only part of the state: the estimates of a
    launch carry the whole state's truth or none, so its summary judges by the log predictive."""
    if config.observation_file is None:
        return
    from dtpf.entity.sources import read_table

    table = read_table(config, model, steps=1)
    if table.problem is not None:
        print(f"dtpf: note: {table.problem}", file=sys.stderr)
    if table.truth is not None and not table.covers(model.dim):
        covered = ", ".join(f"x[{c}]" for c in table.truth_components)
        print(f"dtpf: note: the truth of {config.observation_file} covers {covered} of the state's {model.dim} "
              f"components; a launch judges by the log predictive ('dtpf run' gives the RMSE over {covered})",
              file=sys.stderr)


def _log_failure(problem: str | None) -> str | None:
    """The launch's error when its log ended early (the run went on; the record of it did not)."""
    return f"the log is incomplete: {problem}" if problem else None


def _finish(summary: str, failure: str | None, interrupted: bool) -> int:
    """Print a launch's summary; its exit code (1 on a failure, 130 when interrupted)."""
    print(summary)
    if failure:
        print(f"dtpf launch: error: {failure}", file=sys.stderr)
        return 1
    return 130 if interrupted else 0


def _forecast_horizon(text: str) -> int:
    """``--forecast H``: 0 (none) .. the most steps a published forecast carries."""
    from dtpf.messages.models import MAX_FORECAST_HORIZON

    value = int(text) if text.strip().isdigit() else -1
    if not 0 <= value <= MAX_FORECAST_HORIZON:
        raise argparse.ArgumentTypeError(f"--forecast takes 0 .. {MAX_FORECAST_HORIZON} steps, got {text!r}")
    return value


def _launch_fleet(config, args: argparse.Namespace, port: int) -> int:
    from dtpf.scripts.fleet import launch_fleet
    from dtpf.scripts.launch import LaunchError

    try:
        result = launch_fleet(config, args.twins, log_path=args.log, port=port, timeout=args.timeout,
                              startup_timeout=args.startup_timeout, log_level=args.log_level, rate=args.rate,
                              progress=None if args.quiet else ProgressBar(), cloud_points=args.cloud_points,
                              secure=args.secure, entities=args.entities,
                              restarts=0 if args.no_restart else args.restarts,
                              observation_timeout=args.observation_timeout, threads=args.threads,
                              notify=lambda text: print(f"\ndtpf launch: {text}", file=sys.stderr, flush=True))
    except (LaunchError, ValueError) as error:
        print(f"dtpf launch: error: {error}", file=sys.stderr)
        return 1
    failure = None
    if result.competitors:
        failure = f"another entity ran {len({who.split(':')[0] for who in result.competitors})} of the fleet's twins"
    elif result.failures:
        failure = f"{len(result.failures)} twins did not end their run"
    return _finish(result.summary(), failure or _log_failure(result.log_problem), result.interrupted)


def _address(text: str):
    from dtpf.scripts.foxglove_bridge import parse_address
    return parse_address(text)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _version() -> str:
    """The installed distribution's version (``unknown`` from a source tree that was never installed)."""
    import importlib.metadata

    try:
        return importlib.metadata.version("dtpf")
    except importlib.metadata.PackageNotFoundError:
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dtpf",
        description="Digital-twin particle filter: a particle filter (entity layer) whose small-weight "
                    "particles are moved towards large-weight ones before resampling (information layer, "
                    "Eq. 28-30) with a degree PS set by degradation prediction (system layer).")
    parser.add_argument("--version", action="version", version=f"dtpf {_version()}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    run = commands.add_parser("run", help="run the three layers in one process and print a summary",
                              description="Run the three layers in one process (no transport) on a "
                                          "simulated scenario or an observation file (--observations) and "
                                          "print RMSE (or, without truth, the log predictive likelihood), "
                                          "ESS, PS and timing.")
    add_run_arguments(run, threads=True, choose_by_default=True)
    run.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    run.set_defaults(handler=cmd_run)

    launch = commands.add_parser(
        "launch", help="launch the three layer services and the recorder over an embedded Zenoh",
        description="Start the recorder, system, information and entity services as separate processes, "
                    "connected through a Zenoh router embedded in this process on a free loopback port, run "
                    "the scenario in lockstep, record every message to MCAP and print a summary. Ctrl-C stops "
                    "every service and leaves a readable log. Without --secure the router listens on loopback "
                    "only, unauthenticated: any process of this machine can read and publish on it; with "
                    "--secure DIR only the twin's own layers can steer it (docs/guides/security.md).")
    add_run_arguments(launch, threads=True, choose_by_default=True)
    group = launch.add_argument_group("launch")
    group.add_argument("--log", "-o", type=Path, default=None, metavar="PATH",
                       help="MCAP file to write, never an existing one (default: "
                            "runs/<twin>-<run-id>-<date-time>.mcap); a file of that name, or its segments "
                            "NAME.1.mcap, ..., is an error unless --overwrite")
    group.add_argument("--overwrite", action="store_true",
                       help="replace the log of -o: its file and its segments are removed first (never one a "
                            "recorder is writing)")
    group.add_argument("--port", type=int, default=None,
                       help="loopback port of the embedded Zenoh router (default: a free one)")
    group.add_argument("--timeout", type=float, default=2.0, metavar="SECONDS",
                       help="lockstep wait before a step goes on without the other layer (default: %(default)s)")
    group.add_argument("--startup-timeout", type=float, default=20.0, metavar="SECONDS",
                       help="wait at most this long for the services to come up (default: %(default)s)")
    group.add_argument("--rate", type=float, default=None, metavar="STEPS_PER_SECOND",
                       help="run the entity at most this many steps per second, like a sensor in real time "
                            "(default: as fast as possible)")
    group.add_argument("--observation-timeout", type=float, default=5.0, metavar="SECONDS",
                       help="live observations: after this long without one the entity says so in its "
                            "status and keeps waiting (default: %(default)s)")
    group.add_argument("--log-level", default="WARNING", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                       help="logging level of the services on stderr (default: %(default)s)")
    group.add_argument("--foxglove", type=_address, default=None, metavar="[HOST:]PORT",
                       help="also serve the run live to Foxglove over its WebSocket protocol (foxglove-sdk), e.g. "
                            "8765; in Foxglove: Open connection, ws://127.0.0.1:8765")
    group.add_argument("--cloud-points", type=int, default=None, metavar="K",
                       help="each step's particle set also goes out (and into the log) as a foxglove.PointCloud "
                            "on dtpf/<twin>/entity/cloud, at most K particles: every ceil(N/K)-th (0: none) "
                            "(default: 1000; with --twins, 0: a hundred twins' clouds are more than one recorder "
                            "can check and write)")
    group.add_argument("--forecast", type=_forecast_horizon, default=0, metavar="H",
                       help="the entity also publishes each step's forecast H steps ahead (mean, variance, 95%% "
                            "band) on dtpf/<twin>/entity/forecast_band, recorded, drawn by the Foxglove layout "
                            "(default: 0, none; docs/guides/ask.md)")
    group.add_argument("--secure", metavar="DIR", default=None,
                       help="a folder made by 'dtpf secure init' (DIR, DIR/tls or DIR/usrpwd): the router "
                            "listens on tls/ (or tcp/ with passwords) and enforces its access control, each "
                            "service connects with its role's certificate or password (default: plain tcp/ on "
                            "loopback, no authentication)")
    group.add_argument("--twins", type=int, default=None, metavar="K",
                       help="a fleet: K twins <twin>-1 .. <twin>-K in a few entity processes (--entities), served by one "
                            "information and one system service and recorded by one recorder into one log "
                            "(default: one twin)")
    group.add_argument("--entities", type=int, default=None, metavar="E",
                       help="with --twins: how many entity processes host the twins (default: one per CPU)")
    group.add_argument("--restarts", type=int, default=3, metavar="COUNT",
                       help="start a dead information, system or recorder service again at most this many "
                            "times each; the entity runs on meanwhile with plain resampling (its estimates say "
                            "degraded), a new recorder writes the next segment of the log (default: %(default)s)")
    group.add_argument("--no-restart", action="store_true",
                       help="never start a dead service again (the run still goes on without it)")
    group.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    from dtpf.scripts.ros2.bridge import bridge_arguments
    bridge_arguments(launch, defaults=False)
    launch.set_defaults(handler=cmd_launch)

    from dtpf.scripts import foxglove_bridge, foxglove_layout, router, secure, sensor
    from dtpf.scripts.logs import play, plot, select, summary, verify
    summary.register(commands)
    select.register(commands)
    plot.register(commands)
    play.register(commands)
    verify.register(commands)
    sensor.register(commands)
    foxglove_bridge.register(commands)
    foxglove_layout.register(commands)
    secure.register(commands)
    router.register(commands)
    from dtpf.scripts import compare
    compare.register(commands)
    from dtpf.scripts.ros2 import bridge as ros2_bridge, export as ros2_export
    ros2_export.register(commands)
    ros2_bridge.register(commands)
    from dtpf.scripts import ask, serve
    ask.register(commands)
    serve.register(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    # One BLAS thread, as every layer process has (dtpf.shell.service.run_service): OpenBLAS sums a dot
    # product of more than 10,000 numbers on several threads, in another order, so a command that re-runs a
    # layer (dtpf verify, replay, run) would otherwise differ from the layer in the last digit at large N.
    threadpool_limits(limits=1, user_api="blas")
    return run_command(parser, parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
