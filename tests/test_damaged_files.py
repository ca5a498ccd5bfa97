"""Observation files are read whole or refused (issue 41): a damage corpus.

A tester zeroed 4 kB at 60% of a rosbag2 bag written by rosbags: ``dtpf run`` went on with 68 observations
gone and every later one shifted, though the bag's summary declared 1,000 messages on the topic. Here bags
are written with rosbags (not dtpf), uncompressed and zstd, two chunks each, then damaged the ways a disk
or a copy damages a file: zeroed regions, flipped bytes, cuts, a chunk dropped or zeroed, the summary's
records zeroed. Each kind gives a one-line refusal that names how many messages were read and how many the
bag declares, or a correct read: every row the undamaged bag's row of the same step, none shifted. With
``partial`` each kind gives a refusal, or rows each equal to the undamaged bag's row of the same log time
and a ``problem`` that says what was skipped. Never a silent wrong read.
"""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT

pytest.importorskip("rosbags", reason="rosbags is not installed (pip install 'dtpf[rosbag]')")

from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_typestore

from dtpf.entity import rosbag
from dtpf.entity.observations import ObservationError, read_observations

TYPESTORE = get_typestore(Stores.ROS2_KILTED)
TOPIC, FIELDS, MESSAGES = "/target", "point.x,point.y", 1000
EXAMPLE = "docs/examples/range_bearing.py:RangeBearingTarget"


def write_bag(path: Path, *, compressed: bool, chatter: int = 1500) -> None:
    """MESSAGES geometry_msgs/msg/PointStamped on /target, 20 Hz from t = 1000 s, each followed by a
    std_msgs/msg/String of about ``chatter`` bytes on /chatter (1,500: two chunks of rosbags' 1 MiB)."""
    types = TYPESTORE.types
    point_stamped, header, time, point, text = (types[name] for name in (
        "geometry_msgs/msg/PointStamped", "std_msgs/msg/Header", "builtin_interfaces/msg/Time",
        "geometry_msgs/msg/Point", "std_msgs/msg/String"))
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compressed:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        target = writer.add_connection(TOPIC, point_stamped.__msgtype__, typestore=TYPESTORE)
        other = writer.add_connection("/chatter", text.__msgtype__, typestore=TYPESTORE)
        for i in range(MESSAGES):
            ns = 1_000_000_000_000 + i * 50_000_000
            message = point_stamped(header=header(stamp=time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="radar"),
                                    point=point(x=1000.0 + i, y=0.001 * i, z=0.0))
            writer.write(target, ns, TYPESTORE.serialize_cdr(message, point_stamped.__msgtype__))
            words = f"row {i} " + "x" * (chatter + (i * 7919) % 97)
            writer.write(other, ns + 1, TYPESTORE.serialize_cdr(text(data=words), text.__msgtype__))


def records(data: bytes, opcode: int) -> list[tuple[int, int]]:
    """(offset, length with opcode and length field) of the file's top-level MCAP records of ``opcode``."""
    found, at = [], 8
    while at + 9 <= len(data) - 8:
        op, length = data[at], int.from_bytes(data[at + 1:at + 9], "little")
        if op == opcode:
            found.append((at, 9 + length))
        at += 9 + length
    return found


def zero(data: bytes, at: int, n: int) -> bytes:
    out = bytearray(data)
    out[at:at + n] = bytes(len(out[at:at + n]))
    return bytes(out)


def flip(data: bytes, at: int, n: int = 1) -> bytes:
    out = bytearray(data)
    for i in range(at, at + n):
        out[i] ^= 0xFF
    return bytes(out)


def summary_start(data: bytes) -> int:
    footer = len(data) - 8 - 29
    return int.from_bytes(data[footer + 9:footer + 17], "little")


def chunk(data: bytes, k: int) -> tuple[int, int]:
    return records(data, 0x06)[k]


