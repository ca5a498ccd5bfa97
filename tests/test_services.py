"""The three layers as real processes over Zenoh on loopback, recorded to MCAP."""
from __future__ import annotations

import collections
import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from mcap.reader import make_reader

from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate, ParticleSet, ServiceState, Status
from dtpf.scripts import inprocess
from dtpf.scripts.launch import LaunchError, launch

from conftest import ROOT, service_args

PER_STEP_TOPICS = ("entity/particles", "information/preprocessed", "information/weight_state",
                   "system/ps", "entity/estimate")


def read_with_mcap_only(path):
    """Every message of an MCAP file decoded with only mcap, json, numpy and the schemas in the file."""
    decoded = collections.defaultdict(list)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.message_encoding == "json":
                decoded[channel.topic].append(json.loads(message.data))
            else:
                layout = json.loads(json.loads(schema.data)["$comment"])
                data = message.data
                assert data[:4] == layout["magic"].encode()
                size = int.from_bytes(data[8:12], "little")
                header = json.loads(data[12:12 + size])
                start = (12 + size + layout["alignment"] - 1) // layout["alignment"] * layout["alignment"]
                arrays = {a["name"]: np.frombuffer(data, layout["dtype"], count=int(np.prod(a["shape"])),
                                                   offset=start + a["offset"]).reshape(a["shape"])
                          for a in header["arrays"]}
                decoded[channel.topic].append({**header["fields"], **arrays})
    return decoded


def test_launch_records_every_step_and_reproduces_the_inprocess_run(tmp_path):
    config = RunConfig(particles=300, steps=25, seed=11, twin="t-launch")
    log = tmp_path / "run.mcap"
    result = launch(config, log_path=log, timeout=5.0)
    assert result.exit_codes == {"recorder": 0, "system": 0, "information": 0, "entity": 0}
    reference = inprocess.run(config)
    means = np.array([e.mean for e in sorted(result.estimates, key=lambda e: e.step)])
    np.testing.assert_array_equal(means, reference.means)  # number for number
    assert not any(e.degraded for e in result.estimates)

    decoded = read_with_mcap_only(log)
    for topic in PER_STEP_TOPICS:
        steps = [m["step"] for m in decoded[f"dtpf/t-launch/{topic}"]]
        assert sorted(steps) == list(range(1, 26)), topic
    particles = sorted(decoded["dtpf/t-launch/entity/particles"], key=lambda m: m["step"])
    np.testing.assert_array_equal(particles[0]["particles"], reference.steps[0].particles)
    estimates = sorted(decoded["dtpf/t-launch/entity/estimate"], key=lambda m: m["step"])
    np.testing.assert_array_equal([e["mean"] for e in estimates], reference.means)
    assert all(m["ps"] == 0.81 for m in decoded["dtpf/t-launch/system/ps"])


class _Arrivals:
    """Weight states that arrive at given times, for a TwinSystem whose poll is replaced by this one."""

    def __init__(self, system, arrivals: dict[int, float]):
        self.system, self.arrivals, self.waited = system, dict(arrivals), []

    def poll(self, now: float) -> None:
        for step, at in sorted(self.arrivals.items()):
            if at <= now:
                self.system.decided = max(self.system.decided, step)
                del self.arrivals[step]

    def wait(self, timeout: float) -> set:
        self.waited.append(timeout)
        due = min(self.arrivals.values(), default=float("inf"))
        time.sleep(max(0.0, min(timeout, due - time.monotonic())))
        return set()


