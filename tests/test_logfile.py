"""Reading, summarising and recovering MCAP logs, complete and damaged (dtpf.recording.logfile, dtpf.scripts.logs.summary).

One real launch (four processes over Zenoh on loopback) makes the log the
module's tests read; damaged logs are prefixes and corruptions of it, and
uncompressed and zstd recordings of the same messages made here with
McapRecording, where every message record can be located in the file.
"""
from __future__ import annotations

import argparse
import io
import random
import struct
from collections import Counter

import pytest
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk

from dtpf.messages.config import RunConfig
from dtpf.recording.logfile import MAGIC, LogError, LogMessage, read_log, write_log
from dtpf.recording.writer import AUTO_LIMIT, McapRecording, auto_compression
from dtpf.scripts.inprocess import run
from dtpf.scripts.launch import launch
from dtpf.scripts.logs import summary as inspect_log

CONFIG = RunConfig(particles=200, steps=40, seed=5, twin="t-log", run_id="logtest")
PER_STEP_TOPICS = [f"dtpf/t-log/{topic}" for topic in
                   ("entity/particles", "information/preprocessed", "information/weight_state", "system/ps",
                    "entity/estimate")]


@pytest.fixture(scope="module")
def launched(tmp_path_factory):
    """A log of CONFIG from a real launch; it must be whole (every step on every topic, none degraded)."""
    path = tmp_path_factory.mktemp("launch") / "run.mcap"
    result = launch(CONFIG, log_path=path, timeout=5.0)
    with open(path, "rb") as f:
        counts = Counter(channel.topic for _, channel, _ in make_reader(f).iter_messages(log_time_order=False))
    assert {topic: counts[topic] for topic in PER_STEP_TOPICS} == dict.fromkeys(PER_STEP_TOPICS, CONFIG.steps)
    assert not any(e.degraded for e in result.estimates)
    return path


@pytest.fixture(scope="module")
def intact(launched):
    return read_log(launched)


@pytest.fixture(scope="module")
def inprocess():
    return run(CONFIG)


def _cut(source, tmp_path, size, name="cut.mcap"):
    path = tmp_path / name
    path.write_bytes(source.read_bytes()[:size])
    return path


def _read_back(path):
    """(topic, log_time, publish_time, sequence, data) of every message, with CRCs checked."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        messages = [(channel.topic, m.log_time, m.publish_time, m.sequence, m.data)
                    for _, channel, m in reader.iter_messages(log_time_order=False)]
    return summary, messages


def _as_tuples(messages: list[LogMessage]):
    return [(m.topic, m.log_time, m.publish_time, m.sequence, m.data) for m in messages]


def _chunks(path):
    """(start offset, end offset, message count) of every chunk, read with mcap's own StreamReader."""
    with open(path, "rb") as f:
        out, start = [], len(MAGIC)
        for record in StreamReader(f, emit_chunks=True).records:
            if isinstance(record, Chunk):
                count = sum(isinstance(r, McapMessage) for r in breakup_chunk(record, validate_crc=True))
                out.append((start, f.tell(), count))
            start = f.tell()
    return out


def _chunk_ends(path):
    """(end offset, message count) of every chunk."""
    return [(end, count) for _, end, count in _chunks(path)]


# --- a complete log ---

def test_the_recorder_compresses_small_particle_sets_and_leaves_large_ones_alone(launched):
    assert auto_compression(AUTO_LIMIT) == "lz4" and auto_compression(AUTO_LIMIT + 1) == "none"
    assert auto_compression(100_000 * 2 * 8) == "none"
    with open(launched, "rb") as f:
        compressions = {c.compression for c in make_reader(f).get_summary().chunk_indexes}
    assert compressions == {auto_compression(CONFIG.particles * 2 * 8)} == {"lz4"}


def test_info_counts_every_topic_of_a_complete_launch(intact):
    info = inspect_log.log_info(intact)
    assert intact.complete and intact.problem is None and info.problems == []
    by_topic = {t.topic: t for t in info.topics}
    for topic in PER_STEP_TOPICS:
        assert by_topic[topic].count == CONFIG.steps, topic
        assert (by_topic[topic].first_step, by_topic[topic].last_step) == (1, CONFIG.steps), topic
        assert by_topic[topic].undecodable == 0
    assert by_topic["dtpf/t-log/entity/particles"].message_encoding == "dtpf-envelope"
    assert by_topic["dtpf/t-log/entity/estimate"].schema_name == "dtpf.Estimate"
    assert info.messages == sum(t.count for t in info.topics) == len(intact.messages)
    assert info.run_ids == ["logtest"] and info.twin_ids == ["t-log"]
    assert {s.name: s.current for s in info.schemas} == {
        "dtpf.ParticleSet": "same", "dtpf.WeightState": "same", "dtpf.PSCommand": "same",
        "dtpf.Estimate": "same", "dtpf.Status": "same", "foxglove.PointCloud": "same"}
    assert info.start_ns <= info.end_ns and info.undecodable == 0
    # The statistics record of the file agrees with what was read.
    assert intact.statistics.message_count == len(intact.messages)


