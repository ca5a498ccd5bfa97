"""Nothing recorded is lost, whatever the disk or the bus does: a forged future step, a full disk."""
from __future__ import annotations

import errno
import os
import threading
import time

import numpy as np
import pytest
import zenoh

from dtpf.messages.codec import MessageError, decode_for_key, encode
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate
from dtpf.recording.logfile import LogError, last_estimate_steps, read_log
from dtpf.recording.writer import LogWriteError, McapRecording
from dtpf.scripts.launch import launch
from dtpf.shell.bus import BusError, Inbox, free_port, open_session, zenoh_config


class Forger:
    """A session on a plain twin's router that, once the twin's first estimate passes, publishes
    well-formed estimates of the steps ``forged`` (all at once, long before the twin gets there)."""

    def __init__(self, twin: str, port: int, forged: range):
        self.twin, self.forged, self.sent = twin, forged, 0
        self.session = open_session(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
        self.inbox = Inbox(self.session, f"dtpf/{twin}/entity/estimate")
        self.publisher = self.session.declare_publisher(f"dtpf/{twin}/entity/estimate",
                                                        congestion_control=zenoh.CongestionControl.BLOCK)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set() and not self.sent:
            item = self.inbox.get(timeout=0.05)
            if item is None:
                continue
            try:
                real = decode_for_key(item.key, item.payload)
            except MessageError:
                continue
            for step in self.forged:
                self.publisher.put(encode(real.model_copy(update={"step": step, "mean": [1000.0]})))
                self.sent += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self.inbox.close()
        self.session.close()


FORGED = range(90, 120)


@pytest.fixture(scope="module")
def forged_launch(tmp_path_factory):
    """A plain launch of 120 steps whose estimates of steps 90-119 a forger publishes after step 1."""
    config = RunConfig(particles=100, steps=120, seed=3, twin="t-forged")
    port, log_path, outcome = free_port(), tmp_path_factory.mktemp("forged") / "forged.mcap", {}

    def run():
        outcome["result"] = launch(config, log_path=log_path, port=port, timeout=5.0, rate=60.0,
                                   notify=lambda text: None)

    launcher = threading.Thread(target=run)
    launcher.start()
    forger = None
    try:
        deadline = time.monotonic() + 60
        while forger is None:  # the launcher's router is not listening at once
            try:
                forger = Forger(config.twin, port, FORGED)
            except BusError:
                if time.monotonic() > deadline or not launcher.is_alive():
                    raise
                time.sleep(0.1)
        launcher.join(timeout=180)
    finally:
        if forger is not None:
            forger.close()
        launcher.join(timeout=60)
    assert forger.sent == len(FORGED)
    return config, outcome["result"], log_path


def test_a_forged_estimate_of_future_steps_leaves_every_real_step_in_the_log(forged_launch):
    config, result, log_path = forged_launch
    assert len({e.step for e in result.estimates}) == config.steps
    log = read_log(log_path)
    steps: dict[int, list[Estimate]] = {}
    for _, message in log.decoded(lambda topic: topic.endswith("/entity/estimate")):
        steps.setdefault(message.step, []).append(message)
    assert sorted(steps) == list(range(1, config.steps + 1))  # every real step is in the log
    competing = {step for step, found in steps.items() if len(found) > 1}
    assert competing == set(FORGED)  # the forged steps hold the forgery and the real estimate
    for step in FORGED:
        assert sorted(float(np.ravel(e.mean)[0]) == 1000.0 for e in steps[step]) == [False, True]
    # The launcher saw them too, and its summary names them (a forger has no entity's claim: not a competitor).
    assert result.tally.competing_steps == set(FORGED) and result.competitors == []
    assert "competing       30 steps had an estimate besides the one taken (90-119)" in result.summary()


def test_dtpf_summary_names_the_competing_steps_and_uses_the_real_estimates(forged_launch):
    from dtpf.scripts.logs.summary import format_summary, summarise

    config, result, log_path = forged_launch
    summary = summarise(read_log(log_path))
    (twin,) = summary.twins
    assert twin.steps == list(range(1, config.steps + 1))
    assert twin.competing_steps == list(FORGED) and twin.duplicate_estimates == len(FORGED)
    assert f"{twin.rmse:.4f}" == f"{result.rmse:.4f}"  # the launcher's own figure: the forgeries not used
    assert "competing     30 steps had more than one estimate (90-119; 30 more)" in format_summary(summary)


def test_dtpf_verify_fails_a_log_with_forged_estimates_naming_the_steps(forged_launch, capsys):
    """One twin, one entity: the forged estimates of steps 90-119 are not the twin's run, so the log fails, every
    time, though the layers' outputs of every step are reproduced."""
    import argparse

    from dtpf.scripts.logs.verify import cmd_verify, decoded_by_topic, verify_twin

    config, _, log_path = forged_launch
    result = verify_twin(decoded_by_topic(read_log(log_path)), config.twin)
    assert result.mismatch is None and len(result.checked) == config.steps and not result.ok
    assert result.entity_competing == {f"dtpf/{config.twin}/entity/estimate": list(FORGED)}
    for _ in range(3):
        assert cmd_verify(argparse.Namespace(log=[str(log_path)], twin=None, model=None, verbose=False)) == 1
        out = capsys.readouterr().out
        assert f"FAILED: dtpf/{config.twin}/entity/estimate had more than one message at steps 90-119" in out
        assert "OK:" not in out


def test_dtpf_verify_reproduces_one_of_a_steps_competing_commands_and_says_which(forged_launch, tmp_path):
    import dataclasses

    from dtpf.recording.logfile import write_log
    from dtpf.scripts.logs.verify import decoded_by_topic, verify_twin

    config, _, log_path = forged_launch
    log = read_log(log_path)
    topic = f"dtpf/{config.twin}/system/ps"
    at = next(i for i, item in enumerate(log.messages)
              if item.topic == topic and decode_for_key(item.topic, item.data).step == 5)
    real = decode_for_key(topic, log.messages[at].data)
    forged = dataclasses.replace(log.messages[at], data=encode(real.model_copy(update={"ps": 0.25})))
    log.messages.insert(at, forged)  # received first
    write_log(log, tmp_path / "two-commands.mcap")
    result = verify_twin(decoded_by_topic(read_log(tmp_path / "two-commands.mcap")), config.twin)
    # The layers' outputs are reproduced, the command of step 5 by its second message; the log fails all the
    # same, on the forged estimates (one twin, one entity).
    assert result.mismatch is None and len(result.checked) == config.steps and not result.ok
    estimates = f"dtpf/{config.twin}/entity/estimate"
    assert result.competing == {topic: [5], estimates: list(FORGED)} and result.used == {(topic, 5): 1}
    assert result.entity_competing == {estimates: list(FORGED)}
    # With the forgery alone at that step, the re-run does not reproduce it.
    del log.messages[at + 1]
    write_log(log, tmp_path / "forged-command.mcap")
    result = verify_twin(decoded_by_topic(read_log(tmp_path / "forged-command.mcap")), config.twin)
    assert not result.ok and result.mismatch.step == 5 and result.mismatch.field == "ps"


def test_the_recorder_keeps_at_most_a_bounded_number_of_copies_of_one_step():
    from dtpf.recording import admission

    assert 2 <= admission.MAX_COPIES <= 64 and admission.MAX_TRACKED_STEPS >= 1 << 12


# --- a log that cannot be written --------------------------------------------------------------------------


def _fill(recording: McapRecording, count: int, size: int) -> None:
    for i in range(count):
        recording.write("dtpf/t/entity/unknown", os.urandom(size))


def test_a_write_past_a_file_size_limit_raises_one_log_write_error_and_keeps_what_came_before(tmp_path):
    import resource

    path = tmp_path / "limited.mcap"
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (256 << 10, hard))  # CPython ignores SIGXFSZ: writes fail EFBIG
    try:
        recording = McapRecording(path, compression="none", chunk_size=16 << 10, flush_interval=0.0)
        with pytest.raises(LogWriteError) as raised:
            _fill(recording, 10_000, 1000)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    error = raised.value
    assert error.cause.errno == errno.EFBIG and error.disk_full
    assert str(error).startswith(f"cannot write the log {path}: ") and "\n" not in str(error)
    assert 100 < error.messages < 10_000
    with pytest.raises(LogWriteError):  # the recording has ended
        recording.write("dtpf/t/entity/unknown", b"x")
    recording.close()  # and closing it again is quiet
    log = read_log(path)
    assert not log.complete and error.messages - 20 <= len(log.messages) <= error.messages