#: Damage of a bag's MCAP file, as a tester made it: name -> the damaged bytes.
DAMAGE = {
    "zero 4 kB at 60%": lambda d: zero(d, int(len(d) * 0.6), 4096),
    "zero 4 kB at 20%": lambda d: zero(d, int(len(d) * 0.2), 4096),
    "zero 64 B at 40%": lambda d: zero(d, int(len(d) * 0.4), 64),
    "zero 1 kB before the first message index": lambda d: zero(d, records(d, 0x07)[0][0] - 1024, 1024),
    "flip a byte at 30%": lambda d: flip(d, int(len(d) * 0.3)),
    "flip 16 bytes at 50%": lambda d: flip(d, int(len(d) * 0.5), 16),
    "flip 4 bytes at 10%": lambda d: flip(d, int(len(d) * 0.1), 4),
    "flip 8 bytes at byte 199": lambda d: flip(d, 199, 8),  # zstd: still decompresses, to garbled records
    "flip the first chunk's end time": lambda d: flip(d, chunk(d, 0)[0] + 9 + 8, 2),
    "cut at 50%": lambda d: d[:len(d) // 2],
    "cut in the summary": lambda d: d[:summary_start(d) + 40],
    "cut 40 bytes short": lambda d: d[:-40],
    "drop the first chunk": lambda d: d[:chunk(d, 0)[0]] + d[sum(chunk(d, 0)):],
    "drop the second chunk": lambda d: d[:chunk(d, 1)[0]] + d[sum(chunk(d, 1)):],
    "zero the second chunk": lambda d: zero(d, *chunk(d, 1)),
    "zero the first chunk's header": lambda d: zero(d, chunk(d, 0)[0], 60),
    "zero a message index": lambda d: zero(d, *records(d, 0x07)[0]),
    "zero 8 bytes of a message index": lambda d: zero(d, records(d, 0x07)[0][0] + 40, 8),
    "zero the statistics": lambda d: zero(d, *records(d, 0x0B)[0]),
    "zero the chunk indexes": lambda d: zero(d, *records(d, 0x08)[0]),
    "zero the summary": lambda d: zero(d, summary_start(d), len(d) - 8 - 29 - summary_start(d)),
    "zero the footer": lambda d: zero(d, len(d) - 37, 29),
    "zero the header": lambda d: zero(d, 8, 35),
    "zero the closing magic": lambda d: zero(d, len(d) - 8, 8),
    "zero 4 kB at 60% and the statistics": lambda d: zero(zero(d, *records(d, 0x0B)[0]), int(len(d) * 0.6), 4096),
    "zero 30 kB at 30% and the summary": lambda d: zero(zero(d, summary_start(d), len(d) - 8 - 29 - summary_start(d)),
                                                        int(len(d) * 0.3), 30000),
}

#: Kinds that read silently wrong before (rows gone and the rest shifted) in the uncompressed bag: now refused,
#: naming the gap.
WERE_SILENT = ("zero 4 kB at 60%", "zero 4 kB at 20%", "zero the first chunk's header")

REFUSAL = re.compile(r"the bag declares (\d+|an unknown number of) messages on /target, (?:(\d+) can be read|"
                     r"rosbags stopped after (\d+) messages|(\d+) were read)")


@pytest.fixture(scope="module", params=["uncompressed", "zstd"])
def whole(request, tmp_path_factory):
    """The undamaged bag (a folder), its MCAP file's bytes and its table."""
    path = tmp_path_factory.mktemp(f"whole-{request.param}") / "bag"
    write_bag(path, compressed=request.param == "zstd")
    table = rosbag.read_bag(path, TOPIC, FIELDS)
    assert table.steps == MESSAGES and table.problem is None
    assert len(records((path / "bag.mcap").read_bytes(), 0x06)) == 2  # two chunks: one can be dropped
    return path, (path / "bag.mcap").read_bytes(), table


def damaged(whole, kind: str, tmp_path: Path) -> Path:
    """A copy of the bag folder (its metadata.yaml as written) with its MCAP file damaged by ``kind``."""
    path, data, _ = whole
    folder = tmp_path / "bag"
    shutil.copytree(path, folder)
    (folder / "bag.mcap").write_bytes(DAMAGE[kind](data))
    return folder


def check_refusal(text: str, kind: str) -> None:
    assert "\n" not in text and text.strip(), (kind, text)
    found = REFUSAL.search(text)
    assert found, (kind, text)
    if found.group(1).isdigit():
        assert int(found.group(1)) == MESSAGES, (kind, text)
        # where the gap is: the messages and log times missing, or the widest gap in the log times read
        assert re.search(r"missing messages? \d+(-\d+)? \(log times? [\d.]+", text) or "cannot be told" in text, \
            (kind, text)


@pytest.mark.parametrize("kind", DAMAGE)
def test_a_damaged_bag_is_refused_in_one_line_or_read_right(whole, kind, tmp_path):
    folder = damaged(whole, kind, tmp_path)
    good = whole[2]
    for source in (folder, folder / "bag.mcap"):  # with its metadata.yaml, or the MCAP file alone
        for steps in (None, 1, 700):
            try:
                table = rosbag.read_bag(source, TOPIC, FIELDS, steps=steps)
            except ObservationError as error:
                check_refusal(str(error), kind)
                continue
            rows = table.steps
            assert rows <= (steps or MESSAGES), kind
            np.testing.assert_array_equal(table.observations, good.observations[:rows], err_msg=kind)
            np.testing.assert_array_equal(table.stamps, good.stamps[:rows], err_msg=kind)
            if rows < (steps or MESSAGES):
                assert table.problem and "cut short" in table.problem, (kind, table.problem)
            assert kind not in WERE_SILENT, (kind, "read, not refused")


@pytest.mark.parametrize("kind", DAMAGE)
def test_partial_reads_what_is_intact_and_says_what_it_skipped(whole, kind, tmp_path):
    folder = damaged(whole, kind, tmp_path)
    good = whole[2]
    where = {int(stamp): k for k, stamp in enumerate(good.stamps)}
    try:
        table = rosbag.read_bag(folder, TOPIC, FIELDS, partial=True)
    except ObservationError as error:
        check_refusal(str(error), kind)
        assert kind not in WERE_SILENT, (kind, str(error))
        return
    steps = [where[int(stamp)] for stamp in table.stamps]  # each row is a message of the bag, at its own time
    assert steps == sorted(set(steps)), kind
    np.testing.assert_array_equal(table.observations, good.observations[steps], err_msg=kind)
    if table.steps < MESSAGES:
        assert table.problem and ("skipped" in table.problem or "cut short" in table.problem
                                  or "in file order (--partial)" in table.problem), (kind, table.problem)
        if "skipped" in table.problem:
            first_gap = next(k for k in range(MESSAGES) if k >= len(steps) or steps[k] != k)
            assert f"skipped messages {first_gap + 1}" in table.problem or \
                f"skipped message {first_gap + 1} " in table.problem, (kind, table.problem)


def test_the_testers_bag_is_refused_naming_the_gap_and_partial_runs_on_the_rest(tmp_path):
    """The bag of the report: one chunk, 4 kB zeroed at 60%. dtpf run refuses it (exit 2, one line); --partial
    runs on the intact messages and says which it skipped."""
    from test_ros2_bag import write_bag as write_example_bag

    rows = [(1000.0 + i, 0.5 + 0.0001 * i) for i in range(MESSAGES)]
    bag = tmp_path / "radar"
    write_example_bag(bag, rows)
    data = (bag / "radar.mcap").read_bytes()
    assert len(records(data, 0x06)) == 1
    (bag / "radar.mcap").write_bytes(zero(data, int(len(data) * 0.6), 4096))
    common = ["--model", EXAMPLE, "--observations", str(bag), "--topic", TOPIC, "--ros2-fields", FIELDS, "-n", "100",
              "--policy", "fixed"]
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "run", "-q", *common], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    found = re.search(r"the bag declares 1000 messages on /target, (\d+) can be read: missing messages (\d+)-(\d+) "
                      r"\(log times ([\d.]+)-([\d.]+) s", lines[0])
    assert found, lines[0]
    intact, first, last = (int(found.group(k)) for k in (1, 2, 3))
    assert intact == MESSAGES - (last - first + 1) and 500 < first <= last < 900, lines[0]
    assert float(found.group(4)) == pytest.approx(1000 + (first - 1) * 0.05), lines[0]
    assert "--partial" in lines[0]

    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "run", "-q", "--partial", *common], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"T = {intact}," in done.stdout, done.stdout
    assert f"read {intact} of the 1000 messages on /target the bag declares (--partial); skipped messages " \
           f"{first}-{last}" in done.stderr, done.stderr
    table = rosbag.read_bag(bag, TOPIC, FIELDS, partial=True)
    expected = [k for k in range(MESSAGES) if not first - 1 <= k <= last - 1]
    np.testing.assert_array_equal(table.observations, np.asarray(rows)[expected])
    # The built-in reader named with --reader takes --partial too.
    for flags, code in (([], 2), (["--partial"], 0)):
        named = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "run", "-q", "--reader", "rosbag2", *flags,
                                *common], cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert named.returncode == code, named.stdout + named.stderr
        if code == 0:
            assert f"T = {intact}," in named.stdout and named.stdout.split("time")[0] == done.stdout.split("time")[0]


