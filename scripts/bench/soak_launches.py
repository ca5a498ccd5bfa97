"""Many short launches in a row: does every ``dtpf launch`` start, finish and stop cleanly?

Each launch is one call of :func:`dtpf.scripts.launch.launch` (the embedded Zenoh
router in this process; the recorder, system, information and entity services
as child processes) on a short simulated run, with its MCAP log in a temporary
directory. After each launch the script checks:

- the exit code of every child: a negative code is a child killed by a signal,
  -9 being the launcher's SIGKILL of a child that did not exit within 10 s of
  its SIGINT; any code other than 0 is a failed launch;
- the number of estimates the launcher received, which should be ``--steps``;
- the log: :func:`dtpf.recording.logfile.read_log` must read it as complete, with no
  problem and ``--steps`` estimates; the log is deleted afterwards;
- the wall time of the launch, and its shutdown time: from the arrival of the
  last estimate at the launcher to the return of ``launch()``, i.e. until every
  child has exited and the router is closed (this includes the launcher's
  0.3 s wait for the final statuses).

The children's stderr goes to a file per launch; a launch that fails prints
its last lines. Progress goes to stderr every 10 launches, the table to
stdout at the end, or on Ctrl-C with the launches done so far.

Target: no launch needs SIGKILL (or is killed by any signal), and none fails
(every exit code 0, ``--steps`` estimates, a readable log). Exit code 1 when
the target is missed, 130 after Ctrl-C otherwise.

Run from the repository root::

    python -m dtpf.scripts.bench.soak_launches                       # 200 launches, about 12 minutes on 2 cores
    python -m dtpf.scripts.bench.soak_launches --launches 5
"""
from __future__ import annotations

import argparse
import os
import platform
import signal
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from dtpf.messages import keys
from dtpf.messages.config import RunConfig
from dtpf.recording.logfile import LogError, read_log
from dtpf.scripts.launch import LAYERS, LaunchError, launch

#: Twin id of every soak launch (the run id carries the launch number).
TWIN = "soak"
#: Lines of a failed launch's child stderr shown on stderr.
STDERR_TAIL = 8
#: Progress line every this many launches.
PROGRESS_EVERY = 10


@dataclass
class LaunchOutcome:
    """What one launch did."""

    number: int
    seed: int
    wall: float
    shutdown: float | None = None  #: last estimate received -> launch() returned; None without estimates
    exit_codes: dict[str, int | None] = field(default_factory=dict)
    estimates: int = 0
    log_problem: str | None = None
    error: str | None = None  #: the LaunchError, if launch() raised one
    child_stderr: str = ""

    @property
    def killed(self) -> bool:
        """A child ended by a signal (-9: the launcher's SIGKILL after the 10 s grace)."""
        return any(code is not None and code < 0 for code in self.exit_codes.values())

    @property
    def bad_exit(self) -> bool:
        return any(code != 0 for code in self.exit_codes.values())

    def problems(self, steps: int) -> list[str]:
        """Why this launch failed, in words; empty for a clean launch."""
        found = []
        if self.error is not None:
            found.append(f"launch error: {self.error}")
        if self.bad_exit:
            found.append("exit codes " + ", ".join(f"{layer} {describe_code(code)}"
                                                     for layer, code in self.exit_codes.items() if code != 0))
        if self.estimates != steps:
            found.append(f"{self.estimates} estimates received of {steps}")
        if self.log_problem is not None:
            found.append(f"log: {self.log_problem}")
        return found


def describe_code(code: int | None) -> str:
    """-9 -> '-9 (SIGKILL)'; None -> 'none (not stopped)'."""
    if code is None:
        return "none (not stopped)"
    if code < 0:
        try:
            return f"{code} ({signal.Signals(-code).name})"
        except ValueError:
            return str(code)
    return str(code)


