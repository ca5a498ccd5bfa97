"""CPU a process spends to receive one message: dtpf's callback inbox against Zenoh's FIFO channel.

Three processes on loopback: a Zenoh router; a publisher that puts payloads of ``--size`` bytes,
``--gap`` seconds apart (congestion control BLOCK, as the services publish); and this process, a client
of the router that receives them in one of two ways:

- ``callback``: :class:`dtpf.shell.bus.Inbox`, what every dtpf service and the recorder use: Zenoh calls a
  Python callback on its own thread, which copies the payload into a bounded queue the main thread waits on;
- ``channel``: Zenoh's ``FifoChannel`` read by the main thread (``subscriber.recv()``), the payload copied
  there: no Python on Zenoh's thread, no hand-over between threads.

Each run counts this process's CPU time (``time.process_time``: every thread, Zenoh's included) from the
50th message to the last, per message. Runs alternate the receivers; the table gives medians over runs.
Run from the repository root::

    python -m dtpf.scripts.bench.inbox                        # 16 kB (a set at N = 1e3), 1 ms apart
    python -m dtpf.scripts.bench.inbox --size 200 --repeats 6
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from importlib.metadata import version

import zenoh

from dtpf.shell.bus import Inbox, free_port, open_session, publisher, zenoh_config

KEY = "dtpf/bench-inbox/entity/particles"
END = b"END"
#: Messages left out at the start of a run (discovery, first allocations).
WARM_UP = 50


def _client(port: int) -> zenoh.Session:
    return open_session(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))


def _router(port: int) -> None:
    session = open_session(zenoh_config(mode="router", listen=[f"tcp/127.0.0.1:{port}"]))
    try:
        time.sleep(3600)
    finally:
        session.close()


def _publish(port: int, count: int, size: int, gap: float) -> None:
    session = _client(port)
    pub = publisher(session, KEY)
    time.sleep(1.0)  # the receiver's subscription reaches the router
    payload = os.urandom(size)
    for _ in range(count):
        pub.put(payload)
        time.sleep(gap)
    pub.put(END)
    time.sleep(0.5)
    session.close()


def receive(port: int, kind: str, count: int, size: int, gap: float) -> float:
    """CPU seconds per message of this process, receiving ``count`` payloads with ``kind``."""
    session = _client(port)
    if kind == "callback":
        inbox = Inbox(session, KEY)

        def take() -> bytes | None:
            item = inbox.get(timeout=1.0)
            return None if item is None else item.payload
    else:
        subscriber = session.declare_subscriber(KEY, zenoh.handlers.FifoChannel(1024))

        def take() -> bytes | None:
            return subscriber.recv().payload.to_bytes()
    sender = subprocess.Popen([sys.executable, "-P", "-m", "dtpf.scripts.bench.inbox", "--publish", str(port),
                               "--count", str(count), "--size", str(size), "--gap", str(gap)])

    def end_if_the_sender_died() -> None:  # a channel's recv() has no timeout: it must not wait for ever
        sender.wait()
        time.sleep(2.0)
        try:
            session.put(KEY, END)
        except zenoh.ZError:  # the run ended and closed its session
            pass
    threading.Thread(target=end_if_the_sender_died, daemon=True).start()
    got, start = 0, None
    deadline = time.monotonic() + 60 + count * gap * 3
    try:
        while time.monotonic() < deadline:
            payload = take()
            if payload is None:
                continue
            if payload == END:
                break
            got += 1
            if got == WARM_UP:
                start = time.process_time()
        else:
            raise SystemExit(f"{kind}: {got} of {count} messages within the deadline")
        cpu = time.process_time() - start
    finally:
        sender.wait(timeout=30)
        session.close()
    if got != count:
        raise SystemExit(f"{kind}: received {got} of {count} messages")
    return cpu / (got - WARM_UP)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.inbox", description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=16_000, help="payload bytes (default: %(default)s)")
    parser.add_argument("--gap", type=float, default=0.001, help="seconds between messages (default: %(default)s)")
    parser.add_argument("--count", type=int, default=600, help="messages per run (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=4, help="runs of each receiver (default: %(default)s)")
    parser.add_argument("--publish", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--router", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.router is not None:
        _router(args.router)
        return 0
    if args.publish is not None:
        _publish(args.publish, args.count, args.size, args.gap)
        return 0
    if args.count <= WARM_UP:
        parser.error(f"--count must be above the {WARM_UP} warm-up messages")
    port = free_port()
    router = subprocess.Popen([sys.executable, "-P", "-m", "dtpf.scripts.bench.inbox", "--router", str(port)])
    kinds = ["callback", "channel"]
    per_message: dict[str, list[float]] = {kind: [] for kind in kinds}
    began = time.monotonic()
    load = os.getloadavg()[0]
    try:
        time.sleep(1.0)
        for repeat in range(args.repeats):
            for kind in kinds if repeat % 2 == 0 else kinds[::-1]:
                per_message[kind].append(receive(port, kind, args.count, args.size, args.gap))
                print(f"  run {repeat + 1}/{args.repeats} {kind}: {per_message[kind][-1] * 1e6:.1f} us CPU a message",
                      file=sys.stderr, flush=True)
    finally:
        router.terminate()
        router.wait(timeout=30)
    print(f"`python -m dtpf.scripts.bench.inbox --size {args.size} --gap {args.gap} --count {args.count} --repeats "
          f"{args.repeats}`: Python {platform.python_version()}, eclipse-zenoh {version('eclipse-zenoh')}, "
          f"{os.cpu_count()} CPUs, 1-min load {load:.2f} before, {time.monotonic() - began:.0f} s\n")
    print("| receiver | CPU us per message (median) | range over runs | ratio to channel |")
    print("|---|---|---|---|")
    floor = statistics.median(per_message["channel"])
    for kind in kinds:
        values = per_message[kind]
        median = statistics.median(values)
        print(f"| {kind} | {median * 1e6:.1f} | {min(values) * 1e6:.1f}-{max(values) * 1e6:.1f} | {median / floor:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
