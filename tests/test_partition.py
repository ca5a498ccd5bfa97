"""A fleet split over two hosts keeps its whole record through a partition longer than a Zenoh lease.

Two hosts are two network namespaces joined by a veth link (10.77.0.1 and
10.77.0.2), each with a dtpf router; the routers join. Host A runs the shared
information and system services, a central recorder (``--all-twins``) and two
twins; host B runs two twins, a third twin whose publishers keep a cache of 30
messages (3 s), and a recorder of its own. The link is cut for 15 s mid-run,
longer than a Zenoh session's 10 s lease: host B's twins run on with plain
resampling and host A's recorder hears nothing of them. Both deployments are
checked in the one run:

- a central recorder: when the link comes back, host A's recorder recovers host
  B's messages from their publishers' caches, so its log alone holds every step
  of every twin whose cache outlasted the cut; of the twin with the small cache
  it names the steps it lost (``dtpf summary``), and says when host B's twins
  went silent and when they came back;
- a recorder per host: ``dtpf summary a.mcap b.mcap`` holds every step of every
  twin, the small cache's included;

and host B's twins, degraded while the shared services were out of reach,
preprocess again soon after the link is back (the services ask for their
statuses instead of waiting for the next).

Making namespaces needs root and the ``ip`` command; where either is missing
the test is skipped and says so.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dtpf.recording.logfile import LogError, read_log, read_logs
from dtpf.scripts.logs.summary import format_ranges, format_summary, summarise

STEPS, RATE, CUT = 260, 10.0, 15.0
PORT = 7447
#: The cache of the third twin of host B, in messages a publisher: 3 s at RATE, less than the cut.
SMALL_CACHE = 30
#: Seconds after the link's return within which host B's twins preprocess again: a reconnection (Zenoh tries
#: every half second, :data:`dtpf.shell.bus.RECONNECT`), the services' question and answer, and the entity's
#: next step, with room for a loaded machine.
BACK_WITHIN = 2.5


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)


@pytest.fixture
def two_hosts():
    """Two network namespaces joined by a veth link: {'a': (namespace, address), 'b': ...}."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("two hosts need network namespaces: root and the ip command (iproute2)")
    tag = f"{os.getpid() % 100000}"
    hosts = {"a": (f"dtpf-a{tag}", "10.77.0.1", f"dtpa{tag}"), "b": (f"dtpf-b{tag}", "10.77.0.2", f"dtpb{tag}")}
    made = []
    try:
        for namespace, _, _ in hosts.values():
            done = _ip("netns", "add", namespace)
            if done.returncode != 0:
                pytest.skip(f"cannot make a network namespace here: {done.stderr.strip()}")
            made.append(namespace)
        (na, address_a, link_a), (nb, address_b, link_b) = hosts["a"], hosts["b"]
        for command in (("link", "add", link_a, "netns", na, "type", "veth", "peer", "name", link_b, "netns", nb),
                        ("-n", na, "addr", "add", f"{address_a}/24", "dev", link_a),
                        ("-n", nb, "addr", "add", f"{address_b}/24", "dev", link_b),
                        ("-n", na, "link", "set", link_a, "up"), ("-n", nb, "link", "set", link_b, "up"),
                        ("-n", na, "link", "set", "lo", "up"), ("-n", nb, "link", "set", "lo", "up")):
            done = _ip(*command)
            assert done.returncode == 0, f"ip {' '.join(command)}: {done.stderr}"
        yield hosts
    finally:
        for namespace in made:
            _ip("netns", "del", namespace)


class Host:
    """Processes started in one namespace; every one is stopped at the end, pass or fail."""

    def __init__(self, namespace: str, folder: Path):
        self.namespace, self.folder, self.started = namespace, folder, []

    def start(self, name: str, *args: str) -> subprocess.Popen:
        log = open(self.folder / f"{self.namespace}-{name}.log", "wb")
        process = subprocess.Popen(["ip", "netns", "exec", self.namespace, sys.executable, "-P", *args],
                                   stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        process.name, process.log_path = name, log.name
        self.started.append(process)
        return process

    def output(self, process) -> str:
        return Path(process.log_path).read_text(errors="replace")

    def stop(self, process, grace: float = 20.0) -> None:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGINT)
            try:
                process.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()

    def kill_all(self) -> None:
        for process in self.started:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(timeout=10)


