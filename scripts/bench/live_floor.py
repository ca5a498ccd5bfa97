"""The transport floor under a live twin's latency: the same three hops with no filter in them.

A live lockstep step is three one-way hops over Zenoh: the sensor's
observation to the entity, the entity's particle set to the information
layer, the preprocessed set back to the entity, which then stamps its
estimate. This benchmark runs those hops between processes that do nothing
else: a stand-in entity and a stand-in information layer pass payloads of
a particle set's size (16 bytes a particle: N = 1e3 is 16 KB) and the entity
stamps a small estimate with ``time.time_ns()`` as soon as the answer is in.
A recorder stand-in subscribes to everything, as ``dtpf launch``'s recorder
does, and copies each payload out. The bench process hosts the router (as
the launcher does) and plays the sensor, with the same pause between an
estimate and the next observation as ``dtpf.scripts.bench.live``.

Topologies:

- ``router``: every process is a Zenoh client of the router, as ``dtpf launch`` runs;
- ``peer``: the entity and the information stand-ins are peers linked to each
  other directly and to the router (the sensor and the recorder stay clients).

Receivers: ``callback`` (dtpf's :class:`dtpf.shell.bus.Inbox`: a Python callback
copies the payload into a queue the main thread waits on) or ``channel``
(Zenoh's own FIFO channel, ``subscriber.recv()`` in the main thread).

Whatever the filter adds comes on top of these figures: the latency of a
live twin cannot go below them. Run from the repository root::

    python -m dtpf.scripts.bench.live_floor                  # N = 1e3, 4 repetitions of each variant
    python -m dtpf.scripts.bench.live_floor --sizes 1e3 1e5 --repeats 2
"""
from __future__ import annotations

import argparse
import os
import random
import statistics
import struct
import subprocess
import sys
import time

import numpy as np
import zenoh

from dtpf.shell.bus import Inbox, free_port, open_session, publisher, zenoh_config

TOPOLOGIES = ("router", "peer")
RECEIVERS = ("callback", "channel")
_STAMP = struct.Struct("<qq")  # step, time_ns


def _receiver(session: zenoh.Session, key: str, how: str):
    """A function that waits for the next payload on ``key`` (bytes, or None after 10 s)."""
    if how == "callback":
        inbox = Inbox(session, key)

        def get():
            item = inbox.get(timeout=10)
            return None if item is None else item.payload
        return get
    subscriber = session.declare_subscriber(key, zenoh.handlers.FifoChannel(4096))

    def get():
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            sample = subscriber.try_recv()
            if sample is not None:
                return sample.payload.to_bytes()
            sample = subscriber.recv()  # blocks in Zenoh, the GIL released
            return sample.payload.to_bytes()
        return None
    return get


def _session(role: str, topology: str, router: str, entity: str) -> zenoh.Session:
    if topology == "peer" and role in ("entity", "information"):
        connect = [router] + ([entity] if role == "information" else [])
        listen = [entity] if role == "entity" else [f"tcp/127.0.0.1:{free_port()}"]
        return open_session(zenoh_config(mode="peer", connect=connect, listen=listen))
    return open_session(zenoh_config(mode="client", connect=[router]))


def _serve(role: str, topology: str, how: str, router: str, entity: str, size: int) -> int:
    """One stand-in process: entity, information or recorder, until 10 s without input."""
    session = _session(role, topology, router, entity)
    if role == "recorder":
        inbox = Inbox(session, "floor/**")
        while inbox.get(timeout=10) is not None:
            pass
        os._exit(0)
    if role == "information":
        get, out = _receiver(session, "floor/entity/particles", how), publisher(session, "floor/information/set")
        while (payload := get()) is not None:
            out.put(payload)
        os._exit(0)
    observations = _receiver(session, "floor/sensor/observation", how)
    answers = _receiver(session, "floor/information/set", how)
    particles, estimate = publisher(session, "floor/entity/particles"), publisher(session, "floor/entity/estimate")
    payload = bytes(size)
    while (observation := observations()) is not None:
        step = _STAMP.unpack_from(observation)[0]
        particles.put(payload)
        if answers() is None:
            break
        estimate.put(_STAMP.pack(step, time.time_ns()))
    os._exit(0)