def check_log(path: Path, twin: str, steps: int) -> str | None:
    """None when ``path`` reads as a complete log with ``steps`` estimates; else what is wrong."""
    try:
        log = read_log(path)
    except LogError as error:
        return str(error)
    if log.problem is not None:
        return log.problem
    if not log.complete:
        return "no footer"
    topic = keys.key(twin, "entity", "estimate")
    recorded = sum(message.topic == topic for message in log.messages)
    return None if recorded == steps else f"{recorded} estimates recorded of {steps}"


def one_launch(number: int, args: argparse.Namespace, folder: Path) -> tuple[LaunchOutcome, bool]:
    """Run launch ``number``; (its outcome, whether it was interrupted by Ctrl-C)."""
    seed = args.seed + number
    config = RunConfig(particles=args.particles, steps=args.steps, seed=seed, twin=TWIN, run_id=f"soak{number}")
    log_path = folder / f"soak-{number}.mcap"
    stderr_path = folder / f"soak-{number}.stderr"
    last_estimate = None

    def on_estimate(step, total):
        nonlocal last_estimate
        last_estimate = time.perf_counter()

    start = time.perf_counter()
    outcome = LaunchOutcome(number, seed, wall=0.0)
    interrupted = False
    with open(stderr_path, "w+b") as child_stderr:
        try:
            result = launch(config, log_path=log_path, progress=on_estimate, child_output=child_stderr,
                            timeout=args.timeout)
        except LaunchError as error:
            outcome.error = str(error)
        else:
            interrupted = result.interrupted
            outcome.exit_codes = dict(result.exit_codes)
            outcome.estimates = len(result.estimates)
        end = time.perf_counter()
        child_stderr.seek(0)
        outcome.child_stderr = child_stderr.read().decode(errors="replace")
    stderr_path.unlink()
    outcome.wall = end - start
    if last_estimate is not None:
        outcome.shutdown = end - last_estimate
    if not interrupted:
        outcome.log_problem = check_log(log_path, TWIN, args.steps)
    log_path.unlink(missing_ok=True)
    return outcome, interrupted