_PROBE = "import socket, sys; socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=1).close()"


def _wait_listening(namespace: str, address: str, port: int, timeout: float = 60.0) -> None:
    """Until something accepts TCP connections on ``address:port`` inside ``namespace``."""
    deadline = time.monotonic() + timeout
    while subprocess.run(["ip", "netns", "exec", namespace, sys.executable, "-c", _PROBE, address, str(port)],
                         capture_output=True, timeout=30).returncode != 0:
        assert time.monotonic() < deadline, f"nothing listens on {address}:{port} in {namespace}"
        time.sleep(0.2)


def _wait_said(host: Host, process, text: str, timeout: float = 60.0) -> None:
    """Until ``process`` has written ``text`` to its output."""
    deadline = time.monotonic() + timeout
    while text not in host.output(process):
        assert process.poll() is None, host.output(process)[-3000:]
        assert time.monotonic() < deadline, f"{process.name} did not say {text!r}: {host.output(process)[-3000:]}"
        time.sleep(0.1)


def _estimate_steps(path: Path, twin: str) -> set[int]:
    """The steps of ``twin``'s estimates in a log being written (read as far as it goes)."""
    try:
        log = read_log(path)
    except LogError:
        return set()
    return {m.step for _, m in log.decoded([f"dtpf/{twin}/entity/estimate"]) if hasattr(m, "step")}


