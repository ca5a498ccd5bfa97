"""One information and one system service serve many twins, each learned from its entity.

Real processes on a free loopback port: entity services (one per twin, with
the twin's own flags) and one information and one system service started
with ``--twins 'f-*'`` and no run flags. Each twin's estimates must equal its
own in-process run, number for number.
"""
from __future__ import annotations

import signal
import time

import numpy as np
import pytest

from dtpf.messages.config import RunConfig
from dtpf.messages.keys import twins_chunk
from dtpf.messages.models import Estimate, ServiceState, Status
from dtpf.scripts import inprocess

from conftest import service_args

STEPS = 30


#: The lockstep waits of the tests whose twins must equal their solo runs. A shared service that learns a
#: twin of a new kind compiles its kernels in its one loop (seconds on a cold numba cache and a loaded
#: machine), and the twins it already serves wait meanwhile: the information layer's wait for a PS decision
#: (2 s by default) then runs out, the last PS is kept, and the twin's numbers leave its solo run's. The
#: entity waits longer than the information layer, which waits for the system layer. The other tests keep
#: the services' default and the entity's 10 s.
SHARED_TIMEOUT, ENTITY_TIMEOUT = 30.0, 60.0


def run_flags(config: RunConfig, timeout: float = 10.0) -> list[str]:
    return ["--twin", config.twin, "--seed", str(config.seed), "--particles", str(config.particles),
            "--steps", str(config.steps), "--policy", config.policy, "--ps", repr(config.ps),
            "--resampler", config.resampler, "--scenario", config.scenario, "--timeout", str(timeout)]


def start_shared(processes, router, pattern: str, timeout: float | None = None):
    flags = ["--timeout", str(timeout)] if timeout is not None else []
    return [processes.start(layer, service_args(f"{layer}.service", router.endpoint, "--twins", pattern, *flags))
            for layer in ("information", "system")]


def start_entity(processes, router, config: RunConfig, *extra: str, timeout: float = 10.0):
    return processes.start(config.twin, service_args("dtpf.entity.service", router.endpoint,
                                                     *run_flags(config, timeout), "--wait-for", "information",
                                                     "--wait-for", "system", *extra))


def warnings_of(processes, services, twin: str) -> str:
    """The shared services' warnings about ``twin`` (a wait that ran out, a layer seen gone), for a failure
    message."""
    lines = [line for service in services for line in processes.output(service).splitlines()
             if "WARNING" in line and f"twin {twin}:" in line]
    return "\n".join(lines[:20]) or f"(the shared services logged no warning about {twin})"


def estimates_by_twin(messages) -> dict[str, dict[int, Estimate]]:
    out: dict[str, dict[int, Estimate]] = {}
    for message in messages:
        if isinstance(message, Estimate):
            out.setdefault(message.twin_id, {})[message.step] = message
    return out