def test_dtpf_launch_refuses_the_bag_or_with_partial_runs_on_what_dtpf_run_does(tmp_path):
    """dtpf launch refuses the damaged bag before a service starts; with --partial every service reads the
    intact messages (the flag reaches them) and the run's numbers are dtpf run --partial's."""
    from test_ros2_bag import write_bag as write_example_bag

    bag = tmp_path / "radar"
    write_example_bag(bag, [(1000.0 + i, 0.5 + 0.0001 * i) for i in range(300)])
    data = (bag / "radar.mcap").read_bytes()
    (bag / "radar.mcap").write_bytes(zero(data, int(len(data) * 0.5), 2048))
    common = ["-q", "--model", EXAMPLE, "--observations", str(bag), "--topic", TOPIC, "--ros2-fields", FIELDS,
              "-n", "100", "--twin", "t-partial", "--policy", "fixed"]

    def dtpf(*args):
        return subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", *args], cwd=ROOT, capture_output=True,
                              text=True, timeout=300)

    refused = dtpf("launch", *common, "-o", str(tmp_path / "refused.mcap"))
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1, refused.stderr
    assert "the bag declares 300 messages on /target" in refused.stderr and not (tmp_path / "refused.mcap").exists()
    launched = dtpf("launch", *common, "--partial", "-o", str(tmp_path / "partial.mcap"))
    run = dtpf("run", *common, "--partial")
    assert launched.returncode == 0 and run.returncode == 0, launched.stderr + run.stderr
    found = re.search(r"read (\d+) of the 300 messages on /target the bag declares \(--partial\); skipped", run.stderr)
    assert found and found.group(0) in launched.stderr, launched.stderr
    intact = int(found.group(1))
    assert f"steps           {intact} of {intact}" in launched.stdout, launched.stdout
    figure = [line for line in run.stdout.splitlines() if line.startswith("log predictive")]
    assert figure and figure[0].split("(")[0] in launched.stdout, (figure, launched.stdout)