def test_a_partition_longer_than_a_lease_loses_nothing_a_cache_holds(two_hosts, tmp_path):
    (na, address_a, link_a), (nb, address_b, _) = two_hosts["a"], two_hosts["b"]
    a, b = Host(na, tmp_path), Host(nb, tmp_path)
    router_a, router_b = f"tcp/{address_a}:{PORT}", f"tcp/{address_b}:{PORT}"
    run = ("--steps", str(STEPS), "--rate", str(RATE), "--timeout", "0.5", "--log-level", "INFO",
           "--wait-for", "information", "--wait-for", "system")
    try:
        a.start("router", "-m", "dtpf", "router", "--listen", router_a)
        _wait_listening(na, address_a, PORT)
        b.start("router", "-m", "dtpf", "router", "--listen", router_b, "--connect", router_a)
        _wait_listening(nb, address_b, PORT)
        recorders = [a.start("recorder", "-m", "dtpf.scripts.record", "--connect", router_a, "--all-twins",
                             "--flush-interval", "0.2", "--log-level", "INFO", "-o", str(tmp_path / "a.mcap")),
                     b.start("recorder", "-m", "dtpf.scripts.record", "--connect", router_b, "--all-twins",
                             "--flush-interval", "0.2", "--log-level", "INFO", "-o", str(tmp_path / "b.mcap"))]
        # An --all-twins recorder declares no token of the entities' twins (an entity's --wait-for recorder
        # waited its whole startup timeout, 20 s, for it): the recorders are subscribed once they say so,
        # before the shared layers start, so their subscriptions reach host B before the shared layers'
        # tokens, which the entities wait for.
        for recorder in recorders:
            _wait_said(a if recorder in a.started else b, recorder, "recording dtpf/** into")
        shared = [a.start("information", "-m", "dtpf.information.service", "--connect", router_a, "--twins", "p-*"),
                  a.start("system", "-m", "dtpf.system.service", "--connect", router_a, "--twins", "p-*")]
        entities = [a.start("entity", "-m", "dtpf.entity.service", "--connect", router_a, "--twin", "p-a",
                            "--twins", "2", *run),
                    b.start("entity", "-m", "dtpf.entity.service", "--connect", router_b, "--twin", "p-b",
                            "--twins", "2", *run),
                    b.start("entity-small-cache", "-m", "dtpf.entity.service", "--connect", router_b, "--twin", "p-c",
                            "--twins", "1", "--cache-samples", str(SMALL_CACHE), *run)]
        # Cut the link once host A's recorder hears host B's twins at work.
        deadline = time.monotonic() + 120
        while min(len(_estimate_steps(tmp_path / "a.mcap", twin)) for twin in ("p-b-1", "p-c-1")) < 20:
            assert time.monotonic() < deadline, b.output(entities[1])[-3000:]
            assert all(e.poll() is None for e in entities), [a.output(entities[0])[-2000:], b.output(entities[1])]
            time.sleep(0.25)
        assert _ip("-n", na, "link", "set", link_a, "down").returncode == 0
        time.sleep(CUT)  # the partition itself: what is measured is what survives it
        assert _ip("-n", na, "link", "set", link_a, "up").returncode == 0
        back_at = time.time()  # the estimates' stamps are this machine's wall clock too
        for entity in entities:
            entity.wait(timeout=240)
            assert entity.returncode == 0, (a if entity is entities[0] else b).output(entity)[-3000:]
        for process in [*shared, *recorders]:
            (a if process in a.started else b).stop(process)
    finally:
        a.kill_all()
        b.kill_all()
    said_a = a.output(recorders[0])
    whole = ("p-a-1", "p-a-2", "p-b-1", "p-b-2")
    every = set(range(1, STEPS + 1))
    # The cut was real: host A's recorder said when host B's twins went silent and when they came back.
    assert "twin p-b-1: no message for" in said_a and "twin p-b-1: messages again after" in said_a, said_a[-3000:]
    # A central recorder: its log alone holds every step of the twins whose caches outlasted the cut.
    central = summarise(read_log(tmp_path / "a.mcap"))
    by_twin = {t.twin: t for t in central.twins}
    missing = {t: format_ranges(every - set(by_twin[t].steps)) for t in whole}
    assert all(by_twin[t].steps == sorted(every) for t in whole), (missing, said_a[-3000:])
    # ... and of the twin whose cache did not, the steps it lost, named by dtpf summary as the recorder's.
    small = by_twin["p-c-1"]
    assert small.missing_count > CUT * RATE - SMALL_CACHE - 40, (small.missing_count, format_ranges(small.missing_steps))
    assert set(small.missing_steps) <= set(small.lost_steps), (small.missing_steps, small.lost)
    text = format_summary(central)
    assert f"lost          steps {format_ranges(small.lost_steps)}, declared lost by the recorder" in text, text
    # A recorder per host: the two logs together hold every step of every twin.
    summary = summarise(read_logs([tmp_path / "b.mcap", tmp_path / "a.mcap"]))
    steps = {t.twin: t.steps for t in summary.twins if t.twin in (*whole, "p-c-1")}
    assert steps == {twin: sorted(every) for twin in (*whole, "p-c-1")}, \
        {t: format_ranges(every - set(s)) for t, s in steps.items()}
    # Host B's twins preprocess again soon after the link is back: their last degraded step is made (its estimate's
    # stamp) within BACK_WITHIN seconds of the link's return.
    stamps = {(m.twin_id, m.step): m.stamp.sec + m.stamp.nsec / 1e9
              for _, m in read_log(tmp_path / "b.mcap").decoded(["dtpf/p-b-1/entity/estimate",
                                                                  "dtpf/p-b-2/entity/estimate"])}
    late = {twin: stamps[twin, by_twin[twin].degraded_steps[-1]] - back_at for twin in ("p-b-1", "p-b-2")}
    print(f"small cache: missing {format_ranges(small.missing_steps)}, lost {format_ranges(small.lost_steps)}; "
          f"host B degraded {[format_ranges(by_twin[t].degraded_steps) for t in ('p-b-1', 'p-b-2')]}, the last "
          f"{late} s after the link's return")
    assert all(seconds <= BACK_WITHIN for seconds in late.values()), late
