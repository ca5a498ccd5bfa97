"""One twin, one entity: a second entity of a running twin is refused; one that appears mid-run fails the launch
and is named; a log with competing estimates fails dtpf verify, every time."""
from __future__ import annotations

import argparse
import os
import re
import socket
import threading
import time

import numpy as np

from dtpf.messages.codec import MessageError, decode_for_key, encode
from dtpf.messages.config import RunConfig
from dtpf.recording.logfile import read_log
from dtpf.shell.bus import BusError, Claim, Claims, Inbox, claims_alive, free_port, open_session, zenoh_config

from conftest import service_args

#: Deadlines for a loaded 2-core machine (a service's start imports numpy and numba: seconds).
START = 90.0
RUN = 240.0


def client(port: int, deadline: float = START):
    """A Zenoh client on the launcher's router, once it listens."""
    until = time.monotonic() + deadline
    while True:
        try:
            return open_session(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
        except BusError:
            if time.monotonic() > until:
                raise
            time.sleep(0.1)


def wait_until(condition, timeout: float, what: str) -> None:
    until = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < until, f"not within {timeout:.0f} s: {what}"
        time.sleep(0.05)


def test_a_second_entity_of_a_running_twin_is_refused_and_the_run_goes_on(processes, tmp_path):
    from dtpf.scripts import inprocess
    from dtpf.scripts.launch import launch
    from dtpf.scripts.logs.verify import decoded_by_topic, verify_twin

    # 400 steps at 20 a second: the second entity's start (imports, seconds on a loaded machine) falls in the run.
    config = RunConfig(particles=100, steps=400, seed=3, twin="t-one")
    port, log_path, outcome = free_port(), tmp_path / "run.mcap", {}

    def run():
        outcome["result"] = launch(config, log_path=log_path, port=port, timeout=5.0, rate=20.0,
                                   notify=lambda text: None)

    launcher = threading.Thread(target=run)
    launcher.start()
    session = claims = None
    try:
        session = client(port)
        claims = Claims(session, config.twin)
        wait_until(lambda: claims.seen or not launcher.is_alive(), START, "the launch's entity claims its twin")
        assert launcher.is_alive(), "the launch ended before its entity started"
        # The same twin and run id, against the same router: refused at once, before it publishes anything.
        second = processes.start("second", service_args(
            "dtpf.entity.service", f"tcp/127.0.0.1:{port}", "--twin", config.twin, "--run-id", config.run_id,
            "--particles", "100", "--steps", "400", "--seed", "3"))
        assert second.wait(timeout=START) == 2
        lines = processes.output(second).strip().splitlines()
        assert len(lines) == 1, lines
        assert "twin t-one is already run by another entity on this bus" in lines[0]
        assert "one twin, one entity; not started" in lines[0]
        assert launcher.is_alive(), "the run should still be going on after the refusal"
        launcher.join(timeout=RUN)
    finally:
        if claims is not None:
            claims.close()
        if session is not None:
            session.close()
        launcher.join(timeout=60)
    result = outcome["result"]
    # The first run is unaffected: every step, none degraded, the numbers of the run alone, no competitor.
    assert result.failure is None and result.competitors == [] and not result.tally.competing_steps
    assert result.ignored_statuses == 0 and result.tally.ignored == 0
    assert sorted(e.step for e in result.estimates) == list(range(1, config.steps + 1))
    assert not any(e.degraded for e in result.estimates)
    reference = inprocess.run(config)
    np.testing.assert_array_equal([e.mean for e in result.estimates], reference.means)
    verification = verify_twin(decoded_by_topic(read_log(log_path)), config.twin)
    assert verification.ok and not verification.competing, verification.mismatch


def test_a_predecessor_that_died_leaves_its_twin_free(processes, router):
    """A restarted entity comes back: its predecessor's claim goes with its connection."""
    twin = "t-again"
    def args(steps: int) -> list[str]:
        return service_args("dtpf.entity.service", router.endpoint, "--twin", twin, "--no-preprocess",
                            "--particles", "100", "--steps", str(steps), "--rate", "20", "--cloud-points", "0")

    first = processes.start("first", args(100_000))
    claims = Claims(router.session, twin)
    try:
        wait_until(lambda: claims.seen or first.poll() is not None, START, "the first entity claims its twin")
        assert first.poll() is None, processes.output(first)
        assert [claim.pid for claim in claims_alive(router.session, [twin], grace=0)] == [first.pid]
        os.killpg(first.pid, 9)
        first.wait(timeout=10)
        # At once after its death: the query waits (CLAIM_GRACE) for the dead claim to go.
        again = processes.start("again", args(5))
        assert again.wait(timeout=START) == 0, processes.output(again)
    finally:
        claims.close()


class Competitor:
    """Another entity of the twin appearing mid-run (a healed partition, a mistake): it claims the twin as an
    entity does and publishes estimates of the run's steps again."""

    def __init__(self, port: int, twin: str, run_id: str):
        self.session = client(port)
        self.claim = Claim(twin, run_id, "elsewhere", 4242)
        self.token = None  # claimed once the run is under way: mid-run
        self.inbox = Inbox(self.session, f"dtpf/{twin}/entity/estimate")
        self.publisher = self.session.declare_publisher(f"dtpf/{twin}/entity/estimate")
        self.sent: list[int] = []

    def echo(self, count: int, timeout: float) -> None:
        """Publish ``count`` estimates again, each of a step the twin has just published."""
        until = time.monotonic() + timeout
        while len(self.sent) < count and time.monotonic() < until:
            item = self.inbox.get(timeout=0.1)
            if item is None:
                continue
            try:
                estimate = decode_for_key(item.key, item.payload)
            except MessageError:
                continue
            if estimate.step in self.sent:
                continue
            if self.token is None:
                self.token = self.session.liveliness().declare_token(self.claim.key)
            self.sent.append(estimate.step)
            self.publisher.put(encode(estimate.model_copy(update={"mean": [float(v) + 1.0 for v in estimate.mean]})))

    def close(self) -> None:
        self.inbox.close()
        if self.token is not None:
            self.token.undeclare()
        self.session.close()


def launch_beside_a_competitor(processes, args: list[str], twin: str, count: int):
    """``dtpf launch ARGS`` (40 steps/s, N = 100) with a :class:`Competitor` of ``twin`` echoing ``count`` of its
    estimates mid-run: (the launcher's exit code, its output, the competitor)."""
    port = free_port()
    launcher = processes.start("launcher", ["-m", "dtpf.scripts.cli", "launch", "--policy", "fixed", "--rate", "40", "--particles", "100",
                                            "--port", str(port), "--quiet", *args])
    competitor = None
    try:
        competitor = Competitor(port, twin, "run")
        competitor.echo(count, START)
        assert len(competitor.sent) == count, processes.output(launcher)
        launcher.wait(timeout=RUN)
    finally:
        if competitor is not None:
            competitor.close()
    return launcher.returncode, processes.output(launcher), competitor


def test_a_competitor_that_appears_mid_run_fails_the_launch_and_is_named(processes, tmp_path, capsys):
    from dtpf.scripts.logs.verify import cmd_verify

    twin, log = "t-rival", tmp_path / "run.mcap"
    returncode, output, competitor = launch_beside_a_competitor(
        processes, ["--steps", "200", "--twin", twin, "-o", str(log)], twin, 5)
    assert returncode == 1, output
    named = "competing       another entity ran this twin during the run (twin t-rival: run run, process 4242 " \
            "on elsewhere)"
    assert named in output
    assert "steps had an estimate besides the one taken" in output
    assert "dtpf launch: error: another entity ran twin t-rival during the run" in output
    # Its log holds both entities' estimates: dtpf verify fails it, naming the steps, every time.
    from dtpf.scripts.logs.summary import format_ranges

    competing = format_ranges(competitor.sent)
    for _ in range(3):
        assert cmd_verify(argparse.Namespace(log=[str(log)], twin=None, model=None, verbose=False)) == 1
        out = capsys.readouterr().out
        assert f"FAILED: dtpf/t-rival/entity/estimate had more than one message at steps {competing}:" in out, out
        assert "OK:" not in out


def test_a_competitor_of_one_twin_of_a_fleet_fails_the_fleet_and_is_named(processes):
    base = "t-crowd"
    returncode, output, _ = launch_beside_a_competitor(
        processes, ["--twins", "2", "--steps", "150", "--twin", base, "--entities", "1"], f"{base}-2", 3)
    assert returncode == 1, output
    assert f"competing       another entity ran twin {base}-2: run run, process 4242 on elsewhere" in output
    assert re.search(rf"^{base}-2 .*another entity ran this twin during the run", output, re.MULTILINE), output
    assert not re.search(rf"^{base}-1 .*another entity", output, re.MULTILINE), output
    assert "dtpf launch: error: another entity ran 1 of the fleet's twins" in output


class Partition:
    """A TCP link from ``port`` to the router on ``target``, cut until :meth:`heal` (then it forwards both
    ways): the two sides of a partitioned network."""

    def __init__(self, port: int, target: int):
        self.port, self.target = port, target
        self.sockets: list[socket.socket] = []
        self.server: socket.socket | None = None

    def heal(self) -> None:
        self.server = socket.create_server(("127.0.0.1", self.port))
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                near, _ = self.server.accept()
                far = socket.create_connection(("127.0.0.1", self.target))
            except OSError:
                return
            self.sockets += [near, far]
            for source, sink in ((near, far), (far, near)):
                threading.Thread(target=self._pump, args=(source, sink), daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, sink: socket.socket) -> None:
        try:
            while data := source.recv(1 << 16):
                sink.sendall(data)
            sink.shutdown(socket.SHUT_WR)
        except OSError:
            pass

    def close(self) -> None:
        for sock in ([self.server] if self.server else []) + self.sockets:
            try:
                sock.close()
            except OSError:
                pass


def test_an_entity_behind_a_healed_partition_fails_the_launch_and_is_named(processes, tmp_path):
    """A real entity of the twin, started where the launch's router could not be reached (its start-up check
    finds nobody), joins the launch's bus mid-run when the partition heals."""
    twin, port, cut, log = "t-healed", free_port(), free_port(), tmp_path / "run.mcap"
    # A peer that keeps trying its router every 0.2 s (Zenoh's connect retry) and runs on its own meanwhile.
    rival = processes.start("rival", service_args(
        "dtpf.entity.service", f"tcp/127.0.0.1:{cut}", "--mode", "peer", "--twin", twin, "--particles", "100",
        "--steps", "100000", "--rate", "20", "--cloud-points", "0", "--startup-timeout", "1",
        "--cfg", "connect/timeout_ms:100", "--cfg", "connect/exit_on_failure:false",
        "--cfg", 'connect/retry:{"period_init_ms":200,"period_max_ms":200,"period_increase_factor":1}'))
    partition = Partition(cut, port)
    launcher = session = None
    try:
        wait_until(lambda: "going on without" in processes.output(rival) or rival.poll() is not None, START,
                   "the rival entity runs on its own side")
        launcher = processes.start("launcher", ["-m", "dtpf.scripts.cli", "launch", "--steps", "300", "--rate",
                                                "30", "--particles", "100", "--twin", twin, "--port", str(port),
                                                "-o", str(log), "--quiet"])
        session = client(port)
        estimates = Inbox(session, f"dtpf/{twin}/entity/estimate")
        assert estimates.get(timeout=START) is not None, processes.output(launcher)
        assert rival.poll() is None, processes.output(rival)
        partition.heal()
        launcher.wait(timeout=RUN)
        estimates.close()
    finally:
        partition.close()
        if session is not None:
            session.close()
    output = processes.output(launcher)
    assert launcher.returncode == 1, output
    assert re.search(rf"^competing +another entity ran this twin during the run \(twin {twin}: run run, process "
                     rf"{rival.pid} on \S+\)$", output, re.MULTILINE), output
    assert f"dtpf launch: error: another entity ran twin {twin} during the run" in output