def test_summary_reproduces_the_inprocess_run(intact, inprocess):
    summary = inspect_log.summarise(intact)
    assert summary.problem is None and summary.undecodable == 0
    [twin] = summary.twins
    assert (twin.twin, twin.run_id) == ("t-log", "logtest")
    assert twin.steps == list(range(1, CONFIG.steps + 1)) and twin.missing_steps == []
    assert twin.expected_steps == CONFIG.steps and twin.config["particles"] == CONFIG.particles
    assert twin.truth_steps == CONFIG.steps
    assert twin.rmse == pytest.approx(inprocess.rmse, rel=0, abs=1e-12)
    assert twin.mean_ess == pytest.approx(inprocess.mean_ess, rel=0, abs=1e-9)
    assert twin.min_ess == pytest.approx(inprocess.ess.min(), rel=0, abs=1e-9)
    assert twin.resamplings == inprocess.resamplings == CONFIG.steps
    assert twin.degraded == 0 and twin.degraded_steps == []
    assert (twin.ps_commanded.start, twin.ps_commanded.end, twin.ps_commanded.changes) == (0.81, 0.81, 0)
    assert twin.ps_commanded.count == CONFIG.steps and twin.policies == ["fixed"]
    assert twin.ps_applied.count == CONFIG.steps and (twin.ps_applied.min, twin.ps_applied.max) == (0.81, 0.81)
    assert {"entity", "information", "system"} <= set(twin.statuses)
    assert all(s.rejected == 0 for s in twin.statuses.values())


def test_info_and_summary_commands_print_the_figures(launched, inprocess, capsys):
    assert inspect_log.cmd_info(argparse.Namespace(log=launched)) == 0
    out = capsys.readouterr().out
    assert "state       complete" in out and "dtpf/t-log/entity/estimate" in out and "1..40" in out
    assert inspect_log.cmd_summary(argparse.Namespace(log=launched)) == 0
    out = capsys.readouterr().out
    assert f"RMSE          {inprocess.rmse:.4f}" in out
    assert "steps         40 of 40 (1-40)" in out and "degraded      0" in out


def test_decoded_reports_failures_instead_of_raising(intact):
    log = read_log(intact.path)
    estimate = next(m for m in log.messages if m.topic.endswith("/entity/estimate"))
    index = log.messages.index(estimate)
    log.messages[index] = LogMessage(estimate.topic, estimate.channel_id, estimate.log_time, estimate.publish_time,
                                     estimate.sequence, b'{"not": "an estimate"}')
    results = list(log.decoded(lambda topic: topic.endswith("/entity/estimate")))
    assert len(results) == CONFIG.steps
    errors = [m for _, m in results if isinstance(m, Exception)]
    assert len(errors) == 1 and "Estimate" in str(errors[0])
    summary = inspect_log.summarise(log)
    assert summary.undecodable == 1 and summary.twins[0].missing_steps == [1]


def test_a_complete_log_is_rewritten_unchanged(intact, tmp_path):
    out = tmp_path / "copy.mcap"
    assert write_log(intact, out) == len(intact.messages)
    summary, messages = _read_back(out)
    assert messages == _as_tuples(intact.messages)
    assert sorted(s.name for s in summary.schemas.values()) == sorted(s.name for s in intact.schemas.values())
    assert {s.name: s.data for s in summary.schemas.values()} == {s.name: s.data for s in intact.schemas.values()}


# --- cut short ---

def _cut_offsets(size: int) -> list[int]:
    rng = random.Random(20261122)
    header_middle = len(MAGIC) + 10
    return sorted({3, header_middle, size // 4, size // 2, 3 * size // 4, 99 * size // 100, size - 3,
                   *(rng.randrange(len(MAGIC), size) for _ in range(6))})