def test_one_information_and_one_system_service_serve_twenty_twins_as_their_solo_runs(processes, router, tmp_path):
    """20 twins of two models, different N, seeds, PS, policies and resamplers, in 10 entity processes of two
    twins each (an edge box hosts the twins of one configuration), one information and one system service;
    each twin equals its own in-process run, and the fleet's log verifies twin by twin."""
    from dtpf.recording.logfile import read_log
    from dtpf.scripts.logs.verify import decoded_by_topic, filtered_twins, verify_twin

    kinds = [("fixed", 0.81, "systematic", "ungm"), ("rule", 0.5, "stratified", "ungm-printed"),
             ("predictive", 0.9, "residual", "ungm"), ("fixed", 0.3, "multinomial", "ungm-printed"),
             ("rule", 0.81, "systematic", "ungm")]
    groups = [RunConfig(particles=100 + 20 * i, steps=STEPS, seed=20 + i, twin=f"f-{i}", policy=policy, ps=ps,
                        resampler=resampler, scenario=scenario)
              for i, (policy, ps, resampler, scenario) in enumerate(kinds * 2)]
    log = tmp_path / "fleet.mcap"
    recorder = processes.start("recorder", service_args("dtpf.scripts.record", router.endpoint, "--all-twins",
                                                        "--twin", "f-recorder", "-o", str(log)))
    shared = start_shared(processes, router, "f-*", SHARED_TIMEOUT)
    entities = [start_entity(processes, router, group, "--twins", f"{group.twin}-a,{group.twin}-b",
                             timeout=ENTITY_TIMEOUT) for group in groups]
    configs = [group.model_copy(update={"twin": f"{group.twin}-{side}"}) for group in groups for side in "ab"]
    assert len(configs) == 20
    done = router.collect(lambda ms: all(len(estimates_by_twin(ms).get(c.twin, {})) == STEPS for c in configs),
                          timeout=240)
    assert done, {c.twin: len(estimates_by_twin(router.messages).get(c.twin, {})) for c in configs}
    for entity in entities:
        assert entity.wait(timeout=30) == 0, processes.output(entity)
    got = estimates_by_twin(router.messages)
    for config in configs:
        reference = inprocess.run(config)
        steps = got[config.twin]
        assert not any(e.degraded for e in steps.values()), config.twin
        np.testing.assert_array_equal([steps[k].mean for k in range(1, STEPS + 1)], reference.means,
                                      err_msg=f"{config.twin}\n{warnings_of(processes, shared, config.twin)}")
    # Each finished twin is dropped by the shared services: their last status for it says finished.
    everyone = {(c.twin, layer) for c in configs for layer in ("information", "system")}
    router.collect(lambda ms: _finished_twins(ms) >= everyone, timeout=60)
    assert _finished_twins(router.messages) >= everyone
    for service in shared:
        assert service.poll() is None, processes.output(service)  # the services stay for the next twins
        service.send_signal(signal.SIGINT)
        assert service.wait(timeout=30) == 0
    recorder.send_signal(signal.SIGINT)
    assert recorder.wait(timeout=30) == 0, processes.output(recorder)
    by_topic = decoded_by_topic(read_log(log))
    assert filtered_twins(by_topic) == sorted(c.twin for c in configs)
    for config in configs:
        verification = verify_twin(by_topic, config.twin)
        assert verification.ok and verification.checked == list(range(1, STEPS + 1)), config.twin


def _finished_twins(messages) -> set[tuple[str, str]]:
    return {(m.twin_id, m.layer.value) for m in messages
            if isinstance(m, Status) and m.layer.value in ("information", "system") and m.state == ServiceState.FINISHED}


def test_a_killed_twin_leaves_the_others_whole_and_a_late_one_is_served(processes, router):
    victim = RunConfig(particles=200, steps=200, seed=3, twin="k-victim")
    steady = RunConfig(particles=200, steps=STEPS, seed=4, twin="k-steady")
    late = RunConfig(particles=200, steps=STEPS, seed=5, twin="k-late")
    shared = start_shared(processes, router, "k-*", SHARED_TIMEOUT)
    killed = start_entity(processes, router, victim, "--rate", "20", timeout=ENTITY_TIMEOUT)
    start_entity(processes, router, steady, "--rate", "20", timeout=ENTITY_TIMEOUT)
    assert router.collect(lambda ms: len(estimates_by_twin(ms).get("k-victim", {})) >= 5, timeout=90)
    killed.send_signal(signal.SIGKILL)
    killed.wait(timeout=30)
    # The shared services see the entity's token go and free the twin's state (their last status says so).
    assert router.collect(lambda ms: {("k-victim", "information"), ("k-victim", "system")} <= _finished_twins(ms),
                          timeout=20)  # under forget_after (30 s): the token's going must be what frees the twin
    start_entity(processes, router, late, timeout=ENTITY_TIMEOUT)
    assert router.collect(lambda ms: all(len(estimates_by_twin(ms).get(c.twin, {})) == STEPS
                                         for c in (steady, late)), timeout=120)
    got = estimates_by_twin(router.messages)
    for config in (steady, late):
        assert not any(e.degraded for e in got[config.twin].values()), config.twin
        np.testing.assert_array_equal([got[config.twin][k].mean for k in range(1, STEPS + 1)],
                                      inprocess.run(config).means,
                                      err_msg=f"{config.twin}\n{warnings_of(processes, shared, config.twin)}")


