"""Large particle sets between the processes of a host go through shared-memory slots, and nothing changes.

The slots (dtpf.shell.slots) against hostile references, a slow reader and a killed writer; the bus
(dtpf.shell.shared_sets through dtpf.shell.bus.Inbox) with a reference it cannot read; a launch whose sets
go by reference gives exactly the numbers of one whose sets go as bytes, and verifies; and a subscriber on
another host (a network namespace) gets every set's bytes from its publisher.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from dtpf.recording.logfile import read_log
from dtpf.shell import slots
from dtpf.shell.bus import Inbox, free_port, open_session, publisher, zenoh_config
from dtpf.shell.shared_sets import SetPublisher
from dtpf.shell.slots import Reference, SlotError, SlotMiss, SlotReader, SlotWriter

from test_components import dtpf
from test_partition import Host, _wait_listening, _wait_said, two_hosts  # noqa: F401  (a fixture)

pytestmark = pytest.mark.skipif(slots.shm_folder() is None, reason="no /dev/shm on this system")


def _arrays(seed: int, n: int = 50_000) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 2)), rng.random(n)


def test_a_payload_written_in_parts_is_read_back_byte_for_byte_and_read_only():
    writer, reader = SlotWriter(slots=4), SlotReader()
    try:
        for seed in range(9):  # more payloads than slots: the ring wraps
            particles, weights = _arrays(seed)
            reference = Reference.parse(writer.write([b"head%04d" % seed, particles, weights]))
            held = reader.resolve(reference)
            expected = b"head%04d" % seed + particles.tobytes() + weights.tobytes()
            assert held.view.readonly and held.view.nbytes == len(expected)
            assert held.view.tobytes() == expected
            reader.release(held)
    finally:
        reader.close()
        writer.close()
    assert not os.path.exists(os.path.join(slots.shm_folder(), reference.file))


def test_a_writer_waits_for_a_reader_that_holds_a_slot_and_drops_it_only_after_its_wait():
    writer, reader = SlotWriter(slots=2, wait=0.3), SlotReader()
    try:
        first = reader.resolve(Reference.parse(writer.write([b"one"])))
        writer.write([b"two"])  # the other slot
        # The third payload goes into the first's slot, which the reader still holds: the writer waits for it
        # until its wait runs out, then drops the reader, whose view no longer holds its payload.
        third = Reference.parse(writer.write([b"three"]))
        assert writer.dropped_readers == 1 and not reader.still_valid(first)
        # The dropped reader takes an entry again and reads what comes next.
        held = reader.resolve(third)
        assert held.view.tobytes() == b"three"
        reader.release(held)

        released = threading.Event()
        held = reader.resolve(Reference.parse(writer.write([b"four"])))
        writer.wait = 60.0

        def release_soon():
            released.set()
            reader.release(held)

        threading.Timer(0.05, release_soon).start()
        writer.write([b"five"])
        writer.write([b"six"])  # into four's slot: only once the reader let go of it
        assert released.is_set() and writer.dropped_readers == 1
    finally:
        reader.close()
        writer.close()


def test_a_reader_that_is_gone_does_not_hold_a_writer_up(tmp_path):
    writer = SlotWriter(slots=1, wait=60.0)
    try:
        reference = writer.write([b"held by a process that dies"])
        code = ("import sys; from dtpf.shell.slots import Reference, SlotReader; r = SlotReader(); "
                "h = r.resolve(Reference.parse(bytes.fromhex(sys.argv[1]))); print('held', flush=True); "
                "sys.stdin.read()")
        child = subprocess.Popen([sys.executable, "-c", code, reference.hex()], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, text=True)
        try:
            assert child.stdout.readline().strip() == "held"
        finally:
            child.kill()
            child.wait()
        writer.write([b"next"])  # would wait 60 s for a live reader
        assert writer.dropped_readers == 1
    finally:
        writer.close()


def test_the_slot_files_of_a_killed_writer_are_removed_by_the_next_writer():
    code = ("from dtpf.shell.slots import SlotWriter, Reference; import sys; w = SlotWriter(); "
            "print(Reference.parse(w.write([b'x' * 1000])).file, flush=True); sys.stdin.read()")
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        name = child.stdout.readline().strip()
        assert os.path.exists(os.path.join(slots.shm_folder(), name))
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
    writer = SlotWriter()
    try:
        writer.write([b"y"])
        assert not os.path.exists(os.path.join(slots.shm_folder(), name))
    finally:
        writer.close()


@pytest.mark.parametrize("payload, reason", [
    (b"DTPFREF\x01not json", "not JSON"),
    (b"DTPFREF\x01[1, 2]", "exactly"),
    (b"DTPFREF\x01" + b" " * 2000, "not a slot reference"),
    (b'DTPFREF\x01{"host":"h","file":"../../etc/passwd","slot":0,"seq":1,"length":1,"writer":"ab"}', "not a slot file"),
    (b'DTPFREF\x01{"host":"h","file":"dtpf-' + b"0" * 32 + b'","slot":-1,"seq":1,"length":1,"writer":"ab"}', "out of range"),
    (b'DTPFREF\x01{"host":"h","file":"dtpf-' + b"0" * 32 + b'","slot":0,"seq":1,"length":1e99,"writer":"ab"}', "integer"),
    (b'DTPFREF\x01{"host":"h","file":"dtpf-' + b"0" * 32 + b'","slot":0,"seq":1,"length":99999999999,"writer":"ab"}', "out of range"),
])
def test_a_malformed_reference_is_refused_naming_what_is_wrong(payload, reason):
    with pytest.raises(SlotError, match=reason):
        Reference.parse(payload)


def test_a_reference_to_a_file_that_is_no_slot_file_or_to_a_slot_beyond_its_file_is_refused():
    reader, writer = SlotReader(), SlotWriter(slots=2)
    fake = os.path.join(slots.shm_folder(), "dtpf-" + "ab" * 16)
    try:
        with open(fake, "wb") as file:
            file.write(b"\xff" * 8192)
        with pytest.raises(SlotError, match="header"):
            reader.resolve(Reference(slots.host_id(), os.path.basename(fake), 0, 1, 10, "ab"))
        with pytest.raises(SlotError, match="cannot open"):
            reader.resolve(Reference(slots.host_id(), "dtpf-" + "cd" * 16, 0, 1, 10, "ab"))
        real = Reference.parse(writer.write([b"real"]))
        with pytest.raises(SlotError, match="beyond its file"):
            reader.resolve(Reference(real.host, real.file, 5, real.seq, real.length, real.writer))
        with pytest.raises(SlotMiss, match="no longer holds"):
            reader.resolve(Reference(real.host, real.file, real.slot, real.seq + 2, real.length, real.writer))
    finally:
        os.unlink(fake)
        reader.close()
        writer.close()


@pytest.fixture
def bus():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    sessions = [open_session(zenoh_config(mode="client", connect=[endpoint])) for _ in range(2)]
    try:
        yield sessions
    finally:
        for session in (*sessions, router):
            session.close()


def _until_heard(plain, inbox: Inbox, timeout: float = 60.0) -> None:
    """Put a probe until the inbox has it: its subscription has reached the router, and what follows is
    heard (a put before that is lost)."""
    deadline = time.monotonic() + timeout
    while True:
        plain.put(b"probe")
        item = inbox.get(timeout=0.2)
        if item is not None:
            assert bytes(item.payload) == b"probe"
            while inbox.get(timeout=0.2) is not None:  # the probes that were still on their way
                pass
            return
        assert time.monotonic() < deadline, "the inbox never heard the publisher"


def test_an_inbox_survives_references_it_cannot_read_and_takes_the_sets_that_follow(bus):
    sending, receiving = bus
    key = "dtpf/shared-1/entity/particles"
    drops = []
    inbox = Inbox(receiving, key, on_drop=lambda key, reason, detail: drops.append(detail), views=True)
    plain = publisher(sending, key)
    sets = SetPublisher(sending, key, plain)
    try:
        _until_heard(plain, inbox)
        fake = Reference(slots.host_id(), "dtpf-" + "ef" * 16, 0, 1, 100, "abcd").encode()
        plain.put(b"DTPFREF\x01{oops")
        plain.put(fake)
        particles, weights = _arrays(3)
        sets.put_parts([b"HEADER!!", particles, weights], 8 + particles.nbytes + weights.nbytes)
        item = inbox.get(timeout=30)
        assert item is not None and isinstance(item.payload, memoryview)
        assert np.array_equal(np.frombuffer(item.payload[8:8 + particles.nbytes]).reshape(particles.shape), particles)
        assert len(drops) == 2 and "not JSON" in drops[0] and "cannot open" in drops[1]
        assert inbox.dropped == 2
    finally:
        inbox.close()
        sets.undeclare(drain=0)


def _wait_for(condition, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"gave up waiting for {what}"
        time.sleep(0.01)


def _publish_sets(sets: SetPublisher, count: int) -> list[bytes]:
    payloads = []
    for seed in range(count):
        particles, weights = _arrays(seed)
        parts = [b"SET%05d" % seed, particles, weights]
        payloads.append(b"".join(bytes(memoryview(part)) for part in parts))
        sets.put_parts(parts, len(payloads[-1]))
    return payloads


def test_a_reader_that_takes_none_of_its_sets_holds_its_writer_up_by_none_and_drops_what_finds_no_room(bus):
    """Sets that wait in an inbox are copied out of their slots as the next arrives (three fit in its
    bytes here), the rest dropped and counted: the writer goes on through its ring of four, waiting for
    no reader (it would drop one that held it up for 20 s), and the newest set is still read in place."""
    sending, receiving = bus
    key = "dtpf/stuck-1/entity/particles"
    length = 8 + _arrays(0)[0].nbytes + _arrays(0)[1].nbytes
    drops = []
    inbox = Inbox(receiving, key, max_bytes=int(3.5 * length), views=True,
                  on_drop=lambda key, reason, detail: drops.append(reason))
    sets = SetPublisher(sending, key, publisher(sending, key))
    sets.writer = SlotWriter(slots=4, wait=20.0)
    try:
        _until_heard(sets.publisher, inbox)
        payloads = _publish_sets(sets, 12)
        _wait_for(lambda: len(inbox) >= 12, "12 sets to arrive")
        assert sets.writer.dropped_readers == 0
        got = []
        while (item := inbox.get(timeout=0)) is not None:
            got.append((bytes(item.payload[:8]), isinstance(item.payload, memoryview)))
            assert item.payload.tobytes() == payloads[int(got[-1][0][3:])]
        assert [name for name, _ in got] == [b"SET%05d" % seed for seed in (0, 1, 2, 11)]
        assert inbox.dropped == 8 and drops == ["inbox full"] * 8
    finally:
        inbox.close()
        sets.undeclare(drain=0)


def test_the_newest_set_of_each_publisher_waits_in_its_slot_and_the_one_before_is_copied_out(bus):
    """Two publishers' sets interleaved (a step's particles and its preprocessed set): each one's newest
    waits in its slot, read in place; the one before it is copied out when its publisher's next arrives."""
    sending, receiving = bus
    keys = ["dtpf/two-1/entity/particles", "dtpf/two-1/information/preprocessed"]
    inbox = Inbox(receiving, "dtpf/two-1/**", views=True)
    sets = [SetPublisher(sending, key, publisher(sending, key)) for key in keys]
    length = 8 + _arrays(0)[0].nbytes + _arrays(0)[1].nbytes
    try:
        for publisher_of_key in sets:
            _until_heard(publisher_of_key.publisher, inbox)
        for count, copied in ((1, 0), (2, 2 * length)):
            for publisher_of_key in sets:
                _publish_sets(publisher_of_key, 1)
            _wait_for(lambda: len(inbox) >= 2 * count, f"{2 * count} sets to arrive")
            assert inbox._sets.copied_bytes == copied
        got = [inbox.get(timeout=0) for _ in range(4)]
        assert [type(item.payload) for item in got] == [memoryview] * 4
        assert [item.key for item in got] == keys * 2
        assert inbox._sets.copied_bytes == 0
    finally:
        inbox.close()
        for publisher_of_key in sets:
            publisher_of_key.undeclare(drain=0)