def test_a_log_deleted_while_recording_is_a_log_write_error(tmp_path):
    path = tmp_path / "gone" / "run.mcap"
    recording = McapRecording(path, flush_interval=0.0)
    recording.write("dtpf/t/entity/unknown", b"before")
    os.unlink(path)
    with pytest.raises(LogWriteError, match="deleted while it was being written") as raised:
        recording.write("dtpf/t/entity/unknown", b"after")
    assert raised.value.cause is None and not raised.value.disk_full


def test_last_estimate_steps_names_each_twins_highest_step(tmp_path):
    path = tmp_path / "steps.mcap"
    with McapRecording(path) as recording:
        for twin, last in (("a", 7), ("b", 3)):
            for step in (*range(1, last + 1), 2):
                estimate = Estimate(run_id="r", twin_id=twin, step=step, mean=[0.0], var=[1.0], lower=[-2.0],
                                    upper=[2.0], ess=1.0, ess_ratio=0.01, resampled=True, degraded=False)
                recording.write(f"dtpf/{twin}/entity/estimate", encode(estimate))
    assert last_estimate_steps(read_log(path)) == {"a": 7, "b": 3}


# --- a viewer's configuration from any working directory -----------------------------------------------------

_VIEWER = """
import sys, time, zenoh
config = zenoh.Config.from_file(sys.argv[1])
deadline, session = time.monotonic() + 120, None
while session is None:  # the launcher's router may not listen yet
    try:
        session = zenoh.open(config)
    except zenoh.ZError:
        if time.monotonic() > deadline:
            raise
        time.sleep(0.2)
got = []
subscriber = session.declare_subscriber(sys.argv[2], lambda sample: got.append(sample))
while len(got) < 10 and time.monotonic() < deadline:
    time.sleep(0.05)
print(len(got), flush=True)
session.close()
"""