def test_a_fleet_drops_a_twin_whose_entity_came_and_went_between_two_looks():
    # An entity SIGKILLed while the shared service's loop was busy had never been seen alive
    # by a sweep, and its twin was kept until forget_after (30 s), past the test above's 20 s.
    from dtpf.shell.fleet import twin_gone
    assert twin_gone(seen={"entity"}, alive=set(), quiet=0.1, forget_after=30.0) == "its entity is gone"
    assert twin_gone(seen={"entity", "system"}, alive={"entity", "system"}, quiet=99.0, forget_after=30.0) is None
    assert twin_gone(seen=set(), alive=set(), quiet=5.0, forget_after=30.0) is None  # still starting
    assert twin_gone(seen=set(), alive=set(), quiet=31.0, forget_after=30.0) == "its entity was not heard for 30 s"


def test_presence_remembers_a_peer_that_came_and_went(router):
    from dtpf.shell.bus import Presence, open_session, zenoh_config
    watcher = open_session(zenoh_config(mode="client", connect=[router.endpoint]))
    peer = open_session(zenoh_config(mode="client", connect=[router.endpoint]))
    presence = Presence(watcher, "seen-1", "information", names=["entity", "information", "system"])
    try:
        token = peer.liveliness().declare_token("dtpf/seen-1/entity/alive")
        deadline = time.monotonic() + 10.0
        while "entity" not in presence.alive and time.monotonic() < deadline:
            time.sleep(0.01)
        assert presence.alive == presence.seen == {"entity"}
        token.undeclare()
        while "entity" in presence.alive and time.monotonic() < deadline:
            time.sleep(0.01)
        assert presence.alive == set() and presence.seen == {"entity"}
    finally:
        presence.close()
        watcher.close()
        peer.close()


def test_a_shared_service_loads_no_model_a_status_names_unless_allowed(processes, router):
    """A status from the bus must not make a shared service import code: a twin of --model REF is refused
    (its entity goes on with plain resampling) unless the service was started with --allow-model REF."""
    from conftest import ROOT

    reference = f"{ROOT / 'docs' / 'examples' / 'range_bearing.py'}:RangeBearingTarget"
    config = RunConfig(particles=100, steps=5, seed=1, twin="m-1", model=reference)
    start_shared(processes, router, "m-*")
    entity = start_entity(processes, router, config, "--model", reference, "--startup-timeout", "3")
    assert entity.wait(timeout=60) == 0, processes.output(entity)
    assert router.collect(lambda ms: len(estimates_by_twin(ms).get("m-1", {})) == 5, timeout=30)
    assert all(e.degraded for e in estimates_by_twin(router.messages)["m-1"].values())  # no answer came
    assert not [m for m in router.messages if isinstance(m, Status) and m.twin_id == "m-1"
                and m.layer.value in ("information", "system")]  # never served


@pytest.mark.parametrize("pattern, chunk", [("*", "*"), ("line-1-*", "line-1-$*"), ("a*b", "a$*b"), ("t-1", "t-1")])
def test_twin_patterns_become_zenoh_chunks(pattern, chunk):
    assert twins_chunk(pattern) == chunk


@pytest.mark.parametrize("pattern", ["", "a/b", "**", "a**", "$*", "x$y"])
def test_a_twin_pattern_that_is_not_one_chunk_is_refused(pattern):
    with pytest.raises(ValueError, match="twin pattern|'\\*\\*'"):
        twins_chunk(pattern)