def test_a_reference_received_twice_is_counted_once_by_an_inbox_that_copies_it_out(bus):
    """The same reference put twice (a replayed sample) and copied out when the next set arrives: the inbox
    counts its bytes once, and has counted nothing once every item is taken."""
    sending, receiving = bus
    key = "dtpf/twice-1/entity/particles"
    inbox = Inbox(receiving, key, views=True)
    plain = publisher(sending, key)
    sets = SetPublisher(sending, key, plain)
    sets.writer = SlotWriter(slots=4)
    try:
        _until_heard(plain, inbox)
        particles, weights = _arrays(1)
        reference = sets.writer.write([b"SET00001", particles, weights])
        plain.put(reference)
        plain.put(reference)
        _wait_for(lambda: len(inbox) >= 2, "the reference twice")
        _publish_sets(sets, 1)
        _wait_for(lambda: len(inbox) >= 3, "the next set")
        assert inbox._sets.copied_bytes == 8 + particles.nbytes + weights.nbytes
        while inbox.get(timeout=0) is not None:
            pass
        assert inbox._sets.copied_bytes == 0
    finally:
        inbox.close()
        sets.undeclare(drain=0)


def test_a_recorders_inbox_keeps_the_sets_it_has_no_room_for_in_their_slots_and_its_writer_waits(bus):
    """With back pressure, sets beyond the inbox's room stay in their slots: the writer, through its ring
    of four, waits for the reader and, after its wait (2 s here), drops it; nothing is dropped unread."""
    sending, receiving = bus
    key = "dtpf/stuck-2/entity/particles"
    length = 8 + _arrays(0)[0].nbytes + _arrays(0)[1].nbytes
    inbox = Inbox(receiving, key, max_bytes=int(1.5 * length), views=True, back_pressure=True)
    sets = SetPublisher(sending, key, publisher(sending, key))
    sets.writer = SlotWriter(slots=4, wait=2.0)
    try:
        _until_heard(sets.publisher, inbox)
        _publish_sets(sets, 4)  # the first copied out (room for one), the others kept in their slots
        _wait_for(lambda: len(inbox) >= 4, "4 sets to arrive")
        assert sets.writer.dropped_readers == 0
        _publish_sets(sets, 2)  # the fifth into the first's slot, the sixth waits for the second's
        _wait_for(lambda: len(inbox) >= 6, "6 sets to arrive")
        assert sets.writer.dropped_readers == 1 and inbox.dropped == 0
    finally:
        inbox.close()
        sets.undeclare(drain=0)


