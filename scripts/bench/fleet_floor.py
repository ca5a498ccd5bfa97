"""The transport floor under a fleet's throughput: a fleet's messages with no filter and no decoding in them.

One twin-step of ``dtpf launch --twins K`` is five messages through the
launcher's router: the entity's particle set (to the information layer and
the recorder), the preprocessed set (to the entity and the recorder), the
weight state (to the system layer and the recorder), the PS command (to the
information layer and the recorder) and the estimate (to the recorder and the
launcher's progress), besides about 0.76 statuses per twin-step at K = 100.
This benchmark sends the same messages, of the sizes a real fleet's log holds
at N = 1e3 (``--scale`` for others; :func:`plan_of_launch` reads them from a
short launch's log instead), between stand-in processes that do nothing else:
no filter, no rules, no pydantic, no MCAP writing. The hops are the lockstep's:
the entity stand-in sends step k + 1's set once step k's answer is in, the
information stand-in answers step k once the PS of step k - 1 is in (as the
information layer waits for it; under the fixed policy, the default, it does
not wait, and neither does the stand-in of ``one_run(..., waits=False)``), the
system stand-in answers each weight state. Each stand-in receives as the product does (``dtpf.shell.bus.Inbox``: a Zenoh subscriber whose
Python callback copies the payload into a queue that rings a doorbell) and
publishes with the product's publishers (congestion control BLOCK); the
recorder stand-in takes every message of the fleet and copies it out. The
bench process hosts the router and counts the estimates, as the launcher does.

Receivers:

- ``inbox``: one subscriber per twin and topic, as the shared services and the
  entity hold today (each subscriber's callback runs on a Python thread of
  its own in zenoh-python);
- ``demux``: one subscriber per topic in each process, on a wildcard of its
  twins, that hands each sample to its twin.

Figures: twin-steps per second (estimates from the first to the last, over
that time) and each kind of process's CPU time per twin-step in that window
(utime + stime from /proc). Whatever the layers compute comes on top: a
fleet cannot go faster than this on the same machine. Run from the
repository root::

    python -m dtpf.scripts.bench.fleet_floor                      # K = 100, both receivers, 3 repetitions
    python -m dtpf.scripts.bench.fleet_floor --twins 10 100 --repeats 1
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import random
import statistics
import struct
import subprocess
import sys
import time

from dtpf.scripts.bench.cpu import RssSampler
import numpy as np

from dtpf.shell.bus import Doorbell, Inbox, free_port, open_session, publisher, zenoh_config
from dtpf.shell.shared_sets import MIN_SHARED_BYTES, SetPublisher, shared_sets

RECEIVERS = ("inbox", "demux")
ROLES = ("recorder", "system", "information", "entity")
#: Bytes of each message of one twin-step at N = 1e3 (means over a K = 100 fleet's log), by topic.
SIZES = {"entity/particles": 16_368, "information/preprocessed": 16_464, "information/weight_state": 529,
         "system/ps": 212, "entity/estimate": 421}
#: Topics whose size grows with N (the particle sets).
SCALED = ("entity/particles", "information/preprocessed")
#: The topics that carry the lockstep (a plan must have them): the set out, the answer back, the weight state
#: to the system layer, its PS decision back, and the estimate the launcher counts.
LOCKSTEP = ("entity/particles", "information/preprocessed", "information/weight_state", "system/ps",
            "entity/estimate")
_STEP = struct.Struct("<q")
PREFIX = "floor"


def scaled_plan(scale: float = 1.0) -> dict[str, int]:
    """:data:`SIZES` with the particle sets ``scale`` times as large: bytes of each message of a twin-step."""
    return {topic: int(size * (scale if topic in SCALED else 1.0)) for topic, size in SIZES.items()}


def plan_of_log(path, steps: int) -> dict[str, int]:
    """Bytes of each message of a twin-step by topic (``layer/name``), from a dtpf log of one twin's run of
    ``steps`` steps: the topics with at least one message every other step, statuses left out (a few a run
    and more at its start and end: not step messages), each at its mean size, in the order of their first
    message."""
    from dtpf.recording.logfile import read_log

    counts, sizes = collections.Counter(), collections.Counter()
    for message in read_log(path).messages:
        topic = message.topic.split("/", 2)[2]
        counts[topic] += 1
        sizes[topic] += len(message.data)
    plan = {topic: round(sizes[topic] / counts[topic]) for topic in counts
            if counts[topic] >= steps / 2 and not topic.endswith("/status")}
    missing = [topic for topic in LOCKSTEP if topic not in plan]
    if missing:
        raise RuntimeError(f"the log {path} has no step messages on {', '.join(missing)}: the floor's stand-ins "
                           f"pass those; its step topics are {', '.join(plan) or 'none'}")
    return plan


def plan_of_launch(config, folder, steps: int = 12, **launch_options) -> dict[str, int]:
    """:func:`plan_of_log` of a short ``dtpf launch`` of ``config`` (``steps`` steps, the recorder on;
    ``launch_options`` go to :func:`dtpf.scripts.launch.launch`, e.g. ``cloud_points``)."""
    from pathlib import Path

    from dtpf.scripts.launch import launch

    path = Path(folder) / f"plan-{config.particles}-{time.monotonic_ns()}.mcap"
    config = config.model_copy(update={"steps": steps})
    try:
        launch(config, log_path=path, timeout=10.0, child_output=None, notify=lambda text: None,
               **launch_options)
        return plan_of_log(path, steps)
    finally:
        path.unlink(missing_ok=True)


def _payload(size: int, step: int) -> bytes:
    return _STEP.pack(step) + bytes(max(0, size - _STEP.size))


def _twins_of(process: int, processes: int, k: int) -> list[str]:
    """The twins an entity stand-in hosts: ``e<process>-<i>``, every processes-th of the K."""
    return [f"e{process}-{i}" for i in range(process + 1, k + 1, processes)]


class Receiver:
    """Samples of ``topic`` for a set of twins, as (twin, payload), with one doorbell for all of them."""

    def __init__(self, session, topic: str, twins: list[str] | None, chunk: str, how: str, doorbell: Doorbell):
        self.inboxes: list[Inbox] = []
        if how == "demux" or twins is None:
            self.inboxes.append(Inbox(session, f"{PREFIX}/{chunk}/{topic}", doorbell=doorbell, name=topic,
                                      views=True))
        else:
            self.inboxes += [Inbox(session, f"{PREFIX}/{twin}/{topic}", doorbell=doorbell, name=topic, views=True)
                             for twin in twins]

    def drain(self):
        for inbox in self.inboxes:
            while (item := inbox.get(timeout=0)) is not None:
                yield item.key.split("/", 2)[1], item.payload


class Publishers:
    """One publisher per key, declared on first use (as ``ServiceShell.publish`` does). A message of a
    particle set's size goes as ``ServiceShell.publish`` sends a set: through a shared-memory slot when the
    process shares its sets (:func:`dtpf.shell.shared_sets.shared_sets`), its body copied once from an array
    as the product copies a set's arrays; else as fresh bytes, as the product encodes one."""

    def __init__(self, session):
        self.session = session
        self.by_key = {}
        self.sets = {}
        self.bodies = {}

    def put(self, twin: str, topic: str, size: int, step: int) -> None:
        key = f"{PREFIX}/{twin}/{topic}"
        pub = self.by_key.get(key)
        if pub is None:
            pub = self.by_key[key] = publisher(self.session, key)
        if size < MIN_SHARED_BYTES or not shared_sets():
            pub.put(_payload(size, step))
            return
        sets = self.sets.get(key)
        if sets is None:
            sets = self.sets[key] = SetPublisher(self.session, key, pub)
        body = self.bodies.get(size)
        if body is None:
            body = self.bodies[size] = np.ones(size - _STEP.size, dtype=np.uint8)
        sets.put_parts([_STEP.pack(step), body], size)


