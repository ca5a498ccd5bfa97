"""Memory of a long ``dtpf launch``: does any process grow while the run goes on?

One ``dtpf launch`` (``python -m dtpf.scripts.cli launch --steps S --particles N
--quiet``, its log in a temporary directory) runs as a subprocess on a port
chosen here. This process connects to the launcher's embedded router as a
Zenoh client and follows ``dtpf/<twin>/entity/estimate`` to know the step (the
launcher's progress bar is redrawn only every 2 % of T, too coarse for fixed
steps). At step 1,000, at every ``--sample-every`` steps and at the last step
it reads VmRSS from ``/proc/<pid>/status`` of the launcher and of each of its
children, found in ``/proc`` as the processes whose parent is the launcher
and told apart by the module in their command line (dtpf.scripts.record,
dtpf.system.service, dtpf.information.service, dtpf.entity.service).

The step of a sample is the step of the estimate just taken from the queue;
if this process falls behind, the services are already further on (the
largest backlog is printed). The growth per 1,000 steps is the least-squares
slope of RSS over the samples from step 1,000 on.

Target: the RSS of every process at the end of the run is within 10 % of its
value at step 1,000. Exit code 1 when a process misses it or the run does not
complete.

Run from the repository root::

    python -m dtpf.scripts.bench.soak_memory                          # T = 20,000 at N = 1,000
    python -m dtpf.scripts.bench.soak_memory --steps 3000 --sample-every 250
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from dtpf.messages import keys
from dtpf.messages.codec import MessageError, decode_for_key
from dtpf.messages.models import Estimate
from dtpf.shell.bus import BusError, Inbox, free_port, open_session, zenoh_config

#: The step whose RSS is the reference, and the largest change of RSS allowed after it.
REFERENCE_STEP = 1_000
TOLERANCE = 0.10
#: The launch must go on for a while after the reference step.
MIN_STEPS = 2 * REFERENCE_STEP
#: Twin id of the soak run.
TWIN = "soak-memory"
#: Child processes of the launcher by the module in their command line, in start order.
CHILD_MODULES = {"recorder": "dtpf.scripts.record", "system": "dtpf.system.service",
                 "information": "dtpf.information.service", "entity": "dtpf.entity.service"}
PROCESSES = ("launcher", *CHILD_MODULES)
#: Give up when no estimate arrives for this long.
STALL_SECONDS = 120.0


@dataclass
class RssSeries:
    """The RSS samples of one process."""

    name: str
    pid: int | None = None
    steps: list[int] = field(default_factory=list)
    rss_kb: list[int] = field(default_factory=list)

    def at(self, step: int) -> int | None:
        """RSS (kB) of the first sample at or after ``step``."""
        for k, rss in zip(self.steps, self.rss_kb):
            if k >= step:
                return rss
        return None

    def step_of(self, step: int) -> int | None:
        return next((k for k in self.steps if k >= step), None)

    def slope_per_1000_steps(self, first: int) -> float | None:
        """Least-squares growth of RSS in kB per 1,000 steps over the samples from ``first`` on."""
        points = [(k, rss) for k, rss in zip(self.steps, self.rss_kb) if k >= first]
        if len(points) < 2:
            return None
        k, rss = np.array(points, dtype=float).T
        return 1000.0 * float(np.polyfit(k, rss, 1)[0])


def vm_rss_kb(pid: int) -> int | None:
    """VmRSS of ``pid`` in kB; None when the process is gone."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return None
    return None  # a zombie has no VmRSS


def children_of(parent: int) -> dict[str, int]:
    """The launcher's children by layer name, from /proc (ppid and the module in the command line)."""
    found = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as stat:
                # pid (comm) state ppid ...: comm may hold spaces, so split after its closing parenthesis
                ppid = int(stat.read().rpartition(")")[2].split()[1])
            if ppid != parent:
                continue
            with open(f"/proc/{entry}/cmdline", "rb") as cmdline:
                arguments = cmdline.read().split(b"\0")
        except (FileNotFoundError, ProcessLookupError, PermissionError, IndexError, ValueError):
            continue
        for layer, module in CHILD_MODULES.items():
            if module.encode() in arguments:
                found[layer] = int(entry)
    return found