@pytest.mark.parametrize("decided, arrivals, final", [
    (38, {39: 0.0, 40: 0.1}, 40),   # the last step's state comes 0.1 s after the stop: decided on
    (10, {11: 0.0, 12: 0.1}, 11),   # stopped mid-run: what arrived is answered, nothing waited for
    (38, {39: 0.0, 40: 5.0}, 39),   # the last state never comes in time: at most FINAL_WAIT seconds
])
def test_a_stopped_system_layer_decides_the_last_step_that_arrives_just_after_the_stop(decided, arrivals, final):
    from dtpf.system.service import FINAL_WAIT, TwinSystem
    system = TwinSystem.__new__(TwinSystem)
    system.steps, system.decided = 40, decided
    start = time.monotonic()
    stand_in = _Arrivals(system, {step: start + delay for step, delay in arrivals.items()})
    system.poll = stand_in.poll
    system.finish(stand_in)
    assert system.decided == final
    assert time.monotonic() - start < FINAL_WAIT + 0.5
    assert bool(stand_in.waited) == (decided == 38)


def wait_for_step(router, step, timeout, degraded=None):
    def seen(messages):
        return any(isinstance(m, Estimate) and m.step >= step and (degraded is None or m.degraded == degraded)
                   for m in messages)
    return router.collect(seen, timeout)


def test_launch_without_the_recorder_runs_the_split_alone(tmp_path):
    """record=False (the benchmarks' split alone): no recorder process, no log, the same numbers."""
    config = RunConfig(particles=200, steps=15, seed=5, twin="t-norecord")
    log = tmp_path / "run.mcap"
    result = launch(config, log_path=log, timeout=5.0, record=False, notify=lambda text: None)
    assert result.exit_codes == {"system": 0, "information": 0, "entity": 0}
    assert not log.exists()
    means = np.array([e.mean for e in sorted(result.estimates, key=lambda e: e.step)])
    np.testing.assert_array_equal(means, inprocess.run(config).means)


def test_entity_survives_the_information_layer_being_killed_and_restarted(processes, router, tmp_path):
    # 400 steps at 40 a second: about 9 s after the kill for the new information service to start and answer (with
    # 150, a loaded machine once took longer than the 3 s left, and preprocessing never came back in the run).
    total = 400
    run = ["--particles", "500", "--steps", str(total), "--twin", "t-kill", "--seed", "3"]
    log = tmp_path / "kill.mcap"
    processes.start("recorder", service_args("dtpf.scripts.record", router.endpoint, *run, "--output", str(log)))
    processes.start("system", service_args("dtpf.system.service", router.endpoint, *run))
    information = processes.start("information", service_args("dtpf.information.service", router.endpoint, *run))
    entity = processes.start("entity", service_args("dtpf.entity.service", router.endpoint, *run, "--rate", "40",
                                                    "--timeout", "0.5", "--wait-for", "recorder",
                                                    "--wait-for", "information", "--wait-for", "system"))
    assert wait_for_step(router, 20, timeout=60), processes.output(entity)
    information.kill()
    information.wait()
    assert wait_for_step(router, 1, timeout=30, degraded=True), "no degraded step after the kill"
    processes.start("information", service_args("dtpf.information.service", router.endpoint, *run))
    entity.wait(timeout=120)
    assert entity.returncode == 0, processes.output(entity)
    router.collect(lambda m: {e.step for e in m if isinstance(e, Estimate)} >= set(range(1, total + 1)), timeout=30)
    estimates = sorted((m for m in router.messages if isinstance(m, Estimate)), key=lambda e: e.step)
    assert [e.step for e in estimates] == list(range(1, total + 1))
    degraded = [e.step for e in estimates if e.degraded]
    assert degraded and degraded[0] > 20
    assert any(not e.degraded for e in estimates if e.step > degraded[-1]), "preprocessing never came back"
    assert all(not e.degraded for e in estimates if e.step < 20)

    for process in processes.started:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    for process in processes.started:
        process.wait(timeout=20)
    recorded = read_with_mcap_only(log)
    steps = sorted(m["step"] for m in recorded["dtpf/t-kill/entity/estimate"])
    assert steps == list(range(1, total + 1))  # the log holds every step the entity made
    assert sum(m["degraded"] for m in recorded["dtpf/t-kill/entity/estimate"]) == len(degraded)


