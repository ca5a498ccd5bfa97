"""Does a storm of questions slow a twin? Its step time unqueried and asked its state 100 times a second.

Each run is one ``dtpf launch --observations live`` (the embedded router, the recorder, system,
information and entity services, lockstep with DT preprocessing), this process its sensor at a fixed
rate (``--rate`` observations a second, each sent once the estimate of the one before is out). A step's
time is its estimate's ``stamp`` minus its observation's ``stamp`` (wall clocks of the same machine, taken
just before each is published): the lockstep step as the sensor sees it. In a *queried* run a child
process of this script (its own interpreter, so that asking takes nothing from the sensor's) asks the
entity ``dtpf/<twin>/entity/state`` ``--qps`` times a second from the first observation to the last, and
counts the answers, the error replies (by their first words) and the largest answer. Runs of the two modes
alternate (unqueried, queried, unqueried, ...); the first ``--warm-up`` steps of each are left out.

The table: per mode, the median over runs of each run's median step time, its p90, the runs' range; the
ratio queried / unqueried of the medians (and of each pair of runs, their range); the questions asked,
answered and replied with an error::

    python -m dtpf.scripts.bench.query_storm                 # N = 1000, 20 steps/s, 200 steps, 3 runs a mode
    python -m dtpf.scripts.bench.query_storm --steps 100 --repeats 2
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from dtpf.entity import sources
from dtpf.messages import keys, queries
from dtpf.messages.codec import decode_for_key, encode
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Observation, ServiceState, Status
from dtpf.scripts.bench.live import step_latency
from dtpf.shell.bus import BusError, Inbox, free_port, open_session, publisher, zenoh_config

MODES = ("unqueried", "queried")


def _client(endpoint: str, deadline: float, alive=lambda: True):
    while True:
        try:
            return open_session(zenoh_config(mode="client", connect=[endpoint],
                                             cfg=["connect/timeout_ms:1000", "connect/exit_on_failure:true"]))
        except BusError:
            if time.monotonic() > deadline or not alive():
                raise RuntimeError(f"nothing listens on {endpoint}")
            time.sleep(0.2)


def asker(endpoint: str, twin: str, qps: float) -> int:
    """The child of a queried run: ask the twin's state ``qps`` times a second until SIGTERM, then print
    the counts as one JSON line."""
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    session = _client(endpoint, time.monotonic() + 60)
    key = queries.key(twin, "state")
    asked, answered, largest, reasons = 0, 0, 0, Counter()
    period, tick = 1.0 / qps, time.monotonic()
    print("ready", flush=True)
    while not stop:
        asked += 1
        for reply in session.get(key, timeout=5.0):
            if reply.ok is not None:
                answered += 1
                largest = max(largest, len(reply.ok.payload.to_bytes()))
            else:
                text = reply.err.payload.to_bytes().decode("utf-8", "replace")
                reasons[text.split(":")[0]] += 1
        tick += period
        time.sleep(max(0.0, tick - time.monotonic()))
    session.close()
    print(json.dumps({"asked": asked, "answered": answered, "largest": largest, "errors": dict(reasons)}),
          flush=True)
    return 0


def one_run(mode: str, n: int, steps: int, rate: float, qps: float, warm_up: int, seed: int,
            log_dir: Path) -> tuple[np.ndarray, dict | None]:
    """Step times in ms of steps warm_up+1 .. steps of one live launch, and the asker's counts."""
    twin = "bench-storm"
    config = RunConfig(particles=n, steps=steps, seed=seed, twin=twin)
    data = sources.observations_of(config, sources.load_model(config))
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    launcher = subprocess.Popen(
        [sys.executable, "-P", "-m", "dtpf.scripts.cli", "launch", "--observations", "live", "--particles", str(n),
         "--seed", str(seed), "--twin", twin, "--port", str(port), "--quiet", "-o",
         str(log_dir / f"{mode}-{time.monotonic_ns()}.mcap")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    session, child = None, None
    try:
        session = _client(endpoint, time.monotonic() + 60, lambda: launcher.poll() is None)
        estimates = Inbox(session, keys.key(twin, "entity", "estimate"), keys.key(twin, "entity", "status"))
        out = publisher(session, keys.key(twin, "sensor", "observation"))
        while True:  # until the entity is running (it has subscribed to the sensor key)
            item = estimates.get(timeout=60)
            if item is None:
                raise RuntimeError("the entity never said it was running")
            message = decode_for_key(item.key, item.payload)
            if isinstance(message, Status) and message.state == ServiceState.RUNNING:
                break
        if mode == "queried":
            child = subprocess.Popen([sys.executable, "-P", "-m", "dtpf.scripts.bench.query_storm", "--asker",
                                      endpoint, twin, "--qps", repr(qps)], stdout=subprocess.PIPE, text=True)
            if child.stdout.readline().strip() != "ready":
                raise RuntimeError("the asker did not start")
        times, tick = [], time.monotonic()
        for k in range(1, steps + 1):
            latency = step_latency(out, estimates, twin, k, data.observations[k - 1])
            if k > warm_up:
                times.append(latency)
            tick += 1.0 / rate
            time.sleep(max(0.0, tick - time.monotonic()))
        counts = None
        if child is not None:
            child.send_signal(signal.SIGTERM)
            counts = json.loads(child.communicate(timeout=30)[0].strip().splitlines()[-1])
            child = None
        out.put(encode(Observation(run_id="run", twin_id=twin, step=steps + 1, values=[], end=True)))
        launcher.wait(timeout=60)
        return np.array(times), counts
    finally:
        if child is not None and child.poll() is None:
            child.kill()
            child.wait()
        if session is not None:
            session.close()
        if launcher.poll() is None:
            os.killpg(launcher.pid, signal.SIGINT)
            try:
                launcher.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(launcher.pid, signal.SIGKILL)
                launcher.wait()


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["--asker"]:
        child = argparse.ArgumentParser(prog="query_storm --asker")
        child.add_argument("endpoint")
        child.add_argument("twin")
        child.add_argument("--qps", type=float, default=100.0)
        ask = child.parse_args(argv[1:])
        return asker(ask.endpoint, ask.twin, ask.qps)
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.query_storm", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--particles", type=int, default=1000, help="N (default: %(default)s)")
    parser.add_argument("--rate", type=float, default=20.0, help="observations a second (default: %(default)s)")
    parser.add_argument("--qps", type=float, default=100.0, help="state questions a second (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=200, help="observations a run (default: %(default)s)")
    parser.add_argument("--warm-up", type=int, default=20, help="first steps left out (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=3, help="runs a mode, alternating (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.steps <= args.warm_up or args.repeats < 1 or args.rate <= 0 or args.qps <= 0 or args.particles < 1:
        parser.error("need --steps > --warm-up, --repeats >= 1, --rate, --qps and --particles > 0")
    load = os.getloadavg()[0]
    print(f"query storm: N = {args.particles}, {args.rate:g} steps/s, {args.steps} steps a run ({args.warm_up} "
          f"warm-up), {args.repeats} runs a mode, alternating; queried: {args.qps:g} state questions/s; "
          f"{os.cpu_count()} cores, 1-min load {load:.2f} before", flush=True)
    runs = {mode: [] for mode in MODES}
    counts = []
    start = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeats):
            for mode in MODES:
                times, asked = one_run(mode, args.particles, args.steps, args.rate, args.qps, args.warm_up,
                                       args.seed, Path(tmp))
                runs[mode].append(times)
                if asked is not None:
                    counts.append(asked)
                print(f"  run {i + 1}/{args.repeats} {mode}: median {np.median(times):.3f} ms, p90 "
                      f"{np.percentile(times, 90):.3f} ms" + (f"; {asked}" if asked else ""), flush=True)
    medians = {mode: [float(np.median(r)) for r in runs[mode]] for mode in MODES}
    p90 = {mode: [float(np.percentile(r, 90)) for r in runs[mode]] for mode in MODES}
    print(f"\n{time.monotonic() - start:.0f} s\n")
    print("| mode | median step ms | p90 ms | run medians ms |")
    print("|---|---|---|---|")
    for mode in MODES:
        print(f"| {mode} | {statistics.median(medians[mode]):.3f} | {statistics.median(p90[mode]):.3f} | "
              f"{min(medians[mode]):.3f}-{max(medians[mode]):.3f} |")
    ratios = [q / u for q, u in zip(medians["queried"], medians["unqueried"])]
    print(f"| queried / unqueried | {statistics.median(medians['queried']) / statistics.median(medians['unqueried']):.2f}"
          f" | {statistics.median(p90['queried']) / statistics.median(p90['unqueried']):.2f} | pairs "
          f"{min(ratios):.2f}-{max(ratios):.2f} |")
    asked = sum(c["asked"] for c in counts)
    refused = Counter()
    for c in counts:
        refused.update(c["errors"])
    print(f"\nquestions: {asked} asked, {sum(c['answered'] for c in counts)} answered, error replies "
          f"{dict(refused) or 0}; largest answer {max((c['largest'] for c in counts), default=0)} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