def test_dtpf_launch_twins_runs_a_fleet_whose_log_verifies_twin_by_twin(tmp_path):
    from dtpf.recording.logfile import read_log
    from dtpf.scripts.fleet import launch_fleet
    from dtpf.scripts.logs.summary import format_summary, summarise
    from dtpf.scripts.logs.verify import decoded_by_topic, filtered_twins, verify_twin

    config = RunConfig(particles=200, steps=20, seed=6, twin="fl")
    result = launch_fleet(config, 4, log_path=tmp_path / "fleet.mcap", timeout=10.0)
    assert [t.twin for t in result.twins] == ["fl-1", "fl-2", "fl-3", "fl-4"]
    assert result.twin_steps == 80 and not result.failures
    assert result.exit_codes["information"] == 0 and result.exit_codes["system"] == 0
    references = {twin.twin: inprocess.run(twin) for twin in result.twins}
    for twin in result.twins:
        assert result.tallies[twin.twin].rmse == pytest.approx(references[twin.twin].rmse, rel=1e-12)
        assert result.tallies[twin.twin].degraded == 0
    text = result.summary()
    assert "fl-4" in text and "twin-steps      80 of 80" in text
    log = read_log(tmp_path / "fleet.mcap")
    by_topic = decoded_by_topic(log)
    assert filtered_twins(by_topic) == ["fl-1", "fl-2", "fl-3", "fl-4"]
    for twin in filtered_twins(by_topic):
        recorded = sorted(by_topic[f"dtpf/{twin}/entity/estimate"], key=lambda e: e.step)
        np.testing.assert_array_equal([e.mean for e in recorded], references[twin].means)  # number for number
        verification = verify_twin(by_topic, twin)
        assert verification.ok and verification.checked == list(range(1, 21)), twin
    summary = format_summary(summarise(log))
    assert summary.count("steps         20 of 20") == 4 and "recorder of the fleet" in summary


def test_entity_groups_split_the_twins_evenly_in_order():
    from dtpf.scripts.fleet import entity_groups

    twins = [f"t-{i}" for i in range(1, 8)]
    assert entity_groups(twins, 3) == [["t-1", "t-2", "t-3"], ["t-4", "t-5"], ["t-6", "t-7"]]
    assert entity_groups(twins[:1], 4) == [["t-1"]]
    assert sum(entity_groups(twins, 2), []) == twins


def test_an_entity_hosts_k_twins_or_a_list_and_refuses_repeats():
    from dtpf.entity.service import hosted_configs

    base = RunConfig(twin="edge", seed=3)
    assert [c.twin for c in hosted_configs(base, "3")] == ["edge-1", "edge-2", "edge-3"]
    assert [c.twin for c in hosted_configs(base, "a, b")] == ["a", "b"]
    assert {c.seed for c in hosted_configs(base, "2")} == {3}
    for bad in ("0", "a,a", ",", "bad/id"):
        with pytest.raises(ValueError):
            hosted_configs(base, bad)


