"""Floods on a running launch: does memory stay bounded, and is what a flood added given back?

The target: "memory is bounded under any input: queues and per-step
buffers have limits, and what a flood added is released once it stops". This
starts ``dtpf launch`` (``--rate`` steps per second), waits for step
``--flood-at``, samples the RSS of every process, then ``--floods`` times
publishes ``--payloads`` payloads of ``--size`` bytes of garbage round-robin on
every key the layers subscribe to, sampling at the end of each flood and
``--settle`` seconds after it (the services give free heap pages back a status
interval after a flood stops). Zenoh keeps buffers for large messages once it
has needed them, so the first flood of large payloads leaves some memory
behind; the target is that the floods after it add nothing: the RSS after the
last flood within 10 % (or 16 MB) of the RSS after the first. The run must
still complete with every step.

    python -m dtpf.scripts.bench.soak_flood                  # 20,000 payloads of 64 KiB
    python -m dtpf.scripts.bench.soak_flood --payloads 2000 --size 1000000
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh

from dtpf.messages.codec import MessageError, decode_for_key
from dtpf.messages.models import Estimate
from dtpf.scripts.bench.soak_memory import children_of, connect, stop, vm_rss_kb
from dtpf.shell.bus import Inbox, free_port

TWIN = "soak-flood"
#: The keys the layers subscribe to (the recorder takes them all).
FLOODED = ("entity/particles", "information/preprocessed", "information/weight_state", "system/ps",
           "entity/estimate", "system/status")


def sample(processes: dict[str, int]) -> dict[str, float]:
    return {name: (vm_rss_kb(pid) or 0) / 1024 for name, pid in processes.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.soak_flood", description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1500, help="steps of the launch (default: %(default)s)")
    parser.add_argument("--rate", type=float, default=50.0, help="steps per second (default: %(default)s)")
    parser.add_argument("--particles", type=int, default=1000, help="N (default: %(default)s)")
    parser.add_argument("--flood-at", type=int, default=200, help="step at which the flood starts (default: %(default)s)")
    parser.add_argument("--payloads", type=int, default=20_000, help="payloads in the flood (default: %(default)s)")
    parser.add_argument("--size", type=int, default=64 << 10, help="bytes per payload (default: %(default)s)")
    parser.add_argument("--floods", type=int, default=3, help="floods, one after the other (default: %(default)s)")
    parser.add_argument("--settle", type=float, default=4.0, metavar="SECONDS",
                        help="wait this long after the flood before the last sample (default: %(default)s)")
    args = parser.parse_args(argv)
    if args.steps <= args.flood_at + args.rate * args.floods * (args.settle + 10):
        parser.error("--steps must leave the run going well past the flood and the settling time")
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="dtpf-soak-flood-") as folder:
        launcher = subprocess.Popen([sys.executable, "-P", "-m", "dtpf.scripts.cli", "launch", "--steps", str(args.steps),
                                     "--rate", str(args.rate), "--particles", str(args.particles), "--twin", TWIN,
                                     "--port", str(port), "-o", str(Path(folder) / "flood.mcap"), "--quiet"],
                                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            session = connect(port, launcher)
            estimates = Inbox(session, f"dtpf/{TWIN}/entity/estimate")
            step = 0

            def follow_until(target: int) -> None:
                nonlocal step
                while step < target and launcher.poll() is None:
                    item = estimates.get(timeout=1.0)
                    if item is None:
                        continue
                    try:
                        message = decode_for_key(item.key, item.payload)
                    except MessageError:
                        continue
                    if isinstance(message, Estimate):
                        step = max(step, message.step)

            follow_until(args.flood_at)
            processes = {"launcher": launcher.pid, **children_of(launcher.pid)}
            before = sample(processes)
            publishers = [session.declare_publisher(f"dtpf/{TWIN}/{key}",
                                                    congestion_control=zenoh.CongestionControl.DROP)
                          for key in FLOODED]
            garbage = b"\xff" * args.size
            ends, afters, flood_seconds = [], [], []
            for flood in range(args.floods):
                print(f"step {step}: flood {flood + 1} of {args.floods}, {args.payloads:,} payloads of "
                      f"{args.size:,} bytes", file=sys.stderr)
                start = time.monotonic()
                for i in range(args.payloads):
                    publishers[i % len(publishers)].put(garbage)
                flood_seconds.append(time.monotonic() - start)
                ends.append(sample(processes))
                time.sleep(args.settle)
                afters.append(sample(processes))
                follow_until(step + 1)
            follow_until(args.steps)
            launcher.wait(timeout=120)
            output = launcher.stdout.read()
        finally:
            stop(launcher)
    print(f"{args.floods} floods of {args.payloads:,} x {args.size:,} bytes (each in {max(flood_seconds):.1f} s or "
          f"less) from step {args.flood_at} of {args.steps} (N = {args.particles}, {args.rate:g} steps/s); last step "
          f"seen {step}, launcher exit code {launcher.returncode}\n")
    header = ["process", "RSS before MB"] + [f"flood {i + 1}: end / +{args.settle:g} s MB" for i in range(args.floods)]
    print("| " + " | ".join(header + ["last / first flood", "bounded"]) + " |")
    print("|" + "---|" * (len(header) + 2))
    failed = launcher.returncode != 0 or step < args.steps
    for name in processes:
        first, last = afters[0][name], afters[-1][name]
        ok = last <= max(1.10 * first, first + 16)
        failed |= not ok
        cells = [f"{end[name]:.1f} / {after[name]:.1f}" for end, after in zip(ends, afters)]
        print(f"| {name} | {before[name]:.1f} | " + " | ".join(cells) +
              f" | {last / max(first, 1e-9):.3f} | {'PASS' if ok else 'FAIL'} |")
    rejected = next((line for line in output.splitlines() if line.startswith("rejected")), "rejected        ?")
    print(f"\n{rejected}")
    print(f"target: after the last flood every process within 10% (or 16 MB) of its RSS after the first, the run "
          f"complete: {'FAIL' if failed else 'PASS'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