def test_a_cut_launch_log_is_recovered_to_a_valid_prefix(launched, intact, tmp_path):
    size = launched.stat().st_size
    chunks = _chunk_ends(launched)
    assert [count for _, count in chunks] and sum(c for _, c in chunks) == len(intact.messages)
    recovered_from_cut_chunk = 0
    for offset in _cut_offsets(size):
        path = _cut(launched, tmp_path, offset)
        log = read_log(path)
        assert not log.complete or offset >= size - len(MAGIC), offset
        assert log.problem is not None and "cut short" in log.problem or offset >= size - len(MAGIC), offset
        # A prefix, in file order, of the intact log's messages ...
        k = len(log.messages)
        assert log.messages == intact.messages[:k], offset
        # ... holding at least every message of the chunks that ended before the cut.
        assert k >= sum(count for end, count in chunks if end <= offset), offset
        if log.cut is not None and log.cut.compression is not None:
            recovered_from_cut_chunk += log.cut.recovered
        out = tmp_path / "recovered.mcap"
        write_log(log, out)
        summary, messages = _read_back(out)
        assert messages == _as_tuples(log.messages), offset
        assert summary.statistics.message_count == k
    # lz4 blocks inside the cut chunks gave messages back.
    assert recovered_from_cut_chunk > 0


@pytest.fixture(scope="module", params=["none", "zstd", "lz4"])
def rerecorded(request, intact, tmp_path_factory):
    """The launch's messages recorded again with small chunks; each message record located when uncompressed."""
    path = tmp_path_factory.mktemp("rerecorded") / f"{request.param}.mcap"
    with McapRecording(path, compression=request.param, chunk_size=16 << 10, flush_interval=1e9) as recording:
        for i, item in enumerate(intact.messages):
            recording.write(item.topic, item.data, item.log_time)
            if i % 37 == 36:
                recording.flush()
    return request.param, path


def _record_ends(path, messages: list[LogMessage]) -> list[int]:
    """File offset just after each message record of an uncompressed recording, found byte for byte."""
    data = path.read_bytes()
    ends, position = [], 0
    for m in messages:
        record = struct.pack("<BQHIQQ", Opcode.MESSAGE, 22 + len(m.data), m.channel_id, m.sequence, m.log_time,
                             m.publish_time) + m.data
        start = data.index(record, position)
        position = start + len(record)
        ends.append(position)
    return ends