def test_a_viewer_file_opened_from_another_folder_by_plain_zenoh_receives_a_secured_twin(tmp_path):
    """A Zenoh client that knows nothing of dtpf opens DIR/tls/viewer.json5 from elsewhere: its certificates
    are in the file, not at paths Zenoh would resolve against the working directory."""
    pytest.importorskip("cryptography")
    import subprocess
    import sys

    from dtpf.scripts import secure

    port = free_port()
    secure.init(tmp_path / "deploy", port=port)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    viewer_file = (tmp_path / "deploy" / "tls" / "viewer.json5").resolve()
    twin = "t-viewer-anywhere"
    viewer = subprocess.Popen([sys.executable, "-c", _VIEWER, str(viewer_file), f"dtpf/{twin}/entity/estimate"],
                              cwd=elsewhere, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        result = launch(RunConfig(particles=100, steps=120, seed=1, twin=twin), log_path=tmp_path / "v.mcap",
                        port=port, rate=20.0, timeout=5.0, secure=tmp_path / "deploy" / "tls",
                        notify=lambda text: None)
        out, err = viewer.communicate(timeout=120)
    finally:
        if viewer.poll() is None:
            viewer.kill()
            viewer.wait()
    assert len(result.estimates) == 120
    assert viewer.returncode == 0, err[-2000:]
    assert int(out.split()[-1]) >= 10


# --- a launch onto a full disk ------------------------------------------------------------------------------


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB folder: a tmpfs where this process may mount one, else the same limit as RLIMIT_FSIZE (the
    launcher and its children inherit it; a write past it fails with EFBIG, as CPython ignores SIGXFSZ)."""
    import resource
    import subprocess

    folder = tmp_path / "small"
    folder.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(folder)],
                             capture_output=True).returncode == 0 if os.geteuid() == 0 else False
    limit = None if mounted else (lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (2 << 20, 2 << 20)))
    try:
        yield folder, limit
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def test_a_launch_onto_a_full_disk_ends_its_log_cleanly_and_says_up_to_which_step(small_disk):
    import subprocess
    import sys

    folder, limit = small_disk
    log = folder / "x.mcap"
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "dtpf", "launch", "-q", "--steps", "200", "--rate", "100",
                           "-o", str(log)], capture_output=True, text=True, timeout=180, preexec_fn=limit)
    took = time.monotonic() - started
    assert done.returncode == 1, done.stderr[-3000:]  # the run itself completed, its record did not
    assert "dtpf launch: error: the log is incomplete: cannot write the log" in done.stderr
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    assert took < 60
    assert "steps           200 of 200" in done.stdout
    ended = [line for line in done.stdout.splitlines() if line.startswith("log ended")]
    assert len(ended) == 1 and ("ENOSPC" in ended[0] or "EFBIG" in ended[0]), done.stdout
    held = int(ended[0].split("it holds the run up to step ")[1].split()[0])
    assert 1 <= held < 200
    assert sorted(p.name for p in folder.iterdir()) == ["x.mcap"]  # no recorder restarted into the full disk
    # The log holds exactly what the launcher said, and reads as a cut-short file.
    read = read_log(log)
    assert not read.complete
    assert last_estimate_steps(read) == {"ungm-1": held}
    steps = sorted({m.step for _, m in read.decoded(lambda t: t.endswith("/entity/estimate"))})
    assert steps == list(range(1, held + 1))


# --- what others publish does not hold the end of a run -------------------------------------------------------


class Flooder:
    """Publishes ``{}`` at ``rate`` Hz on a twin's system status key until closed."""

    def __init__(self, twin: str, port: int, rate: float):
        self.twin, self.rate, self.sent = twin, rate, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(port,), daemon=True)
        self._thread.start()

    def _run(self, port: int) -> None:
        session = None
        while session is None and not self._stop.is_set():
            try:
                session = open_session(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
            except BusError:
                time.sleep(0.05)
        if session is None:
            return
        publisher = session.declare_publisher(f"dtpf/{self.twin}/system/status")
        while not self._stop.wait(1.0 / self.rate):
            publisher.put(b"{}")
            self.sent += 1
        session.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)