def test_a_flooded_twin_is_counted_against_itself_and_slows_no_other(processes, router):
    import threading

    import zenoh

    from dtpf.messages.codec import MessageError, decode_for_key
    from dtpf.shell.bus import Inbox, open_session, zenoh_config

    calm = [RunConfig(particles=200, steps=STEPS, seed=7 + i, twin=f"z-calm-{i}") for i in range(2)]
    flooded = RunConfig(particles=200, steps=STEPS, seed=9, twin="z-flood")
    # The test's own view: estimates and statuses only (the router fixture's dtpf/** would fill with the flood).
    watch = Inbox(router.session, "dtpf/*/entity/estimate", "dtpf/*/*/status", max_items=100_000)
    seen = []

    def collect(until, timeout):
        deadline = time.monotonic() + timeout
        while not until(seen) and time.monotonic() < deadline:
            item = watch.get(timeout=0.1)
            if item is not None:
                try:
                    seen.append(decode_for_key(item.key, item.payload))
                except MessageError:
                    pass
        return until(seen)

    start_shared(processes, router, "z-*")
    for config in (*calm, flooded):
        start_entity(processes, router, config, "--rate", "15")
    assert collect(lambda ms: all(len(estimates_by_twin(ms).get(c.twin, {})) >= 3 for c in (*calm, flooded)), 90)
    session = open_session(zenoh_config(mode="client", connect=[router.endpoint]))
    sent = 0
    stop = threading.Event()

    def flood():  # garbage on every key the shared services take for this twin, thousands a second
        nonlocal sent
        publishers = [session.declare_publisher(f"dtpf/z-flood/{key}", congestion_control=zenoh.CongestionControl.BLOCK)
                      for key in ("entity/particles", "information/weight_state", "system/ps",
                                  "information/preprocessed")]
        while not stop.is_set():
            for publisher in publishers:
                publisher.put(b"\x00garbage" * (1 + sent % 50))
                sent += 1
            if sent % 400 == 0:
                time.sleep(0.01)

    flooder = threading.Thread(target=flood)
    flooder.start()
    try:
        assert collect(lambda ms: all(len(estimates_by_twin(ms).get(c.twin, {})) == STEPS for c in calm), 120)
    finally:
        stop.set()
        flooder.join()
        session.close()
    # The statuses after the flood: each twin's last, said by the shared services when its entity has gone
    # (a running fleet twin's status comes only every 5 s, so no fixed wait would do on a loaded machine).
    everyone = {(c.twin, layer) for c in (*calm, flooded) for layer in ("information", "system")}
    assert collect(lambda ms: _finished_twins(ms) >= everyone, 120), everyone - _finished_twins(seen)
    watch.close()
    assert sent >= 5_000
    got = estimates_by_twin(seen)
    for config in calm:  # every step, none degraded, the numbers of the solo run
        assert not any(e.degraded for e in got[config.twin].values()), config.twin
        np.testing.assert_array_equal([got[config.twin][k].mean for k in range(1, STEPS + 1)],
                                      inprocess.run(config).means, err_msg=config.twin)
    last = {}
    for m in seen:
        if isinstance(m, Status) and m.layer.value in ("information", "system"):
            last[m.twin_id, m.layer.value] = m
    assert last["z-flood", "information"].rejected > 0 and last["z-flood", "system"].rejected > 0
    assert all(last[c.twin, layer].rejected == 0 for c in calm for layer in ("information", "system"))


def _descends_from(pid: int, ancestor: int) -> bool:
    """Whether process ``pid`` is ``ancestor`` or one of its descendants (its parents read from /proc)."""
    while pid > 1:
        if pid == ancestor:
            return True
        try:
            with open(f"/proc/{pid}/stat", "rb") as handle:
                stat = handle.read()
        except OSError:
            return False
        pid = int(stat.rsplit(b")", 1)[1].split()[1])  # the field after the state: the parent's pid
    return False


def _fleet_with_a_kill(tmp_path, twin: str, seed: int, *marks: bytes):
    """A fleet of 3 twins (N = 200, T = 150, 40 steps/s) whose process with ``marks`` in its command line
    is SIGKILLed 60 twin-steps in: (the launch's result, what the launcher said)."""
    import os
    import threading

    from dtpf.scripts.fleet import launch_fleet

    config = RunConfig(particles=200, steps=150, seed=seed, twin=twin)
    said: list[str] = []
    outcome: dict = {}
    stepping = threading.Event()

    def run():
        outcome["result"] = launch_fleet(config, 3, log_path=tmp_path / "fleet.mcap", timeout=1.0, rate=40.0,
                                         notify=said.append, progress=lambda done, total: done >= 60 and stepping.set())

    launcher = threading.Thread(target=run, daemon=True)  # a failed test must not wait on it at exit
    launcher.start()
    assert stepping.wait(timeout=90)
    killed = None
    for pid in os.listdir("/proc"):
        try:
            command = open(f"/proc/{pid}/cmdline", "rb").read()
        except OSError:
            continue
        # Only a child of this test's launcher: another suite on the machine may run the same fleet.
        if all(mark in command for mark in marks) and _descends_from(int(pid), os.getpid()):
            os.kill(int(pid), signal.SIGKILL)
            killed = int(pid)
            break
    launcher.join(timeout=120)
    assert killed is not None and not launcher.is_alive()
    return outcome["result"], said


def test_a_fleet_launch_restarts_a_killed_shared_service_and_every_twin_finishes(tmp_path):
    result, said = _fleet_with_a_kill(tmp_path, "fr", 8, b"dtpf.information.service", b"fr-*", b"--twins")
    assert not result.failures
    assert result.twin_steps == 3 * 150  # every twin, every step
    assert said and "the shared information service died (killed by SIGKILL)" in said[0]
    assert "started again" in result.summary()
    degraded = sum(t.degraded for t in result.tallies.values())
    assert 0 < degraded < 3 * 150  # plain resampling while it was gone, preprocessing again after