def test_a_launch_whose_sets_go_by_reference_gives_the_numbers_of_one_whose_sets_go_as_bytes(tmp_path):
    args = ("launch", "-q", "-n", "20000", "-T", "12", "--seed", "5")
    with ThreadPoolExecutor(2) as pool:  # side by side, each on a free port of its own
        shared_run = pool.submit(dtpf, *args, "-o", "shared.mcap", cwd=tmp_path)
        bytes_run = pool.submit(dtpf, *args, "-o", "bytes.mcap", cwd=tmp_path, env={"DTPF_SHARED_SETS": "0"})
        by_reference, as_bytes = shared_run.result(), bytes_run.result()
    assert by_reference.returncode == 0, by_reference.stderr[-3000:]
    assert as_bytes.returncode == 0, as_bytes.stderr[-3000:]
    shared, plain = read_log(tmp_path / "shared.mcap"), read_log(tmp_path / "bytes.mcap")
    sets = [record for record in shared.messages if record.topic.endswith("entity/particles")]
    assert len(sets) == 12 and all(len(record.data) > 256 << 10 for record in sets)  # sets of the size shared
    for topic in ("entity/particles", "information/preprocessed", "information/weight_state", "entity/estimate"):
        ours = [_without_stamp(r.data) for r in shared.messages if r.topic.endswith(topic)]
        theirs = [_without_stamp(r.data) for r in plain.messages if r.topic.endswith(topic)]
        assert len(ours) == 12 and ours == theirs, topic
    verified = dtpf("verify", "shared.mcap", cwd=tmp_path)
    assert verified.returncode == 0, verified.stdout[-3000:] + verified.stderr[-3000:]