def _tail(twin: str, flood: bool) -> tuple[float, int]:
    """Seconds from the run's last estimate to the launch's return, and how many flood messages were sent."""
    port, last = free_port(), {}
    flooder = Flooder(twin, port, rate=50.0) if flood else None

    def progress(step, total):
        last["at"] = time.monotonic()

    try:
        result = launch(RunConfig(particles=100, steps=60, twin=twin), record=False, port=port, timeout=5.0,
                        rate=30.0, progress=progress, notify=lambda text: None)
        ended = time.monotonic()
    finally:
        if flooder is not None:
            flooder.close()
    assert len(result.estimates) == 60
    return ended - last["at"], flooder.sent if flooder else 0


def test_a_status_flood_does_not_hold_the_end_of_a_launch():
    quiet, _ = _tail("t-quiet-end", flood=False)
    flooded, sent = _tail("t-flooded-end", flood=True)
    assert sent >= 50  # the flood ran for the whole run (60 steps at 30 steps/s: 2 s)
    assert flooded <= quiet + 2.0, (flooded, quiet)


def test_a_recorder_stopped_before_a_twin_ended_waits_for_it_and_still_finishes_its_log(processes, router, tmp_path):
    """Stopped while a twin it heard from has not said its run ended, the recorder keeps taking messages for
    --drain-finished seconds, longer than the exit watchdog's grace (which cut that wait and left the log
    without its summary and footer, exit code 130), then says so, finishes the log and exits 0."""
    import signal

    from conftest import service_args
    from dtpf.shell.service import EXIT_GRACE

    log = tmp_path / "waiting.mcap"
    recorder = processes.start("recorder", service_args("dtpf.scripts.record", router.endpoint, "--all-twins",
                                                        "--twin", "w-recorder", "--drain-finished", "4", "-o",
                                                        str(log)))
    assert router.collect(lambda ms: any(getattr(m, "layer", None) == "recorder" for m in ms), timeout=60), \
        processes.output(recorder)
    publisher = router.session.declare_publisher("dtpf/w-1/entity/estimate")
    estimate = Estimate(run_id="w", twin_id="w-1", step=1, mean=[0.0], var=[1.0], lower=[-1.0], upper=[1.0],
                        ess=10.0, ess_ratio=0.5, resampled=True, degraded=False, observation=[0.0])
    def logged() -> bool:  # the log as far as it is written (the recorder flushes it every second)
        try:
            return any(m.topic == "dtpf/w-1/entity/estimate" for m in read_log(log).messages)
        except (OSError, LogError):  # not created, or nothing written yet
            return False

    deadline = time.monotonic() + 60
    while not logged():
        assert time.monotonic() < deadline and recorder.poll() is None, processes.output(recorder)
        publisher.put(encode(estimate))
        time.sleep(0.2)
    stopped = time.monotonic()
    recorder.send_signal(signal.SIGINT)
    assert recorder.wait(timeout=60) == 0, processes.output(recorder)
    assert time.monotonic() - stopped > EXIT_GRACE  # it waited past the watchdog's grace
    assert "stopped before w-1 said their run ended" in processes.output(recorder), processes.output(recorder)
    written = read_log(log)
    assert written.complete and written.problem is None
    assert any(m.topic == "dtpf/w-1/entity/estimate" for m in written.messages)