def test_a_fleet_launch_restarts_a_killed_recorder_and_the_segments_hold_every_twin(tmp_path):
    """SIGKILL of the fleet's recorder 60 twin-steps in: the launcher records the fleet's keys until a new
    recorder listens, which writes the next segment; the joined segments verify twin by twin, and each
    twin's estimates are missing at most for the recorder's 1 s flush interval (40 steps at 40 steps/s)."""
    from dtpf.recording.logfile import read_logs
    from dtpf.scripts.logs.verify import decoded_by_topic, verify_twin

    result, said = _fleet_with_a_kill(tmp_path, "fk", 9, b"dtpf.scripts.record", b"--all-twins", b"fk")
    assert not result.failures
    assert result.twin_steps == 3 * 150
    assert said and "the shared recorder service died (killed by SIGKILL)" in said[0]
    assert [p.name for p in result.segments] == ["fleet.mcap", "fleet.1.mcap", "fleet.2.mcap"]
    assert " + " in result.summary()
    by_topic = decoded_by_topic(read_logs(result.segments))
    for twin in (t.twin for t in result.twins):
        estimates = {m.step for m in by_topic.get(f"dtpf/{twin}/entity/estimate", [])}
        assert len(estimates) >= 150 - 45, twin
        assert max(estimates) == 150  # the new recorder wrote the end
        verification = verify_twin(by_topic, twin)
        assert verification.ok, (twin, str(verification.mismatch))


def test_a_live_fleet_follows_one_sensor_per_twin_as_their_solo_runs(processes, tmp_path):
    """dtpf launch --twins 2 --observations live: each twin waits for its own sensor and ends with its
    stream; the estimates are those of the twin's dtpf run (the sensor simulates the same path)."""
    import threading

    from dtpf.scripts.fleet import launch_fleet
    from dtpf.shell.bus import free_port

    port = free_port()
    config = RunConfig(particles=200, steps=None, seed=6, twin="fl", observations="live")
    outcome: dict = {}

    def run():
        outcome["result"] = launch_fleet(config, 2, log_path=tmp_path / "live.mcap", port=port, timeout=2.0,
                                         keep_estimates=True)

    launcher = threading.Thread(target=run, daemon=True)  # a failed test must not wait on it at exit
    launcher.start()
    sensors = [processes.start(f"sensor-{i}", ["-m", "dtpf.scripts.sensor", "--connect", f"tcp/127.0.0.1:{port}",
                                               "--twin", f"fl-{i}", "--particles", "200", "--seed", "6",
                                               "--steps", str(20 + 10 * i), "--rate", "40"])
               for i in (1, 2)]
    for sensor in sensors:
        assert sensor.wait(timeout=90) == 0, processes.output(sensor)
    launcher.join(timeout=90)
    assert not launcher.is_alive(), "the live fleet did not end with its sensors' streams"
    result = outcome["result"]
    assert not result.failures and result.twin_steps == 30 + 40
    for i in (1, 2):
        tally = result.tallies[f"fl-{i}"]
        reference = inprocess.run(RunConfig(particles=200, steps=20 + 10 * i, seed=6, twin=f"fl-{i}"))
        np.testing.assert_array_equal([e.mean for e in tally.estimates], reference.means)
        assert tally.degraded == 0
    assert "(live)" in result.summary()


def test_the_fleet_benchmark_counts_cpu_between_two_instants_by_kind():
    # CPU per twin-step in dtpf.scripts.bench.fleet: each process's samples interpolated at the fleet's first and
    # last estimate, summed by kind; a process that ended in the window counts to its last sample.
    import os

    from dtpf.scripts.bench.fleet import RssSampler, _descendants
    sampler = RssSampler()
    sampler.cpu = {1: ("entity", [(10.0, 1.0), (11.0, 1.5), (12.0, 2.5)]),
                   2: ("entity", [(10.0, 0.0), (10.5, 0.2)]),  # ended at 10.5
                   3: ("recorder", [(9.0, 3.0), (13.0, 7.0)])}
    got = sampler.cpu_between(10.5, 11.5)
    assert got["entity"] == pytest.approx((2.0 - 1.25) + 0.0)
    assert got["recorder"] == pytest.approx(1.0)
    me = {pid: rest for pid, *rest in _descendants(os.getpid())}[os.getpid()]
    assert me[2] > 0  # this process's own CPU seconds, from /proc