def _serve(role: str, router: str, how: str, k: int, processes: int, process: int, steps: int,
           plan: dict[str, int], waits: bool = True) -> int:
    """One stand-in process, until 10 s pass without input (or, for an entity, its twins are done).

    Each layer stand-in publishes its layer's topics of ``plan`` (``layer/name``: bytes) in the plan's order,
    the lockstep's message first: the entity its set, then (once the answer is in) the rest of its step's
    messages before the next set; the information layer its answer, then the weight state and the rest.
    """
    session = open_session(zenoh_config(mode="client", connect=[router]))
    doorbell = Doorbell()
    out = Publishers(session)
    all_twins = [twin for p in range(processes) for twin in _twins_of(p, processes, k)]
    mine = [(topic, size) for topic, size in plan.items() if topic.split("/", 1)[0] == role]
    if role == "recorder":
        # Every message copied once into memory of its own, a buffer it reuses (as a writer's chunk buffer).
        inbox = Inbox(session, f"{PREFIX}/**", views=True)
        buffer = bytearray(0)
        while (item := inbox.get(timeout=10)) is not None:
            size = len(item.payload)
            if size > len(buffer):
                buffer = bytearray(size)
            memoryview(buffer)[:size] = item.payload
        os._exit(0)
    if role == "system":
        weights = Receiver(session, "information/weight_state", all_twins, "*", how, doorbell)
        while doorbell.wait(10):
            for twin, payload in weights.drain():
                step = _STEP.unpack_from(payload)[0]
                for topic, size in mine:
                    out.put(twin, topic, size, step)
        os._exit(0)
    if role == "information":
        answer = sorted(mine, key=lambda item: item[0] != "information/preprocessed")
        sets = Receiver(session, "entity/particles", all_twins, "*", how, doorbell)
        commands = Receiver(session, "system/ps", all_twins, "*", how, doorbell)
        decided = dict.fromkeys(all_twins, 0)  # the step of each twin's latest PS decision
        held: dict[str, list[int]] = {twin: [] for twin in all_twins}  # steps waiting for the decision before
        while doorbell.wait(10):
            touched = set()
            for twin, payload in commands.drain():
                decided[twin] = max(decided[twin], _STEP.unpack_from(payload)[0])
                touched.add(twin)
            for twin, payload in sets.drain():
                held[twin].append(_STEP.unpack_from(payload)[0])
                touched.add(twin)
            for twin in touched:
                steps_held = held[twin]
                while steps_held and (not waits or steps_held[0] - 1 <= decided[twin]):
                    step = steps_held.pop(0)
                    for topic, size in answer:
                        out.put(twin, topic, size, step)
        os._exit(0)
    twins = _twins_of(process, processes, k)
    particles = plan["entity/particles"]
    after = [(topic, size) for topic, size in mine if topic != "entity/particles"]
    answers = Receiver(session, "information/preprocessed", twins, f"e{process}-$*", how, doorbell)
    time.sleep(2.0)  # every stand-in subscribed
    done = 0
    for twin in twins:
        out.put(twin, "entity/particles", particles, 1)
    while done < len(twins) and doorbell.wait(10):
        for twin, payload in answers.drain():
            step = _STEP.unpack_from(payload)[0]
            for topic, size in after:
                out.put(twin, topic, size, step)
            if step < steps:
                out.put(twin, "entity/particles", particles, step + 1)
            else:
                done += 1
    time.sleep(0.5)
    os._exit(0)


