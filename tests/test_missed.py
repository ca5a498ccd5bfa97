"""What the recorder missed and could not recover: its notes, and how dtpf summary and dtpf verify name them.

The recorder sees a lost gap as a jump in a publisher's sequence numbers (:class:`dtpf.recording.missed.Gaps`);
Zenoh's own count may come late and is noted at the end only when no jump showed it. A log with such notes
names the steps in ``dtpf summary`` (``lost``) and fails ``dtpf verify``. The end-to-end case (a partition
longer than a publisher's cache) is ``tests/test_partition.py``.
"""
from __future__ import annotations

import subprocess
import sys

import pytest

from dtpf.messages import keys
from dtpf.messages.codec import encode
from dtpf.messages.models import Estimate, Missed
from dtpf.recording.logfile import read_log
from dtpf.recording.missed import Gaps, lost_steps
from dtpf.recording.writer import McapRecording
from dtpf.scripts.logs.summary import format_summary, summarise

KEY = "dtpf/t-1/entity/estimate"


def _estimate(step: int) -> Estimate:
    return Estimate.model_construct(run_id="r", twin_id="t-1", step=step)


def test_a_jump_in_the_numbers_is_noted_with_the_steps_around_it_whenever_zenoh_says_so():
    gaps = Gaps("recorder-twin", "r")
    assert [gaps.heard("S", sn, KEY, _estimate(sn + 1)) for sn in range(5)] == [[]] * 5
    # Zenoh's count comes after the messages that follow the gap (a Python listener is called late).
    (note,) = gaps.heard("S", 8, KEY, _estimate(9))
    gaps.missed("S", 3)
    assert (note.twin_id, note.key, note.count, note.after_step, note.before_step) == ("t-1", KEY, 3, 5, 9)
    assert gaps.close_all() == [] and gaps.messages == 3  # the count no jump showed: none
    # A rejected message's number is no gap; Zenoh's count of the publisher's last messages is noted at the end.
    gaps.passed("S", 9)
    assert gaps.heard("S", 10, KEY, _estimate(11)) == []
    gaps.missed("S", 2)
    (last,) = gaps.close_all()
    assert (last.count, last.after_step, last.before_step) == (2, 11, None) and gaps.messages == 5
    assert lost_steps([note, last]) == {KEY: [6, 7, 8, 12, 13]}


@pytest.fixture(scope="module")
def launch_log(tmp_path_factory):
    folder = tmp_path_factory.mktemp("missed")
    done = subprocess.run([sys.executable, "-m", "dtpf", "launch", "-q", "--policy", "fixed", "--particles", "200", "--steps", "30",
                           "--timeout", "1.0", "-o", str(folder / "run.mcap")], capture_output=True, text=True,
                          timeout=180)
    assert done.returncode == 0, done.stdout + done.stderr
    return folder / "run.mcap"


def test_summary_and_verify_name_the_steps_the_recorder_declared_lost(launch_log, tmp_path):
    log = read_log(launch_log)
    twin = summarise(log).twins[0].twin
    lost = range(11, 14)
    dropped = [f"dtpf/{twin}/entity/{topic}" for topic in ("particles", "estimate", "cloud")]
    steps = {(item.topic, item.sequence, item.log_time): message.step for item, message in log.decoded(dropped)}
    run_id = next(m.run_id for _, m in log.decoded(dropped[1:2]))
    copy = tmp_path / "lost.mcap"
    with McapRecording(copy) as recording:  # the run as a recorder would have written it, steps 11-13 missed
        for message in log.messages:
            if steps.get((message.topic, message.sequence, message.log_time)) in lost:
                continue
            recording.write(message.topic, message.data, message.log_time)
        for topic in ("entity/particles", "entity/estimate"):
            note = Missed(run_id=run_id, twin_id=twin, step=11, key=f"dtpf/{twin}/{topic}", source="S",
                          count=3, after_step=10, before_step=14)
            recording.write(keys.key_for(note), encode(note))
    text = format_summary(summarise(read_log(copy)))
    assert "  missing       11-13\n" in text, text
    assert "  lost          steps 11-13, declared lost by the recorder (entity/estimate 11-13, entity/particles " \
           "11-13; 6 messages in 2 gaps its publishers' caches no longer held)" in text, text
    verified = subprocess.run([sys.executable, "-m", "dtpf", "verify", str(copy)], capture_output=True, text=True,
                              timeout=120)
    assert verified.returncode == 1, verified.stdout + verified.stderr
    assert f"FAILED: the recorder declared steps 11-13 of dtpf/{twin}/entity/particles lost" in verified.stdout, \
        verified.stdout
    assert "MISMATCH" not in verified.stdout, verified.stdout  # the re-run stopped before the first lost step