GARBAGE = [
    b"",
    b"\x00\xff not a message",
    b'{"run_id": "run", "twin_id": "t-bad", "step": 1}',                       # JSON missing fields
    b'{"run_id": "run", "twin_id": "t-bad", "step": -5, "stamp": {"sec": 0, "nsec": 0}}',
    b"DTPF\x01\x00\x00\x00\xff\xff\xff\x00{",                                  # envelope, header past the end
]


def test_every_service_survives_garbage_and_counts_it(processes, router):
    import zenoh

    run = ["--particles", "200", "--steps", "60", "--twin", "t-bad"]
    processes.start("system", service_args("dtpf.system.service", router.endpoint, *run))
    processes.start("information", service_args("dtpf.information.service", router.endpoint, *run))
    entity = processes.start("entity", service_args("dtpf.entity.service", router.endpoint, *run, "--rate", "30",
                                                    "--wait-for", "information", "--wait-for", "system"))
    assert wait_for_step(router, 5, timeout=60), processes.output(entity)
    # A valid envelope cut in half: rejected, never half-decoded.
    truncated = bytearray(_valid_particle_set_payload())
    bad_keys = ["dtpf/t-bad/entity/particles", "dtpf/t-bad/system/ps", "dtpf/t-bad/information/weight_state",
                "dtpf/t-bad/information/preprocessed"]
    for key in bad_keys:
        publisher = router.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        for payload in [*GARBAGE, bytes(truncated[: len(truncated) // 2])]:
            publisher.put(payload)
        publisher.undeclare()
    entity.wait(timeout=120)
    assert entity.returncode == 0, processes.output(entity)
    for process in processes.started[:2]:
        assert process.poll() is None, f"{process.name} died: {processes.output(process)}"
        process.send_signal(signal.SIGINT)
        process.wait(timeout=20)
        assert process.returncode == 0, processes.output(process)
    # Every layer's final status (a fixed wait for them was too short on a loaded machine).
    router.collect(lambda m: {s.layer.value for s in m if isinstance(s, Status) and s.state == ServiceState.FINISHED}
                   >= {"entity", "information", "system"}, timeout=30)
    final = {}
    for m in router.messages:
        if isinstance(m, Status):
            final[m.layer.value] = m
    sent = len(GARBAGE) + 1
    assert final["entity"].rejected >= sent            # information/preprocessed
    assert final["information"].rejected >= 2 * sent   # entity/particles and system/ps
    assert final["system"].rejected >= sent            # information/weight_state
    estimates = [m for m in router.messages if isinstance(m, Estimate)]
    assert sorted(e.step for e in estimates) == list(range(1, 61))


def _valid_particle_set_payload() -> bytes:
    from dtpf.messages.codec import encode

    return encode(ParticleSet(run_id="run", twin_id="t-bad", step=7, layer="entity", kind="propagated",
                              particles=np.zeros((10, 1)), weights=np.full(10, 0.1)))


def test_sigint_to_the_launcher_stops_every_child_and_leaves_a_readable_log(processes, tmp_path):
    log = tmp_path / "interrupted.mcap"
    launcher = processes.start("launcher", ["-m", "dtpf.scripts.cli", "launch", "--steps", "1000", "--rate", "20",
                                            "--twin", "t-int", "-o", str(log), "--quiet"])
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 20_000):
        time.sleep(0.2)
    time.sleep(1.0)
    launcher.send_signal(signal.SIGINT)
    launcher.wait(timeout=60)
    assert launcher.returncode == 130, processes.output(launcher)
    decoded = read_with_mcap_only(log)
    pids = {m["pid"] for topic, ms in decoded.items() if topic.endswith("/status") for m in ms}
    assert len(pids) == 4, decoded.keys()
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    steps = [m["step"] for m in decoded["dtpf/t-int/entity/estimate"]]
    assert 5 < len(steps) < 1000 and sorted(steps) == list(range(1, len(steps) + 1))
    assert "steps" in processes.output(launcher) and "(interrupted)" in processes.output(launcher)
    # The printed summary and the log tell the same run: the last step had its answer, none degraded.
    output = processes.output(launcher)
    assert f"steps           {len(steps)} of 1000 (interrupted)" in output, output
    degraded = sum(m["degraded"] for m in decoded["dtpf/t-int/entity/estimate"])
    assert degraded == 0 and "degraded steps  0" in output, output


def test_sigint_stops_a_launch_started_with_sigint_ignored(tmp_path):
    """A script that starts ``dtpf launch &`` hands it SIGINT ignored (a non-interactive shell does so for
    background jobs, and Python then installs no handler); the launcher still stops on SIGINT."""
    launcher = subprocess.Popen([sys.executable, "-m", "dtpf.scripts.cli", "launch", "--steps", "1000", "--rate", "20",
                                 "--twin", "t-ign", "-o", str(tmp_path / "ignored.mcap"), "--quiet"],
                                cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        # Mid-run: the recorder has written steps (a fixed wait was either long or, loaded, too short).
        log = tmp_path / "ignored.mcap"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 20_000):
            time.sleep(0.2)
        assert launcher.poll() is None and log.stat().st_size >= 20_000, "the launch did not get going"
        launcher.send_signal(signal.SIGINT)
        output = launcher.communicate(timeout=60)[0].decode(errors="replace")
        assert launcher.returncode == 130, output
        assert "(interrupted)" in output
    finally:
        if launcher.poll() is None:
            os.killpg(launcher.pid, signal.SIGKILL)
            launcher.wait()


def test_launch_says_when_its_port_is_in_use(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(LaunchError, match="cannot start on tcp/127.0.0.1:%d.*already in use" % port):
            launch(RunConfig(steps=2), log_path=tmp_path / "x.mcap", port=port)
        completed = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "launch", "--port", str(port),
                                    "-o", str(tmp_path / "y.mcap")], cwd=ROOT, capture_output=True,
                                   text=True, timeout=60)
        router = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "router", "--listen",
                                 f"tcp/127.0.0.1:{port}"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 1
    # One line: the port is in use and how to pick another; Zenoh's reason without its Rust source paths.
    said = completed.stderr.strip().splitlines()[-1]
    assert said == (f"dtpf launch: error: embedded Zenoh router cannot start on tcp/127.0.0.1:{port}: the port is "
                    f"already in use by another program (Address already in use (os error 98)); give --port "
                    f"another port, or leave --port out for a free one, or stop the program that holds it"), said
    assert router.returncode == 2 and ".rs" not in router.stderr and "/src/" not in router.stderr, router.stderr
    assert router.stderr.strip() == (f"dtpf router: error: cannot listen on tcp/127.0.0.1:{port}: the port is already "
                                     f"in use by another program (Address already in use (os error 98)); give "
                                     f"--listen an endpoint with another port (tcp/HOST:PORT), or stop the program "
                                     f"that holds it"), router.stderr


@pytest.mark.parametrize("layer", ["entity", "information", "system", "recorder"])
def test_every_run_option_of_a_launch_reaches_its_services(layer, tmp_path):
    """A launched service parses the run configuration of the launch back from its command line, every field a
    run flag sets (a --jitter or --move-rule the command line left out ran the services without them)."""
    import importlib

    from dtpf.messages.config import _FLAG_FIELDS, RunConfig, config_from_args
    from dtpf.scripts.launch import MODULES, service_command

    defaults = RunConfig()
    configs = [
        RunConfig(scenario="drift", particles=321, steps=17, resampler="stratified", resample_below=0.5,
                  threshold="inverse-n", weight_rule="likelihood", move_rule="relative", jitter="roughening",
                  policy="rule", ps=0.5, ps_rate=0.125, seed=9, twin="t-flags", run_id="r-9"),
        RunConfig(policy="choose", choose_base="roughening", twin="t-flags-3"),
        RunConfig(model="docs/examples/range_bearing.py:RangeBearingTarget", observations="live", steps=None,
                  preprocess=False, jitter="regularised", twin="t-flags-2"),
        RunConfig(model="docs/examples/range_bearing.py:RangeBearingTarget", reader="csv", steps=None,
                  observations="docs/examples/range_bearing_no_truth.csv", twin="t-flags-4"),
        RunConfig(model="docs/examples/range_bearing.py:RangeBearingTarget", partial=True,
                  observations="docs/examples/range_bearing_no_truth.csv", twin="t-flags-5"),
        RunConfig(model="docs/examples/unicycle.py:Unicycle", sensor_files={"gps": "gps.csv", "beacons": "b.csv"},
                  controls="odometry.csv", reorder_window=0.25, steps=None, twin="t-flags-6"),
        RunConfig(model="docs/examples/unicycle.py:Unicycle", sensor_files={"gps": "run.mcap:/fix"},
                  sensor_fields={"gps": "latitude,longitude"}, controls="run.mcap:/cmd_vel",
                  control_fields="linear.x,angular.z", steps=10, twin="t-flags-7"),
    ]
    changed = {name for config in configs for name in _FLAG_FIELDS if getattr(config, name) != getattr(defaults, name)}
    assert set(_FLAG_FIELDS) - changed <= {"topic", "ros2_fields"}  # a ROS 2 topic's, tests/test_ros2_live.py
    parser = importlib.import_module(MODULES[layer]).build_parser()
    for config in configs:
        command = service_command(layer, config, "tcp/127.0.0.1:7447", timeout=5.0, log_path=tmp_path / "x.mcap",
                                  log_level="INFO")
        arguments = command[command.index(MODULES[layer]) + 1:]
        parsed = config_from_args(parser.parse_args(arguments))
        assert {name: getattr(parsed, name) for name in _FLAG_FIELDS} == \
            {name: getattr(config, name) for name in _FLAG_FIELDS}


def test_services_reject_bad_configuration_at_startup():
    completed = subprocess.run([sys.executable, "-m", "dtpf.information.service", "--resampler", "best"],
                               cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2
    assert "--resampler: unknown resampler 'best'; expected one of killing, multinomial," in completed.stderr
    completed = subprocess.run([sys.executable, "-m", "dtpf.system.service", "--ps", "1.5"],
                               cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2
    assert "--ps: Input should be less than or equal to 1" in completed.stderr


def test_recorder_that_cannot_write_its_log_says_so_and_exits_2(tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the log's folder should be")
    output = blocker / "run.mcap"
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.record", "--output", str(output),
                           "--listen", "tcp/127.0.0.1:0"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert f"cannot write the log {output}" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_signal_inside_interrupts_held_takes_effect_when_the_block_ends():
    """The launcher folds a message it took off its inbox before Ctrl-C stops it (else that estimate was lost
    and the next one counted as out of order)."""
    from dtpf.scripts.launch import interrupts_held

    folded = []
    # Python's own handler, as dtpf launch installs it: a test process started in the background of a
    # non-interactive shell has SIGINT ignored, and then an ignored signal rightly raises nothing.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with interrupts_held():
                signal.raise_signal(signal.SIGINT)  # to this thread: its handler runs here, now
                folded.append("after the signal")  # still runs: the signal waits for the block's end
        assert folded == ["after the signal"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is put back
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with interrupts_held():  # a signal ignored before the block stays ignored after it
            signal.raise_signal(signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_sigterm_inside_interrupts_held_runs_the_installed_handler_at_the_end():
    from dtpf.scripts.launch import interrupts_held

    seen = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: seen.append(signum))
    try:
        with interrupts_held():
            signal.raise_signal(signal.SIGTERM)
            assert seen == []
        assert seen == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, previous)