def _kind(command: list[bytes]) -> str:
    text = b" ".join(command).decode(errors="replace")
    for role in ROLES:
        if f"--serve {role} " in text:
            return role
    return "other"


def one_run(k: int, how: str, steps: int, processes: int, scale: float = 1.0,
            plan: dict[str, int] | None = None, waits: bool = True, recorder: bool = True) -> dict:
    """Twin-steps per second, seconds per step of one twin (``step_s``) and CPU ms per twin-step by kind of
    process, of one fleet of stand-ins sending ``plan`` (default: :func:`scaled_plan` of ``scale``);
    ``waits``: the information stand-in waits for the PS decision of the step before; ``recorder``: with
    the recorder stand-in."""
    plan = plan or scaled_plan(scale)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    children = []
    try:
        session = open_session(zenoh_config(mode="client", connect=[endpoint]))
        estimates = Inbox(session, f"{PREFIX}/*/entity/estimate")
        with RssSampler(kind=_kind) as sampler:
            for role in (role for role in ROLES if recorder or role != "recorder"):
                for process in range(processes if role == "entity" else 1):
                    children.append(subprocess.Popen(
                        [sys.executable, "-P", "-m", "dtpf.scripts.bench.fleet_floor", "--serve", role, endpoint, how, str(k),
                         str(processes), str(process), str(steps), json.dumps(plan, separators=(",", ":")),
                         "wait" if waits else "no-wait"]))
            first = last = None
            count = 0
            ends: dict[str, list[float]] = {}
            while count < k * steps:
                item = estimates.get(timeout=30)
                if item is None:  # a twin's message was lost (seen in the inbox variant): this run counts as stalled
                    return {"stalled": count}
                last = time.time()
                first = first or last
                count += 1
                ends.setdefault(item.key.split("/", 2)[1], []).append(time.perf_counter())
        session.close()
        cpu = sampler.cpu_between(first, last)
        window = count - 1
        # One twin's step: the time between its consecutive estimates, from its 10th on, median over the twins.
        step_s = statistics.median((e[-1] - e[min(9, len(e) - 2)]) / (len(e) - 1 - min(9, len(e) - 2))
                                   for e in ends.values())
        return {"rate": window / (last - first), "step_s": step_s,
                "cpu_ms": {kind: 1e3 * s / window for kind, s in cpu.items()}}
    finally:
        for child in children:
            child.kill()
            child.wait()
        router.close()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.fleet_floor", description=__doc__.split("\n\n")[0])
    parser.add_argument("--twins", nargs="+", type=int, default=[100], metavar="K",
                        help="fleet sizes (default: 100)")
    parser.add_argument("--steps", type=int, default=200, help="steps per twin (default: %(default)s)")
    parser.add_argument("--entities", type=int, default=2,
                        help="entity stand-in processes, as dtpf launch --entities (default: %(default)s)")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="particle sets this many times the size of N = 1e3's (default: %(default)s)")
    parser.add_argument("--receivers", nargs="+", choices=RECEIVERS, default=list(RECEIVERS),
                        help="receivers to compare (default: both)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per variant, interleaved (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the run order")
    parser.add_argument("--serve", nargs=9, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        role, router, how, k, processes, process, steps, plan, waits = args.serve
        return _serve(role, router, how, int(k), int(processes), int(process), int(steps), json.loads(plan),
                      waits == "wait")
    variants = [(k, how) for k in args.twins for how in args.receivers]
    order = variants * args.repeats
    random.Random(args.seed).shuffle(order)
    load = os.getloadavg()[0]
    start = time.perf_counter()
    runs: dict[tuple, list[dict]] = {v: [] for v in variants}
    stalled: dict[tuple, int] = {}
    for i, (k, how) in enumerate(order, 1):
        result = one_run(k, how, args.steps, args.entities, args.scale)
        if "stalled" in result:
            stalled[k, how] = stalled.get((k, how), 0) + 1
            print(f"  run {i}/{len(order)}: K = {k} {how}: stalled after {result['stalled']} of {k * args.steps} "
                  "estimates (none for 30 s)", file=sys.stderr, flush=True)
            continue
        runs[k, how].append(result)
        print(f"  run {i}/{len(order)}: K = {k} {how}: {result['rate']:.0f} twin-steps/s, "
              f"{sum(result['cpu_ms'].values()):.3f} ms CPU per twin-step", file=sys.stderr, flush=True)
    print(f"`python -m dtpf.scripts.bench.fleet_floor{' ' + ' '.join(sys.argv[1:]) if sys.argv[1:] else ''}`: Python "
          f"{platform.python_version()}, {os.cpu_count()} CPUs, 1-min load {load:.2f} before, "
          f"{time.perf_counter() - start:.0f} s in all; {args.steps} steps per twin, {args.entities} entity "
          f"processes, particle sets of {int(SIZES['entity/particles'] * args.scale)} bytes.\n")
    kinds = ("entity", "information", "system", "recorder", "launcher")
    print("| K | receiver | runs (stalled) | twin-steps/s (range) | CPU ms per twin-step: " + " | ".join(kinds)
          + " | all |")
    print("|---" * (len(kinds) + 5) + "|")
    for k, how in variants:
        if not runs[k, how]:
            print(f"| {k} | {how} | 0 ({stalled.get((k, how), 0)}) |" + " - |" * (len(kinds) + 2))
            continue
        rates = [r["rate"] for r in runs[k, how]]
        cpu = {kind: statistics.median(r["cpu_ms"].get(kind, 0.0) for r in runs[k, how]) for kind in kinds}
        total = statistics.median(sum(r["cpu_ms"].values()) for r in runs[k, how])
        print(f"| {k} | {how} | {len(rates)} ({stalled.get((k, how), 0)}) | {statistics.median(rates):.0f} ({min(rates):.0f}-{max(rates):.0f}) | "
              + " | ".join(f"{cpu[kind]:.3f}" for kind in kinds) + f" | {total:.3f} |")
    print(f"\nMedians over {args.repeats} runs, variants interleaved. CPU: utime + stime from /proc between the "
          "first and the last estimate; 'launcher' is the bench process, with the router in it. "
          f"{os.cpu_count()} cores give {os.cpu_count() * 1000} ms of CPU a second: 1,000 twin-steps/s needs at most "
          f"{os.cpu_count():.1f} ms per twin-step in all.")
    return 0


if __name__ == "__main__":
    # Leave without the interpreter's teardown, where Zenoh's runtime threads kept a finished bench waiting.
    try:
        code = main()
    except Exception:
        import traceback
        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