def _without_stamp(payload: bytes) -> bytes:
    """A message's bytes without the fields that differ between two runs of the same numbers (times)."""
    from dtpf.messages.codec import decode
    message = decode(payload)
    fields = message.model_dump(exclude={"stamp", "run_id", "elapsed_s", "t_wall"}, exclude_none=True)
    return json.dumps({k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in fields.items()},
                      sort_keys=True, default=str).encode()


PUBLISH = """
import os, sys, time, numpy as np
from dtpf.shell.bus import open_session, publisher, zenoh_config
from dtpf.shell.shared_sets import SetPublisher
session = open_session(zenoh_config(mode="router", listen=[sys.argv[1]]))
key = "dtpf/far-1/entity/particles"
sets = SetPublisher(session, key, publisher(session, key))
while not os.path.exists(sys.argv[2]):  # until the subscribers listen
    time.sleep(0.05)
for step in range(1, 21):
    values = np.full(40_000, float(step))
    sets.put_parts([step.to_bytes(8, "little"), values], 8 + values.nbytes)
    time.sleep(0.02)
print("sent", flush=True)
time.sleep(600)
"""

SUBSCRIBE = """
import sys, numpy as np
from dtpf.shell.bus import Inbox, open_session, zenoh_config
session = open_session(zenoh_config(mode="client", connect=[sys.argv[1]]))
inbox = Inbox(session, "dtpf/far-1/entity/particles", on_drop=lambda *a: print("dropped", a, flush=True))
print("listening", flush=True)
got = []
while len(got) < 20:
    item = inbox.get(timeout=120)
    if item is None:
        break
    step = int.from_bytes(bytes(item.payload[:8]), "little")
    values = np.frombuffer(item.payload[8:], dtype=float)
    got.append(step if values.shape == (40_000,) and (values == step).all() else -step)
print("got", got, flush=True)
"""


