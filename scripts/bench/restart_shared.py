"""How long a fleet's twins stay degraded when a shared service dies and is started again.

Starts a router, a recorder, the shared information and system services (``--twins 'b-*'``) and
``--entities`` entity processes hosting ``--twins`` paced twins, SIGKILLs the shared information (or
system) service once twin b-1's estimates reach ``--kill-at``, starts it again at once, and reads the log:
for each twin, the steps it ran degraded (plain resampling, no answer of the shared layer) from the kill
on, and when the last of them was made::

    python3 scripts/bench/restart_shared.py --twins 20 --rate 50 --steps 600 --kill-at 100
    python3 scripts/bench/restart_shared.py ... --entity-cache 0   # entities without a cache: no history

With ``--entity-cache 0`` the entities' status publishers keep nothing, so the new service learns each
twin from its next status (every 5 s once it runs) instead of asking for its last one.
"""
from __future__ import annotations

import argparse
import datetime as dt
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dtpf.messages.codec import decode_for_key
from dtpf.recording.logfile import read_logs
from dtpf.shell.bus import Inbox, free_port, open_session, zenoh_config

_ASKED = re.compile(r"^(\S+ \S+) \S+\s+INFO serving the twins under")


def _start(folder: Path, name: str, *args: str) -> subprocess.Popen:
    out = open(folder / f"{name}.log", "wb")
    process = subprocess.Popen([sys.executable, "-m", *args], stdout=out, stderr=subprocess.STDOUT,
                               start_new_session=True)
    process.log_path = out.name
    return process


def _asked_at(path: str) -> float | None:
    """The wall-clock time a fleet service said it asked for its twins (its log line), or None."""
    for line in Path(path).read_text(errors="replace").splitlines():
        found = _ASKED.match(line)
        if found:
            return dt.datetime.strptime(found.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
    return None


def run(twins: int, entities: int, rate: float, steps: int, kill_at: int, layer: str, entity_cache: int | None,
        folder: Path) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    connect = ("--connect", endpoint)
    names = [f"b-{i}" for i in range(1, twins + 1)]
    groups = [names[i::entities] for i in range(entities)]
    processes = []
    cache = ("--cache-samples", str(entity_cache)) if entity_cache is not None else ()
    try:
        processes.append(_start(folder, "router", "dtpf", "router", "--listen", endpoint))
        time.sleep(1.0)
        processes.append(_start(folder, "recorder", "dtpf.scripts.record", *connect, "--all-twins",
                                "-o", str(folder / "fleet.mcap")))
        shared = {name: _start(folder, f"{name}-1", f"dtpf.{name}.service", *connect, "--twins", "b-*")
                  for name in ("information", "system")}
        processes += shared.values()
        time.sleep(2.0)
        entity = [_start(folder, f"entity-{i}", "dtpf.entity.service", *connect, "--twins", ",".join(group),
                         "--steps", str(steps), "--rate", str(rate), "--wait-for", "information", "--wait-for",
                         "system", *cache) for i, group in enumerate(groups)]
        processes += entity
        killed_at = started = None
        with open_session(zenoh_config(mode="peer", connect=[endpoint])) as session:
            inbox = Inbox(session, "dtpf/b-1/entity/estimate")
            deadline = time.monotonic() + 300
            while killed_at is None and time.monotonic() < deadline:
                item = inbox.get(timeout=0.5)
                if item is not None and decode_for_key(item.key, item.payload).step >= kill_at:
                    os.kill(shared[layer].pid, signal.SIGKILL)
                    killed_at = decode_for_key(item.key, item.payload).step
                    started = time.time()
                    shared[layer] = _start(folder, f"{layer}-2", f"dtpf.{layer}.service", *connect, "--twins", "b-*")
                    processes.append(shared[layer])
            inbox.close()
        for process in entity:
            process.wait(timeout=600)
        for process in reversed(processes):
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGINT)
                process.wait(timeout=30)
    finally:
        for process in processes:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
    log = read_logs([folder / "fleet.mcap"])
    stamps, steps, degraded = {}, {}, {}
    for _, message in log.decoded(lambda topic: topic.endswith("/entity/estimate")):
        steps.setdefault(message.twin_id, set()).add(message.step)
        if getattr(message, "degraded", False):
            stamps[message.twin_id, message.step] = message.stamp.sec + message.stamp.nsec / 1e9
            degraded.setdefault(message.twin_id, set()).add(message.step)
    asked = _asked_at(shared[layer].log_path)
    per_twin = {}
    for twin in sorted(steps):
        if twin not in names:
            continue
        after = sorted(s for s in degraded.get(twin, ()) if s >= killed_at)
        end = stamps.get((twin, after[-1])) if after else None
        per_twin[twin] = dict(degraded=len(after), last=after[-1] if after else None, steps=len(steps[twin]),
                                after_start=None if end is None else end - started,
                                after_asked=None if end is None or asked is None else end - asked)
    return {"killed_at": killed_at, "up": None if asked is None else asked - started, "twins": per_twin}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--twins", type=int, default=20)
    parser.add_argument("--entities", type=int, default=2)
    parser.add_argument("--rate", type=float, default=50.0)
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--kill-at", type=int, default=100)
    parser.add_argument("--layer", choices=["information", "system"], default="information")
    parser.add_argument("--entity-cache", type=int, default=None, metavar="N",
                        help="the entities' --cache-samples (default: theirs; 0: no cache, no history)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        result = run(args.twins, args.entities, args.rate, args.steps, args.kill_at, args.layer, args.entity_cache,
                     Path(folder))
    twins = result["twins"]
    print(f"{args.layer} SIGKILLed at step {result['killed_at']} of twin b-1 and started again at once "
          f"({args.twins} twins in {args.entities} entity processes, {args.rate:g} steps/s); the new service asked "
          f"for its twins {result['up']:.2f} s after it started (its start-up)")
    for twin in sorted(twins, key=lambda name: int(name.split("-")[1])):
        t = twins[twin]
        print(f"  {twin:<6} {t['degraded']:>4} degraded steps from the kill on"
              + (f", the last (step {t['last']}) {t['after_start']:.2f} s after the restart, "
                 f"{t['after_asked']:.2f} s after the service asked" if t["last"] is not None else ""))
    counts = [t["degraded"] for t in twins.values()]
    ends = [t["after_asked"] for t in twins.values() if t["after_asked"] is not None]
    print(f"degraded steps per twin from the kill on: min {min(counts)}, median {statistics.median(counts):g}, "
          f"max {max(counts)}")
    if ends:
        print(f"the twins' last degraded steps came {min(ends):.2f} .. {max(ends):.2f} s after the new service asked")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
