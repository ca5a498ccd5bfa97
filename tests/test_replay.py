"""dtpf verify and dtpf play on logs made by real launches."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
import time

import numpy as np
import pytest

from dtpf.messages.codec import decode_for_key, encode
from dtpf.messages.config import RunConfig
from dtpf.recording.logfile import read_log, write_log
from dtpf.scripts.launch import launch
from dtpf.scripts.logs.play import select
from dtpf.scripts.logs.verify import verify

from conftest import ROOT


@pytest.fixture(scope="module")
def clean_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("replay") / "clean.mcap"
    result = launch(RunConfig(particles=200, steps=30, seed=4, twin="t-replay"), log_path=path, timeout=5.0)
    assert result.exit_codes["entity"] == 0
    return path


def altered_copy(source, target, topic_suffix, step, change):
    """A copy of the log with the message of ``step`` on ``topic_suffix`` replaced by ``change(message)``."""
    log = read_log(source)
    for i, item in enumerate(log.messages):
        if item.topic.endswith(topic_suffix):
            message = decode_for_key(item.topic, item.data)
            if message.step == step:
                log.messages[i] = dataclasses.replace(item, data=encode(change(message)))
                break
    else:
        raise AssertionError(f"no {topic_suffix} message at step {step}")
    write_log(log, target)
    return target


def test_verify_reproduces_every_step_of_a_clean_log(clean_log):
    result = verify(read_log(clean_log))
    assert result.ok, str(result.mismatch)
    assert result.checked == list(range(1, 31))
    assert result.unanswered == []
    completed = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "verify", str(clean_log)], cwd=ROOT,
                               capture_output=True, text=True, timeout=120)
    assert completed.returncode == 0, completed.stdout + completed.stderr
    assert "OK: 30 steps reproduced exactly" in completed.stdout


def test_verify_names_the_step_and_field_of_an_altered_particle(clean_log, tmp_path):
    def nudge(message):
        particles = message.particles.copy()
        particles[17, 0] = np.nextafter(particles[17, 0], np.inf)  # one ulp
        return message.model_copy(update={"particles": particles})

    log = altered_copy(clean_log, tmp_path / "particle.mcap", "information/preprocessed", 7, nudge)
    result = verify(read_log(log))
    assert result.mismatch is not None
    assert (result.mismatch.step, result.mismatch.field) == (7, "particles[17, 0]")
    assert result.checked == list(range(1, 7))
    completed = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "verify", str(log)], cwd=ROOT,
                               capture_output=True, text=True, timeout=120)
    assert completed.returncode == 1
    assert "MISMATCH step 7: dtpf/t-replay/information/preprocessed particles[17, 0] differs" in completed.stdout


def test_verify_names_an_altered_ps_command(clean_log, tmp_path):
    log = altered_copy(clean_log, tmp_path / "ps.mcap", "system/ps", 12,
                       lambda m: m.model_copy(update={"ps": 0.5}))
    mismatch = verify(read_log(log)).mismatch
    assert (mismatch.step, mismatch.topic, mismatch.field) == (12, "dtpf/t-replay/system/ps", "ps")
    assert (mismatch.recorded, mismatch.rerun) == (0.5, 0.81)


def test_verify_names_an_altered_weight_state(clean_log, tmp_path):
    log = altered_copy(clean_log, tmp_path / "ws.mcap", "information/weight_state", 20,
                       lambda m: m.model_copy(update={"ess": m.ess * 1.01}))
    mismatch = verify(read_log(log)).mismatch
    assert (mismatch.step, mismatch.field) == (20, "ess")


def test_play_republishes_every_message_in_order_with_scaled_spacing(clean_log, router):
    log = read_log(clean_log)
    chosen = select(log, ["entity/particles", "entity/estimate"])
    assert len(chosen) == 60
    span = (chosen[-1].log_time - chosen[0].log_time) / 1e9
    start = time.monotonic()
    completed = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "play", str(clean_log), "--rate", "2",
                                "--topics", "entity/particles", "entity/estimate", "--connect", router.endpoint,
                                "--quiet"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    elapsed = time.monotonic() - start
    assert completed.returncode == 0, completed.stderr
    assert "published 60 messages" in completed.stderr
    received = []
    while (item := router.inbox.get(timeout=1.0)) is not None:
        received.append(item)
    assert [(r.key, r.payload) for r in received] == [(m.topic, m.data) for m in chosen]
    assert elapsed >= span / 2 * 0.9  # the original spacing, halved


def test_play_and_verify_refuse_a_missing_file(tmp_path):
    for command in ("play", "verify"):
        completed = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", command, str(tmp_path / "nope.mcap")],
                                   cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert completed.returncode == 2
        assert "nope.mcap" in completed.stdout + completed.stderr
        assert "Traceback" not in completed.stderr