def test_a_subscriber_on_another_host_gets_every_set_from_its_publisher(two_hosts, tmp_path):  # noqa: F811
    (na, address_a, _), (nb, _, _) = two_hosts["a"], two_hosts["b"]
    a, b = Host(na, tmp_path), Host(nb, tmp_path)
    port = free_port()
    try:
        go = tmp_path / "go"
        a.start("publisher", "-c", PUBLISH, f"tcp/{address_a}:{port}", str(go))
        _wait_listening(na, address_a, port)
        far = b.start("subscriber", "-c", SUBSCRIBE, f"tcp/{address_a}:{port}")
        near = a.start("near", "-c", SUBSCRIBE, f"tcp/{address_a}:{port}")
        for host, process in ((b, far), (a, near)):
            _wait_said(host, process, "listening")
        go.touch()
        for host, process in ((b, far), (a, near)):
            _wait_said(host, process, "got", timeout=120)
            assert f"got {list(range(1, 21))}" in host.output(process), host.output(process)[-2000:]
            assert "dropped" not in host.output(process)
    finally:
        a.kill_all()
        b.kill_all()


def test_decoding_a_reference_as_a_message_says_what_it_is():
    from dtpf.messages.codec import MessageError, decode
    reference = Reference(slots.host_id(), "dtpf-" + "ab" * 16, 0, 1, 10, "ab").encode()
    with pytest.raises(MessageError, match=r"reference to a particle set .*\(DTPF_SHARED_SETS=0"):
        decode(reference)


def test_a_service_with_no_room_in_shared_memory_sends_its_sets_as_bytes(bus, monkeypatch):
    """A full /dev/shm (a container's 64 MB) fails the ring's posix_fallocate: the service says so once and
    sends that key's sets as bytes; a subscriber gets every set either way."""
    from dtpf.messages.codec import decode
    from dtpf.messages.config import RunConfig
    from dtpf.messages.models import ParticleSet
    from dtpf.shell.service import ServiceShell

    sending, receiving = bus
    key = "dtpf/room-1/entity/particles"
    inbox = Inbox(receiving, key)
    calls = []

    def no_room(fd, offset, length):
        calls.append(length)
        raise OSError(28, "No space left on device")

    shell = ServiceShell("entity", RunConfig(twin="room-1", run_id="run"), session=sending)
    try:
        sets = []
        for step, room in ((1, True), (2, False), (3, False)):
            if not room:
                monkeypatch.setattr(slots.os, "posix_fallocate", no_room)
            particles, weights = _arrays(step, n=20_000)
            sets.append(ParticleSet(run_id="run", twin_id="room-1", step=step, kind="propagated",
                                    particles=particles, weights=weights / weights.sum()))
            if step == 2:  # the ring is full at 20,000 particles: a set four times as large needs a new one
                particles, weights = _arrays(step, n=80_000)
                sets[-1] = ParticleSet(run_id="run", twin_id="room-1", step=step, kind="propagated",
                                       particles=particles, weights=weights / weights.sum())
            shell.publish(sets[-1])
        got = []
        while len(got) < 3:
            item = inbox.get(timeout=30)
            assert item is not None, f"{len(got)} of 3 sets"
            got.append(decode(item.payload))
        assert [(m.step, m.particles.shape) for m in got] == [(m.step, m.particles.shape) for m in sets]
        assert all(np.array_equal(a.particles, b.particles) for a, b in zip(got, sets))
        assert len(calls) == 1 and key in shell._bytes_only  # tried once, then bytes
    finally:
        inbox.close()
        shell.presence.close()
        shell._close_publishers()