def one_run(n: int, topology: str, how: str, steps: int, warm_up: int, gap: float,
            recorder: bool = True) -> np.ndarray:
    """Latencies in ms (sensor publish to estimate stamp) of steps after the warm-up."""
    port, entity_port = free_port(), free_port()
    router_endpoint, entity_endpoint = f"tcp/127.0.0.1:{port}", f"tcp/127.0.0.1:{entity_port}"
    router = open_session(zenoh_config(mode="router", listen=[router_endpoint]))
    children = []
    try:
        for role in ("recorder", "information", "entity")[0 if recorder else 1:]:
            children.append(subprocess.Popen(
                [sys.executable, "-P", "-m", "dtpf.scripts.bench.live_floor", "--serve", role, topology, how,
                 router_endpoint, entity_endpoint, str(16 * n)]))
        session = open_session(zenoh_config(mode="client", connect=[router_endpoint]))
        estimates = Inbox(session, "floor/entity/estimate")
        sensor = publisher(session, "floor/sensor/observation")
        time.sleep(3.0)  # the children subscribe and, as peers, find each other
        latencies = []
        for step in range(1, steps + 1):
            sent = time.time_ns()
            sensor.put(_STAMP.pack(step, sent) + bytes(16))
            while True:
                item = estimates.get(timeout=10)
                if item is None:
                    raise RuntimeError(f"no estimate of step {step} ({topology}, {how}, N = {n})")
                got, stamp = _STAMP.unpack(item.payload)
                if got == step:
                    break
            if step > warm_up:
                latencies.append((stamp - sent) / 1e6)
            time.sleep(gap)
        session.close()
        return np.array(latencies)
    finally:
        for child in children:
            child.kill()
            child.wait()
        router.close()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.live_floor",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["1e3"], help="particle counts N (default: 1e3)")
    parser.add_argument("--steps", type=int, default=400, help="observations per run (default: %(default)s)")
    parser.add_argument("--warm-up", type=int, default=50, help="first steps left out (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=4, help="runs per variant, interleaved (default: %(default)s)")
    parser.add_argument("--gap", type=float, default=0.005, metavar="SECONDS",
                        help="pause between an estimate and the next observation (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the run order")
    parser.add_argument("--no-recorder", dest="recorder", action="store_false",
                        help="leave the recorder stand-in out (dtpf launch always records)")
    parser.add_argument("--serve", nargs=6, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        role, topology, how, router, entity, size = args.serve
        return _serve(role, topology, how, router, entity, int(size))
    sizes = [int(float(s)) for s in args.sizes]
    variants = [(n, topology, how) for n in sizes for topology in TOPOLOGIES for how in RECEIVERS]
    order = variants * args.repeats
    random.Random(args.seed).shuffle(order)
    print(f"transport floor of a live step (3 hops, no filter), {os.cpu_count()} cores, load "
          f"{os.getloadavg()[0]:.2f}; {args.steps} observations per run ({args.warm_up} warm-up), "
          f"{args.repeats} repetitions, gap {args.gap * 1e3:g} ms, "
          f"{'with' if args.recorder else 'without'} the recorder stand-in", flush=True)
    runs: dict[tuple, list[np.ndarray]] = {v: [] for v in variants}
    for i, variant in enumerate(order, 1):
        latencies = one_run(*variant, args.steps, args.warm_up, args.gap, args.recorder)
        runs[variant].append(latencies)
        print(f"  run {i}/{len(order)}: N = {variant[0]:g} {variant[1]} {variant[2]}: "
              f"p50 {np.percentile(latencies, 50):.3f} ms", flush=True)
    print("\n| N | topology | receiver | p50 ms | p99 ms | p50 range over runs |")
    print("|---|---|---|---|---|---|")
    for variant in variants:
        p50 = [float(np.percentile(r, 50)) for r in runs[variant]]
        p99 = [float(np.percentile(r, 99)) for r in runs[variant]]
        print(f"| {variant[0]:g} | {variant[1]} | {variant[2]} | {statistics.median(p50):.3f} | "
              f"{statistics.median(p99):.3f} | {min(p50):.3f}-{max(p50):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