def report(outcomes: list[LaunchOutcome], args: argparse.Namespace, elapsed: float, interrupted: bool) -> bool:
    """Print the table; True when the target is met."""
    steps = args.steps
    done = len(outcomes)
    killed = [o for o in outcomes if o.killed]
    bad_exit = [o for o in outcomes if o.bad_exit or o.error is not None]
    wrong_count = [o for o in outcomes if o.estimates != steps]
    bad_log = [o for o in outcomes if o.log_problem is not None]
    failed = [o for o in outcomes if o.problems(steps)]
    noisy = [o for o in outcomes if o.child_stderr.strip()]
    walls = [o.wall for o in outcomes]
    shutdowns = [o.shutdown for o in outcomes if o.shutdown is not None]

    def share(items) -> str:
        return f"{len(items)}" + (f" ({', '.join(f'#{o.number}' for o in items[:10])}"
                                  f"{', ...' if len(items) > 10 else ''})" if items else "")

    def spread(values) -> str:
        return f"{statistics.median(values):.2f} | {max(values):.2f}" if values else "- | -"

    print(f"\n{done} launches of {args.launches}{' (interrupted by Ctrl-C)' if interrupted else ''}: "
          f"N = {args.particles}, T = {steps}, lockstep timeout {args.timeout:g} s, seeds {args.seed}.."
          f"{args.seed + max(done, 1) - 1}; Python {platform.python_version()}, {os.cpu_count()} CPUs; "
          f"{elapsed:.0f} s in all\n")
    print("| launches | count |")
    print("|---|---|")
    print(f"| completed | {done} |")
    print(f"| a child killed by a signal (SIGKILL: exit code -9) | {share(killed)} |")
    print(f"| a child's exit code not 0, or launch() raised | {share(bad_exit)} |")
    print(f"| estimates received not {steps} | {share(wrong_count)} |")
    print(f"| log unreadable, incomplete or not {steps} estimates | {share(bad_log)} |")
    print(f"| failed (any of the above) | {share(failed)} |")
    print(f"| child stderr not empty (information only) | {share(noisy)} |")
    print("\n| seconds per launch | median | max |")
    print("|---|---|---|")
    print(f"| wall time of launch() | {spread(walls)} |")
    print(f"| shutdown: last estimate -> every child exited | {spread(shutdowns)} |")
    codes: dict[tuple[str, int | None], int] = {}
    for o in outcomes:
        for layer, code in o.exit_codes.items():
            if code != 0:
                codes[layer, code] = codes.get((layer, code), 0) + 1
    if codes:
        print("\nexit codes other than 0: " + ", ".join(
            f"{layer} {describe_code(code)} x{n}" for (layer, code), n in sorted(codes.items(), key=str)))
    errors = sorted({o.error for o in outcomes if o.error is not None})
    if errors:
        print("launch errors: " + "; ".join(errors))
    ok = not killed and not failed
    print(f"\ntarget: no launch needs SIGKILL and none fails: {'PASS' if ok else 'FAIL'}"
          + (f" (over the {done} launches done)" if interrupted else ""))
    return ok


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m dtpf.scripts.bench.soak_launches",
        description="Run many short dtpf launches (dtpf.scripts.launch.launch) one after another and count those "
                    "where a child had to be SIGKILLed, a child's exit code was not 0, the estimates received "
                    "were not --steps or the log was not readable; prints a table and the wall and shutdown "
                    "times per launch.",
        epilog="Each log is written to a temporary directory, read with dtpf.recording.logfile.read_log and deleted. "
               "Shutdown time = from the last estimate the launcher received to the return of launch() (every "
               "child exited, router closed). Ctrl-C prints the table of the launches done so far. Exit code 1 "
               "when a launch needed SIGKILL or failed.")
    parser.add_argument("--launches", type=int, default=200, help="launches in a row (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=20, help="steps T of each launch (default: %(default)s)")
    parser.add_argument("--particles", type=int, default=300, help="particles N of each launch (default: %(default)s)")
    parser.add_argument("--timeout", type=float, default=2.0, metavar="SECONDS",
                        help="lockstep timeout of the services, as dtpf launch --timeout (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the first launch; launch i uses seed + i (default: %(default)s)")
    args = parser.parse_args(argv)
    if args.launches < 1 or args.steps < 1 or args.particles < 1:
        parser.error("--launches, --steps and --particles must be at least 1")

    print(f"soak: {args.launches} launches, N = {args.particles}, T = {args.steps}; {len(LAYERS)} children each "
          f"({', '.join(LAYERS)}); load {os.getloadavg()[0]:.2f}", file=sys.stderr)
    outcomes: list[LaunchOutcome] = []
    interrupted = False
    start = time.perf_counter()
    try:
        with tempfile.TemporaryDirectory(prefix="dtpf-soak-") as folder:
            for number in range(args.launches):
                outcome, interrupted = one_launch(number, args, Path(folder))
                if interrupted:
                    break
                outcomes.append(outcome)
                problems = outcome.problems(args.steps)
                if problems:
                    print(f"launch #{number} (seed {outcome.seed}) failed: {'; '.join(problems)}", file=sys.stderr)
                    tail = outcome.child_stderr.strip().splitlines()[-STDERR_TAIL:]
                    for line in tail:
                        print(f"    {line}", file=sys.stderr)
                if len(outcomes) % PROGRESS_EVERY == 0 or len(outcomes) == args.launches:
                    failed = sum(bool(o.problems(args.steps)) for o in outcomes)
                    killed = sum(o.killed for o in outcomes)
                    print(f"launch {len(outcomes)}/{args.launches}: {killed} SIGKILLed, {failed} failed; wall "
                          f"median {statistics.median(o.wall for o in outcomes):.2f} s, last {outcome.wall:.2f} s",
                          file=sys.stderr)
    except KeyboardInterrupt:
        interrupted = True
    ok = report(outcomes, args, time.perf_counter() - start, interrupted)
    return 1 if not ok else 130 if interrupted else 0


if __name__ == "__main__":
    raise SystemExit(main())