def connect(port: int, launcher: subprocess.Popen) -> zenoh.Session:
    """A Zenoh client session on the launcher's router, retried while the router comes up."""
    deadline = time.monotonic() + 60
    while True:
        try:
            return open_session(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"],
                                             cfg=["connect/timeout_ms:1000", "connect/exit_on_failure:true"]))
        except BusError:
            if time.monotonic() > deadline or launcher.poll() is not None:
                raise RuntimeError(f"the launcher's router on port {port} did not come up") from None
            time.sleep(0.2)


def stop(launcher: subprocess.Popen) -> None:
    """SIGTERM to the launcher (dtpf launch stops its children and finishes the log), SIGKILL after 30 s."""
    if launcher.poll() is not None:
        return
    launcher.send_signal(signal.SIGTERM)
    try:
        launcher.wait(timeout=30)
    except subprocess.TimeoutExpired:
        launcher.kill()
        launcher.wait()


def follow(launcher: subprocess.Popen, port: int, args: argparse.Namespace,
           series: dict[str, RssSeries]) -> tuple[int, int]:
    """Sample RSS while the run goes on; (last step seen, largest backlog of estimates when sampling)."""
    session = connect(port, launcher)
    try:
        estimates = Inbox(session, keys.key(TWIN, "entity", "estimate"))
        last_step, backlog, last_arrival = 0, 0, time.monotonic()
        series["launcher"].pid = launcher.pid
        while True:
            item = estimates.get(timeout=0.5)
            if item is None:
                if launcher.poll() is not None:
                    return last_step, backlog
                if time.monotonic() - last_arrival > STALL_SECONDS:
                    raise RuntimeError(f"no estimate for {STALL_SECONDS:.0f} s after step {last_step}")
                continue
            last_arrival = time.monotonic()
            try:
                message = decode_for_key(item.key, item.payload)
            except MessageError:
                continue
            if not isinstance(message, Estimate):
                continue
            step = last_step = message.step
            if step != REFERENCE_STEP and step % args.sample_every and step != args.steps:
                continue
            backlog = max(backlog, len(estimates))
            missing = [layer for layer in CHILD_MODULES if series[layer].pid is None]
            if missing:
                for layer, pid in children_of(launcher.pid).items():
                    series[layer].pid = pid
            for name in PROCESSES:
                pid = series[name].pid
                rss = vm_rss_kb(pid) if pid is not None else None
                if rss is not None:
                    series[name].steps.append(step)
                    series[name].rss_kb.append(rss)
            print(f"step {step}/{args.steps}: " + ", ".join(
                f"{name} {series[name].rss_kb[-1] / 1024:.1f} MB" for name in PROCESSES
                if series[name].steps and series[name].steps[-1] == step), file=sys.stderr)
    finally:
        session.close()