def test_a_bag_whose_metadata_declares_more_than_it_holds_is_refused(whole, tmp_path):
    """A folder's metadata.yaml that declares more messages of the topic than its MCAP file holds (a file of a
    split bag gone): refused, naming both counts; --partial reads what is there and says what is missing."""
    path, _, good = whole
    folder = tmp_path / "bag"
    shutil.copytree(path, folder)
    meta = folder / "metadata.yaml"
    text = meta.read_text()
    assert text.count("message_count: 1000") == 2  # each topic's: /target is the first
    meta.write_text(text.replace("  - message_count: 1000\n    topic_metadata:\n      name: /target",
                                 "  - message_count: 1200\n    topic_metadata:\n      name: /target"))
    with pytest.raises(ObservationError, match=r"the bag declares 1200 messages on /target, 1000 can be read: "
                                               r"missing none of the 1000 its index lists, and 200 that its "
                                               r"metadata.yaml declares and no MCAP index lists"):
        rosbag.read_bag(folder, TOPIC, FIELDS)
    table = rosbag.read_bag(folder, TOPIC, FIELDS, partial=True)
    np.testing.assert_array_equal(table.observations, good.observations)
    assert "read 1000 of the 1200 messages" in table.problem


def test_a_sound_bag_reads_the_same_whole_in_steps_and_with_partial(whole):
    path, _, good = whole
    for partial in (False, True):
        table = rosbag.read_bag(path, TOPIC, FIELDS, partial=partial)
        assert table.problem is None
        np.testing.assert_array_equal(table.observations, good.observations)
        head = rosbag.read_bag(path, TOPIC, FIELDS, steps=37, partial=partial)
        np.testing.assert_array_equal(head.observations, good.observations[:37])


def test_a_nan_in_a_sound_bag_is_still_the_message_that_is_wrong(tmp_path):
    """A message that does not fit the model, in a sound bag, is named as before: the bag is not damaged."""
    from test_ros2_bag import write_bag as write_example_bag

    bag = tmp_path / "nan"
    write_example_bag(bag, [(1000.0 + i, 0.5) for i in range(50)], nan_at=17)
    with pytest.raises(ObservationError, match=r"message 18 on /target: nan \(observations must be finite\)"):
        rosbag.read_bag(bag, TOPIC, FIELDS, partial=True)


def test_a_damaged_npy_or_npz_is_refused_naming_its_rows(tmp_path):
    """An .npy's header declares its shape: cut short, it is refused naming the whole rows it holds and the
    rows its header declares. An .npz archive's members carry CRCs: damage anywhere in a member refuses it, even
    when only its first rows are read."""
    z = np.arange(2000.0).reshape(1000, 2)
    np.save(tmp_path / "a.npy", z)
    data = (tmp_path / "a.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[:int(len(data) * 0.6)])
    with pytest.raises(ObservationError, match=r"cut short: .*: 596 whole rows of the 1000 its header declares "
                                               r"\(rows 596 to 999 missing\)"):
        read_observations(tmp_path / "cut.npy")
    np.savez(tmp_path / "a.npz", observations=z)
    data = bytearray((tmp_path / "a.npz").read_bytes())
    data[int(len(data) * 0.8)] ^= 0xFF  # a row near the end
    (tmp_path / "flipped.npz").write_bytes(bytes(data))
    for steps in (None, 10):
        with pytest.raises(ObservationError, match="Bad CRC-32"):
            read_observations(tmp_path / "flipped.npz", steps=steps)