def test_the_fleet_benchmark_counts_a_process_sampled_before_its_exec_under_its_layer():
    # subprocess forks, then execs the layer: a sample in between shows the bench's own command line.
    from dtpf.scripts.bench.fleet import RssSampler
    sampler = RssSampler()
    sampler.record(10.0, [(7, "launcher-ish", 900, 50.0), (8, "other", 500 << 20, 0.0)], me=7)
    sampler.record(11.0, [(7, "launcher-ish", 900, 51.0), (8, "information", 200 << 20, 0.6)], me=7)
    sampler.record(12.0, [(7, "launcher-ish", 900, 52.0), (8, "information", 250 << 20, 1.4)], me=7)
    sampler.record(13.0, [(7, "launcher-ish", 900, 53.0), (8, "other", 10 << 20, 2.0)], me=7)  # unreadable
    got = sampler.cpu_between(10.0, 13.0)
    assert got == pytest.approx({"launcher": 3.0, "information": 2.0})
    assert sampler.by_kind() == {"information": [250 << 20]}  # not the fork's 500 MB of the parent


def test_a_fleet_twin_says_its_status_every_second_while_it_starts_and_every_five_once_it_runs():
    # A K = 100 fleet published about 0.76 statuses per twin-step at one a second; a starting twin's status
    # is how the shared services learn it, so that one keeps its pace.
    from dtpf.shell.bus import open_session, zenoh_config
    from dtpf.shell.service import FLEET_STATUS_INTERVAL, STATUS_INTERVAL, ServiceShell

    session = open_session(zenoh_config(mode="peer", listen=["tcp/127.0.0.1:0"]))
    try:
        shell = ServiceShell("information", RunConfig(twin="cadence-1", run_id="run"), session=session)
        said = []
        shell.publish_status = lambda: said.append(shell.state)
        start = time.monotonic()
        ticks = [start + STATUS_INTERVAL * i / 4 for i in range(1, 4 * 3 + 1)]  # 3 s, four ticks a second
        for now in ticks:
            shell.tick(now)
        assert said == [ServiceState.STARTING] * 3
        shell.state = ServiceState.RUNNING
        said.clear()
        for i in range(1, 4 * 10 + 1):  # ten seconds
            shell.tick(ticks[-1] + i / 4)
        assert said == [ServiceState.RUNNING] * 2 and FLEET_STATUS_INTERVAL == 5.0
        shell.presence.close()
    finally:
        session.close()


def test_a_shared_service_says_which_twin_each_of_its_lines_is_about(caplog):
    # A fleet's information service serves twenty twins in one process; "step 3: no PS decision" alone
    # does not say whose step 3 it was.
    import logging

    from dtpf.shell.bus import open_session, zenoh_config
    from dtpf.shell.service import ServiceShell

    session = open_session(zenoh_config(mode="peer", listen=["tcp/127.0.0.1:0"]))
    try:
        shells = [ServiceShell("information", RunConfig(twin=twin, run_id="run"), session=session)
                  for twin in ("line-a", "line-b")]
        with caplog.at_level(logging.INFO, logger="dtpf.information"):
            for shell in shells:
                shell.log.warning("step %d: no PS decision of step %d within %.1f s", 3, 2, 2.0)
        assert [r.getMessage() for r in caplog.records if r.name == "dtpf.information"] == [
            "twin line-a: step 3: no PS decision of step 2 within 2.0 s",
            "twin line-b: step 3: no PS decision of step 2 within 2.0 s"]
        for shell in shells:
            shell.presence.close()
    finally:
        session.close()