def report(series: dict[str, RssSeries], args: argparse.Namespace, last_step: int, backlog: int,
           launcher_code: int | None, elapsed: float) -> bool:
    """Print the table; True when every process meets the target."""
    print(f"\ndtpf launch --steps {args.steps} --particles {args.particles}: last step seen {last_step}, launcher "
          f"exit code {launcher_code}, {elapsed:.0f} s; RSS sampled every {args.sample_every} steps (largest "
          f"backlog of estimates when sampling: {backlog}); {os.cpu_count()} CPUs\n")
    print(f"| process | pid | RSS at step {REFERENCE_STEP:,} MB | RSS at end MB (step) | end / step {REFERENCE_STEP:,} "
          f"| growth per 1,000 steps MB | max RSS MB | within {TOLERANCE:.0%} |")
    print("|---|---|---|---|---|---|---|---|")
    ok = True
    for name in PROCESSES:
        s = series[name]
        reference = s.at(REFERENCE_STEP)
        if reference is None or len(s.steps) < 2 or s.steps[-1] <= s.step_of(REFERENCE_STEP):
            ok = False
            print(f"| {name} | {s.pid or '-'} | {'-' if reference is None else f'{reference / 1024:.1f}'} | - | - "
                  f"| - | - | FAIL (no samples after step {REFERENCE_STEP:,}) |")
            continue
        end = s.rss_kb[-1]
        ratio = end / reference
        passed = abs(ratio - 1.0) <= TOLERANCE
        ok &= passed
        slope = s.slope_per_1000_steps(REFERENCE_STEP)
        print(f"| {name} | {s.pid} | {reference / 1024:.1f} | {end / 1024:.1f} ({s.steps[-1]}) | {ratio:.3f} | "
              f"{'-' if slope is None else f'{slope / 1024:+.2f}'} | {max(s.rss_kb) / 1024:.1f} | "
              f"{'PASS' if passed else 'FAIL'} |")
    complete = last_step == args.steps and launcher_code == 0
    if not complete:
        print(f"\nthe run did not complete (last step {last_step} of {args.steps}, launcher exit code "
              f"{launcher_code}): the figures cover only part of it")
    print(f"\ntarget: every process's RSS at the end within {TOLERANCE:.0%} of its RSS at step {REFERENCE_STEP:,}: "
          f"{'PASS' if ok and complete else 'FAIL'}")
    return ok and complete


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m dtpf.scripts.bench.soak_memory",
        description="Run one long dtpf launch and sample the resident memory (VmRSS) of the launcher and of its "
                    "recorder, system, information and entity processes as the run goes on; prints a table and "
                    f"PASS/FAIL against 'RSS at the end within {TOLERANCE:.0%} of RSS at step {REFERENCE_STEP:,}'.",
        epilog="The step is taken from the entity's estimates, which this process receives as a Zenoh client of "
               "the launcher's router (loopback, a free port). The log goes to a temporary directory and is "
               "deleted. Exit code 1 when a process misses the target or the run does not complete.")
    parser.add_argument("--steps", type=int, default=20_000, help=f"steps T of the launch, at least {MIN_STEPS:,} "
                                                                    "(default: %(default)s)")
    parser.add_argument("--particles", type=int, default=1_000, help="particles N (default: %(default)s)")
    parser.add_argument("--sample-every", type=int, default=500, metavar="STEPS",
                        help=f"sample RSS every this many steps, besides step {REFERENCE_STEP:,} and the last "
                             "(default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the run (default: %(default)s)")
    args = parser.parse_args(argv)
    if args.steps < MIN_STEPS:
        parser.error(f"--steps must be at least {MIN_STEPS:,}: RSS is compared with its value at step "
                     f"{REFERENCE_STEP:,}")
    if args.sample_every < 1 or args.particles < 1:
        parser.error("--sample-every and --particles must be at least 1")

    series = {name: RssSeries(name) for name in PROCESSES}
    port = free_port()
    start = time.monotonic()
    last_step, backlog, failure = 0, 0, None
    with tempfile.TemporaryDirectory(prefix="dtpf-soak-memory-") as folder:
        folder = Path(folder)
        command = [sys.executable, "-P", "-m", "dtpf.scripts.cli", "launch", "--steps", str(args.steps),
                   "--particles", str(args.particles), "--seed", str(args.seed), "--twin", TWIN,
                   "--port", str(port), "-o", str(folder / "soak-memory.mcap"), "--quiet"]
        print(f"soak-memory: {' '.join(command[1:])}", file=sys.stderr)
        with open(folder / "launcher.out", "w+") as out, open(folder / "launcher.err", "w+") as err:
            launcher = subprocess.Popen(command, stdout=out, stderr=err, start_new_session=True)
            try:
                last_step, backlog = follow(launcher, port, args, series)
                launcher.wait(timeout=60)
            except KeyboardInterrupt:
                failure = "interrupted by Ctrl-C"
            except (RuntimeError, subprocess.TimeoutExpired) as error:
                failure = str(error)
            finally:
                stop(launcher)
            out.seek(0)
            err.seek(0)
            summary, errors = out.read().strip(), err.read().strip()
    if failure:
        print(f"soak-memory: {failure}", file=sys.stderr)
    if launcher.returncode != 0 and errors:
        print("launcher stderr (last lines):\n    " + "\n    ".join(errors.splitlines()[-10:]), file=sys.stderr)
    if summary:
        print("launcher summary:\n    " + "\n    ".join(summary.splitlines()), file=sys.stderr)
    ok = report(series, args, last_step, backlog, launcher.returncode, time.monotonic() - start)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