def test_cut_recordings_keep_every_complete_message_record(rerecorded, tmp_path):
    compression, path = rerecorded
    whole = read_log(path)
    assert whole.complete and whole.problem is None
    size = path.stat().st_size
    chunks = _chunk_ends(path)
    assert len(chunks) > 5
    rng = random.Random(7)
    offsets = set(_cut_offsets(size)) | {rng.randrange(len(MAGIC), size) for _ in range(25)}
    ends = _record_ends(path, whole.messages) if compression == "none" else None
    if ends is not None:
        # Cuts right at the end of a message record and one byte before it.
        offsets |= {ends[10], ends[10] - 1, ends[len(ends) // 2], ends[len(ends) // 2] - 1}
    for offset in sorted(offsets):
        log = read_log(_cut(path, tmp_path, offset))
        k = len(log.messages)
        assert log.messages == whole.messages[:k], offset
        if ends is not None:
            assert k == sum(end <= offset for end in ends), offset
        else:
            assert k >= sum(count for end, count in chunks if end <= offset), offset
        if offset < size - len(MAGIC):
            assert not log.complete and log.problem.startswith("log cut short"), offset
            # The recovered file reads completely, with CRCs checked.
            out = tmp_path / "recovered.mcap"
            write_log(log, out)
            assert _read_back(out)[1] == _as_tuples(log.messages), offset


def test_the_problem_says_what_is_missing(launched, intact, tmp_path):
    chunk_start, chunk_end, _ = max(_chunks(launched), key=lambda chunk: chunk[2])
    offset = chunk_start + (chunk_end - chunk_start) * 3 // 4
    log = read_log(_cut(launched, tmp_path, offset))
    problem = log.problem
    assert problem.startswith(f"log cut short: records readable up to byte {chunk_start:,} of {offset:,}")
    assert "no data end, summary or footer" in problem
    last = log.messages[-1]
    assert f"{len(log.messages):,} messages read, the last at step " in problem
    assert f"the file ends inside the chunk at byte {chunk_start:,}" in problem and "(lz4)" in problem
    assert f"{log.cut.recovered:,} of its messages recovered" in problem and log.cut.recovered > 0
    assert log.cut.offset == chunk_start and log.cut.name == "CHUNK"
    assert last.topic in problem or "run-level" in problem


def test_a_file_cut_between_records_loses_nothing_before_the_cut(launched, intact, tmp_path):
    chunks = _chunks(launched)
    start, _, _ = chunks[-1]  # the last chunk starts right after the message indexes of the one before
    log = read_log(_cut(launched, tmp_path, start))
    assert log.messages == intact.messages[:sum(c for _, _, c in chunks[:-1])]
    assert log.read_to == start and f"the file ends between two records, at byte {start:,}" in log.problem


def test_a_file_cut_in_the_summary_keeps_every_message(launched, intact, tmp_path):
    log = read_log(_cut(launched, tmp_path, launched.stat().st_size - 40))
    assert not log.complete and log.data_end
    assert log.messages == intact.messages
    assert "no footer" in log.problem and "every message of the data section was read" in log.problem


def test_info_summary_and_recover_on_a_cut_file(launched, intact, tmp_path, capsys):
    path = _cut(launched, tmp_path, launched.stat().st_size // 2)
    assert inspect_log.cmd_info(argparse.Namespace(log=path)) == 0
    captured = capsys.readouterr()
    assert "DAMAGED" in captured.out and "log cut short" in captured.out and "Traceback" not in captured.err
    assert inspect_log.cmd_summary(argparse.Namespace(log=path)) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[1].endswith("DAMAGED") and lines[2].startswith("problem       log cut short")
    assert "missing" in captured.out and "Traceback" not in captured.err
    out = tmp_path / "fixed.mcap"
    assert inspect_log.cmd_recover(argparse.Namespace(log=path, output=out)) == 0
    captured = capsys.readouterr()
    log = read_log(path)
    assert f"{len(log.messages):,} messages" in captured.out and "lost" in captured.out
    assert _read_back(out)[1] == _as_tuples(log.messages)


def test_recover_refuses_to_overwrite_its_input(launched, tmp_path, capsys):
    path = _cut(launched, tmp_path, launched.stat().st_size // 2)
    before = path.read_bytes()
    assert inspect_log.cmd_recover(argparse.Namespace(log=path, output=tmp_path / "." / path.name)) == 2
    assert "is the log being recovered" in capsys.readouterr().err
    assert path.read_bytes() == before


def test_recover_fails_when_nothing_can_be_read(launched, tmp_path, capsys):
    out = tmp_path / "out.mcap"
    for size in (5, len(MAGIC) + 10):
        assert inspect_log.cmd_recover(argparse.Namespace(log=_cut(launched, tmp_path, size), output=out)) == 1
        assert "nothing to recover" in capsys.readouterr().err
    assert not out.exists()
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file at all")
    assert inspect_log.cmd_recover(argparse.Namespace(log=garbage, output=out)) == 1
    assert "not an MCAP file" in capsys.readouterr().err and not out.exists()


# --- damaged in other ways ---

def test_garbage_and_empty_files_raise_log_error(tmp_path):
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"PK\x03\x04 a zip, not a log")
    with pytest.raises(LogError, match=r"garbage\.mcap is not an MCAP file: it starts with b'PK\\x03\\x04 a z'"):
        read_log(garbage)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(LogError, match=r"empty\.mcap is empty \(0 bytes\)"):
        read_log(empty)
    with pytest.raises(LogError, match=r"cannot read .*missing\.mcap"):
        read_log(tmp_path / "missing.mcap")
    assert issubclass(LogError, ValueError)


def test_a_magic_cut_short_is_an_empty_damaged_log(launched, tmp_path):
    log = read_log(_cut(launched, tmp_path, 5))
    assert log.messages == [] and not log.complete and "inside the MCAP magic" in log.problem
    out = tmp_path / "empty.mcap"
    write_log(log, out)
    assert _read_back(out)[1] == []


@pytest.mark.parametrize("damaged", [0, 2])
def test_a_damaged_chunk_is_dropped_and_reading_goes_on(rerecorded, tmp_path, damaged):
    # Chunk 0 holds the first channel records: the messages after it stay readable through the
    # channel records the summary section repeats.
    compression, path = rerecorded
    whole = read_log(path)
    chunks = _chunks(path)
    start, end, count = chunks[damaged]
    data = bytearray(path.read_bytes())
    data[(start + end) // 2] ^= 0xFF  # in the middle of the chunk's (compressed) records
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    log = read_log(bad)
    assert log.complete and f"chunk at byte {start:,}" in log.problem and "dropped" in log.problem
    assert "never defined" not in log.problem
    before = sum(c for _, _, c in chunks[:damaged])
    assert log.messages == whole.messages[:before] + whole.messages[before + count:]


def test_junk_after_the_last_chunk_stops_reading_without_a_traceback(launched, intact, tmp_path):
    chunks = _chunk_ends(launched)
    end = chunks[0][0]
    junk = bytes(random.Random(3).randrange(256) for _ in range(5000))
    path = tmp_path / "junk.mcap"
    path.write_bytes(launched.read_bytes()[:end] + junk)
    log = read_log(path)
    assert not log.complete and log.problem
    assert log.messages == intact.messages[:len(log.messages)]
    assert len(log.messages) >= chunks[0][1]


def test_a_truncated_closing_magic_still_reads_the_footer(launched, intact, tmp_path):
    log = read_log(_cut(launched, tmp_path, launched.stat().st_size - 3))
    assert log.complete and log.messages == intact.messages
    assert "inside the closing magic" in log.problem


# --- helpers and the command line ---

def test_format_ranges():
    assert inspect_log.format_ranges([1, 2, 3, 5, 7, 8]) == "1-3, 5, 7-8"
    assert inspect_log.format_ranges([21, 22, 34, 23]) == "21-23, 34"
    assert inspect_log.format_ranges([]) == ""


def test_register_adds_the_three_commands():
    parser = argparse.ArgumentParser(prog="dtpf")
    inspect_log.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["recover", "in.mcap", "-o", "out.mcap"])
    assert args.handler is inspect_log.cmd_recover and str(args.output) == "out.mcap"
    assert parser.parse_args(["info", "x.mcap"]).handler is inspect_log.cmd_info
    assert parser.parse_args(["summary", "x.mcap"]).handler is inspect_log.cmd_summary
    with pytest.raises(SystemExit):
        parser.parse_args(["recover", "in.mcap"])  # -o is required
    help_text = io.StringIO()
    parser.print_help(help_text)
    assert all(name in help_text.getvalue() for name in ("info", "summary", "recover"))


def test_fast_crc_is_zlibs_crc32_and_mcap_files_check_with_plain_zlib(tmp_path):
    import os
    import zlib

    from mcap.reader import make_reader

    from dtpf.recording import crc
    from dtpf.recording.writer import McapRecording

    data = os.urandom(300_001)
    assert crc.crc32(data) == zlib.crc32(data)
    assert crc.crc32(data[1000:], crc.crc32(data[:1000])) == zlib.crc32(data)  # running value
    assert crc.FAST, "zlib-ng is a dependency: the fast CRC should be in use"
    path = tmp_path / "crc.mcap"
    with McapRecording(path, compression="none", chunk_size=100_000) as recording:
        for step in range(5):
            recording.write("dtpf/t/entity/unknown", data[step:])
    import mcap.stream_reader
    assert mcap.stream_reader.zlib.crc32 is crc.crc32  # the mcap package computes with it too
    crc.use_fast_crc(False)  # now check every chunk and the summary with CPython's zlib
    try:
        assert mcap.stream_reader.zlib is zlib
        with open(path, "rb") as f:
            messages = [m.data for _, _, m in make_reader(f, validate_crcs=True).iter_messages()]
    finally:
        crc.use_fast_crc()
    assert messages == [data[step:] for step in range(5)]


def test_the_recording_benchmark_replays_a_launch_log_through_the_recorders_admission(launched, tmp_path):
    """``python -m dtpf.scripts.bench.recording --replay LOG``: per step (the log's estimates), the time of each
    part of the recorder's work on the log's own messages; a log without an estimate is named."""
    from dtpf.scripts.bench.recording import replay

    messages = len(read_log(launched).messages)
    lines = replay(launched, 1)
    assert lines[0].startswith(f"{launched}: {messages:,} messages, {CONFIG.steps} steps")
    rows = {line.split(" | ")[0].lstrip("| "): float(line.split(" | ")[1].rstrip(" |")) for line in lines[4:]}
    assert set(rows) == {"decode (the admission's part)", "write, lz4 chunks", "write, no compression",
                         "admission and write, lz4 (the recorder while a set is at most 64 KiB)",
                         "admission and write, no compression"}
    assert all(value > 0 for value in rows.values())
    empty = tmp_path / "empty.mcap"
    with McapRecording(empty, compression="none") as recording:
        recording.write("dtpf/t-log/system/status", b"{}")
    with pytest.raises(SystemExit, match="no estimate in the log"):
        replay(empty, 1)
