"""Every JSON message of a real launch log is valid against the schema embedded beside it.

Checked with an independent validator (``jsonschema``), not with the models
that wrote them, over launches in the default, ``--no-preprocess``, ``--policy predictive``
and ``--scenario video`` modes.
"""
from __future__ import annotations

import json

import jsonschema
import pytest

from dtpf.messages.config import RunConfig
from dtpf.recording.logfile import read_log
from dtpf.scripts.launch import launch

MODES = {
    "default": dict(),
    "no-preprocess": dict(preprocess=False),
    "predictive": dict(policy="predictive"),
    "video": dict(scenario="video"),
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

    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "run", "--scenario", "video", "-q", "--particles",
                           "100", "--steps", "51"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "--steps: the video scenario can simulate at most 50 steps, got 51" in done.stderr
    assert "Traceback" not in done.stderr
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "run", "--scenario", "video", "-q", "--particles",
                           "100"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "T = 50" in done.stdout


#: The keywords of JSON Schema 2020-12 (core, applicator, validation, meta-data, format, content).
KEYWORDS = {
    "$schema", "$id", "$ref", "$anchor", "$dynamicRef", "$dynamicAnchor", "$vocabulary", "$comment", "$defs",
    "allOf", "anyOf", "oneOf", "not", "if", "then", "else", "dependentSchemas", "prefixItems", "items", "contains",
    "properties", "patternProperties", "additionalProperties", "propertyNames", "unevaluatedItems",
    "unevaluatedProperties", "type", "enum", "const", "multipleOf", "maximum", "exclusiveMaximum", "minimum",
    "exclusiveMinimum", "maxLength", "minLength", "pattern", "maxItems", "minItems", "uniqueItems", "maxContains",
    "minContains", "maxProperties", "minProperties", "required", "dependentRequired", "title", "description",
    "default", "deprecated", "readOnly", "writeOnly", "examples", "format", "contentEncoding", "contentMediaType",
    "contentSchema",
}
_SCHEMA_MAPS = {"properties", "patternProperties", "$defs", "dependentSchemas"}
_SCHEMA_VALUES = {"items", "additionalProperties", "not", "if", "then", "else", "contains", "propertyNames",
                  "unevaluatedItems", "unevaluatedProperties", "contentSchema"}
_SCHEMA_LISTS = {"allOf", "anyOf", "oneOf", "prefixItems"}


def unknown_keywords(schema, path="#") -> list[str]:
    """Keywords a strict validator (ajv in strict mode) would refuse, with their paths."""
    if not isinstance(schema, dict):
        return []
    found = [f"{path}/{key}" for key in schema if key not in KEYWORDS]
    for key, value in schema.items():
        if key in _SCHEMA_MAPS and isinstance(value, dict):
            found += [item for name, sub in value.items() for item in unknown_keywords(sub, f"{path}/{key}/{name}")]
        elif key in _SCHEMA_VALUES:
            found += unknown_keywords(value, f"{path}/{key}")
        elif key in _SCHEMA_LISTS and isinstance(value, list):
            found += [item for i, sub in enumerate(value) for item in unknown_keywords(sub, f"{path}/{key}/{i}")]
    return found


def test_every_embedded_schema_uses_only_json_schema_keywords():
    # ajv in strict mode refuses a schema with a keyword it does not know (it refused "x-dtpf-envelope");
    # checked here keyword by keyword, so the test needs no JavaScript.
    from dtpf.messages.codec import envelope_layout, schema_for
    from dtpf.messages.keys import MESSAGE_CLASSES
    from dtpf.messages.models import ParticleSet

    for cls in MESSAGE_CLASSES.values():
        schema = json.loads(schema_for(cls).data)
        assert unknown_keywords(schema) == [], cls.__name__
        jsonschema.Draft202012Validator.check_schema(schema)
    layout = json.loads(json.loads(schema_for(ParticleSet).data)["$comment"])
    assert layout == envelope_layout() and layout["magic"] == "DTPF"
    assert unknown_keywords({"type": "object", "x-dtpf-envelope": {}}) == ["#/x-dtpf-envelope"]


def test_each_step_has_a_point_cloud_of_its_particle_set(launched_log):
    import base64

    import numpy as np

    from dtpf.messages.codec import decode_for_key
    from dtpf.messages.foxglove import PointCloud

    mode, log = launched_log
    clouds, sets = {}, {}
    for item in log.messages:
        if item.topic.endswith("/entity/cloud"):
            clouds[decode_for_key(item.topic, item.data).step] = decode_for_key(item.topic, item.data)
        elif item.topic.endswith("/entity/particles"):
            sets[decode_for_key(item.topic, item.data).step] = decode_for_key(item.topic, item.data)
    assert sorted(clouds) == list(range(1, 16))
    cloud = clouds[7]
    assert isinstance(cloud, PointCloud) and [f.name for f in cloud.fields] == ["x", "y", "z", "weight"]
    points = np.frombuffer(base64.b64decode(cloud.data), dtype="<f8").reshape(-1, 4)
    if sets:  # with preprocessing the propagated set is logged: the cloud is that set (N = 200 <= 1000)
        particles, weights = sets[7].particles, sets[7].weights
        np.testing.assert_array_equal(points[:, 0], particles[:, 0])
        np.testing.assert_array_equal(points[:, 3], weights)
        if particles.shape[1] == 1:  # a 1-D state is drawn with its relative weight as height
            np.testing.assert_allclose(points[:, 1], weights * 200)
        else:
            np.testing.assert_array_equal(points[:, 1], particles[:, 1])
    assert points.shape == (200, 4)


def test_a_cloud_of_a_large_set_is_every_stride_th_particle():
    import numpy as np

    from dtpf.entity.cloud import cloud_points

    rng = np.random.default_rng(0)
    particles = rng.standard_normal((10_001, 2))
    weights = rng.random(10_001)
    weights /= weights.sum()
    points = cloud_points(particles, weights, 1000)
    assert points.shape == (910, 4)  # stride ceil(10001 / 1000) = 11
    np.testing.assert_array_equal(points[:, :2], particles[::11])
    np.testing.assert_array_equal(points[:, 3], weights[::11])
    assert (points[:, 2] == 0).all()


def test_a_video_log_draws_each_steps_particles_and_estimate_over_its_frame(launched_log):
    from dtpf.messages.codec import decode_for_key

    mode, log = launched_log
    frames, annotations, estimates = {}, {}, {}
    for item in log.messages:
        name = item.topic.rsplit("/", 1)[1]
        if name in ("frame", "annotations", "estimate"):
            message = decode_for_key(item.topic, item.data)
            {"frame": frames, "annotations": annotations, "estimate": estimates}[name][message.step] = message
    if mode != "video":  # only the video scenario has frames to draw on
        assert annotations == {} and frames == {}
        return
    assert sorted(annotations) == sorted(frames) == list(range(1, 16))
    for step, drawn in annotations.items():
        (points,) = drawn.points
        assert 0 < len(points.points) <= 200 and points.timestamp == frames[step].timestamp
        (circle,) = drawn.circles
        assert (circle.position.x, circle.position.y) == tuple(estimates[step].mean[:2])
