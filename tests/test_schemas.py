"""Every JSON message of a real launch log is valid against the schema embedded beside it.

Checked with an independent validator (``jsonschema``), not with the models
that wrote them, over launches in the default, ``--no-preprocess`` and
``--policy predictive`` modes (issue 14).
"""
from __future__ import annotations

import json

import jsonschema
import pytest

from messages.config import RunConfig
from messages.logfile import read_log
from scripts.launch import launch

MODES = {
    "default": dict(),
    "no-preprocess": dict(preprocess=False),
    "predictive": dict(policy="predictive"),
}


@pytest.fixture(scope="module", params=sorted(MODES))
def launched_log(request, tmp_path_factory):
    config = RunConfig(particles=200, steps=15, seed=5, twin=f"t-schema-{request.param}", **MODES[request.param])
    path = tmp_path_factory.mktemp("schemas") / f"{request.param}.mcap"
    result = launch(config, log_path=path, timeout=5.0, notify=lambda text: None)
    assert result.exit_codes["entity"] == 0
    return request.param, read_log(path)


def test_every_json_message_validates_against_its_embedded_schema(launched_log):
    mode, log = launched_log
    validators, checked, failures = {}, 0, []
    for message in log.messages:
        channel = log.channels[message.channel_id]
        if channel.message_encoding != "json":
            continue
        if channel.schema_id not in validators:
            schema = json.loads(log.schemas[channel.schema_id].data)
            cls = jsonschema.validators.validator_for(schema, default=jsonschema.Draft202012Validator)
            cls.check_schema(schema)
            validators[channel.schema_id] = cls(schema)
        errors = list(validators[channel.schema_id].iter_errors(json.loads(message.data)))
        checked += 1
        if errors:
            failures.append(f"{channel.topic}: {errors[0].message} at {list(errors[0].path)}")
    assert checked > 15, f"{mode}: only {checked} JSON messages"  # at least one estimate a step
    assert failures == [], f"{mode}: {len(failures)} of {checked} invalid, e.g. " + "; ".join(failures[:5])


def test_a_video_launch_without_steps_runs_the_videos_frames_and_too_many_steps_is_one_line(tmp_path):
    import subprocess
    import sys

    from conftest import ROOT

    done = subprocess.run([sys.executable, "-m", "scripts.cli", "run", "--scenario", "video", "-q", "--particles",
                           "100", "--steps", "51"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "--steps: the video scenario can simulate at most 50 steps, got 51" in done.stderr
    assert "Traceback" not in done.stderr
    done = subprocess.run([sys.executable, "-m", "scripts.cli", "run", "--scenario", "video", "-q", "--particles",
                           "100"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "T = 50" in done.stdout