# --- a stalled router does not make a service drop its own queue ------------------------------------------------


def test_a_service_waits_longer_than_a_router_before_it_drops_a_blocked_link():
    from dtpf.shell.bus import SERVICE_WAIT_BEFORE_CLOSE, WAIT_BEFORE_CLOSE_KEY, ZENOH_WAIT_BEFORE_CLOSE

    def wait(config) -> int:
        return int(config.get_json(WAIT_BEFORE_CLOSE_KEY))

    assert SERVICE_WAIT_BEFORE_CLOSE > ZENOH_WAIT_BEFORE_CLOSE
    assert wait(zenoh_config(mode="client", connect=["tcp/127.0.0.1:7447"])) == SERVICE_WAIT_BEFORE_CLOSE
    assert wait(zenoh_config(mode="peer")) == SERVICE_WAIT_BEFORE_CLOSE
    assert wait(zenoh_config(mode="router", listen=["tcp/127.0.0.1:0"])) == ZENOH_WAIT_BEFORE_CLOSE
    assert wait(zenoh_config(mode="client", connect=["tcp/127.0.0.1:7447"],
                             cfg=[f"{WAIT_BEFORE_CLOSE_KEY}:2000000"])) == 2_000_000


def test_a_router_stalled_longer_than_zenohs_wait_loses_none_of_a_clients_blocked_messages(processes):
    """A router that reads nothing for 8 s (SIGSTOP), longer than Zenoh's 5 s wait before it closes a blocked
    link: the client publishing 30 MB meanwhile blocks and waits, and every message arrives once the router
    goes on. With Zenoh's default wait the client closes its link and drops what its queue held."""
    import signal

    port = free_port()
    router = processes.start("router", ["-m", "dtpf", "router", "--listen", f"tcp/127.0.0.1:{port}"])
    endpoint = [f"tcp/127.0.0.1:{port}"]
    deadline = time.monotonic() + 60
    while True:
        try:
            subscriber = open_session(zenoh_config(mode="client", connect=endpoint))
            break
        except BusError:
            assert time.monotonic() < deadline and router.poll() is None, processes.output(router)
            time.sleep(0.1)
    publisher = open_session(zenoh_config(mode="client", connect=endpoint))
    received: list[int] = []
    arrived = threading.Event()
    count = 300

    probes: list[int] = []

    def take(sample) -> None:
        index = int.from_bytes(sample.payload.to_bytes()[:4], "big")
        (received if index else probes).append(index)
        if len(received) == count:
            arrived.set()

    sink = subscriber.declare_subscriber("stall/test", take)
    put = publisher.declare_publisher("stall/test", congestion_control=zenoh.CongestionControl.BLOCK)
    body = bytes(100_000)
    try:
        # The route is there before the router stops: a put before the router has learnt of the subscriber
        # goes nowhere, so the probe is sent again until one arrives.
        deadline = time.monotonic() + 60
        while not probes:
            assert time.monotonic() < deadline, "no probe arrived"
            put.put((0).to_bytes(4, "big") + body)
            time.sleep(0.1)
        os.kill(router.pid, signal.SIGSTOP)
        stopped = time.monotonic()
        done = threading.Event()

        def publish() -> None:
            for i in range(1, count + 1):
                put.put(i.to_bytes(4, "big") + body)
            done.set()

        thread = threading.Thread(target=publish, daemon=True)
        thread.start()
        blocked = not done.wait(8.0)
        os.kill(router.pid, signal.SIGCONT)
        resumed = time.monotonic() - stopped
        assert done.wait(120), "the client's puts did not end after the router went on"
        arrived.wait(60)  # the last message, if it comes
        assert sorted(received) == list(range(1, count + 1)), (
            f"{count - len(set(received))} of {count} messages lost after a router stall of {resumed:.1f} s "
            f"(the puts {'blocked' if blocked else 'ended'} while the router was stopped)")
        assert blocked, "30 MB went out while the router was stopped: the test did not fill the link"

    finally:
        os.kill(router.pid, signal.SIGCONT)
        sink.undeclare()
        publisher.close()
        subscriber.close()
