"""Tests of the messages package: models, codec, keys, schemas.

Three levels, as in mcap's own tests: round trips (in memory and through an
MCAP file), corrupted payloads with the error text pinned, and the Foxglove
subset of every JSON Schema.
"""
from __future__ import annotations

import io
import json
import math
import pickle
import struct

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from pydantic import BaseModel, ValidationError

from dtpf.messages import (
    Estimate,
    Layer,
    McapDecoderFactory,
    MessageError,
    ParticleSet,
    PSCommand,
    Status,
    Time,
    WeightState,
    decode,
    decode_for_key,
    encode,
    json_schema,
    keys,
    message_encoding,
    schema_for,
)
from dtpf.messages.arrays import check_particles, check_weights
from dtpf.messages.codec import ENVELOPE_ENCODING, EnvelopeHeader
from dtpf.messages.foxglove import CompressedImage, ImageAnnotations, PointCloud
from dtpf.messages.keys import MESSAGE_CLASSES
from dtpf.messages.models import Control, Missed, Observation, ParticleSetHeader, Rejected
from dtpf.messages.schema import foxglove_problems

HEADER = dict(run_id="run-1", twin_id="ungm-1", step=7, stamp=Time(sec=1_700_000_000, nsec=123_456_789))


# --- message factories ---

def particle_set(n=5, d=1, kind="propagated", seed=0, **changes) -> ParticleSet:
    rng = np.random.default_rng(seed)
    particles = rng.normal(size=(n, d)) if d > 1 else rng.normal(size=n)
    weights = rng.random(n)
    weights /= weights.sum()
    fields = dict(HEADER, kind=kind, particles=particles, weights=weights, observation=[0.25])
    if kind == "preprocessed":
        fields.update(ps=0.81, threshold=float(np.sort(weights)[-1]) if n else 0.0,
                      n_large=1, n_processed=n - 1, n_mixed=(n - 1) // 2, n_plain=n - 1 - (n - 1) // 2)
    fields.update(changes)
    return ParticleSet(**fields)


def weight_state(**changes) -> WeightState:
    fields = dict(HEADER, n=100, ess=42.5, ess_ratio=0.425, entropy=3.9, entropy_ratio=0.85, max_weight=0.2,
                  threshold=0.01, n_above_threshold=40, distinct=93, q10=0.001, q50=0.008, q90=0.02, q99=0.15,
                  ps=0.81, n_large=40, n_processed=60, n_mixed=49, n_plain=11)
    fields.update(changes)
    return WeightState(**fields)


def ps_command(**changes) -> PSCommand:
    fields = dict(HEADER, ps=0.5, applies_from_step=8, policy="ess-band", reason="ESS ratio 0.31 < 0.4",
                  predicted_ess_ratio=0.45, predicted_distinct_ratio=None)
    fields.update(changes)
    return PSCommand(**fields)


def estimate(**changes) -> Estimate:
    fields = dict(HEADER, mean=[1.5, -2.0], var=[0.3, 0.0], lower=[0.4, -2.0], upper=[2.6, -2.0], ess=312.0,
                  ess_ratio=0.624, resampled=True, degraded=False, truth=[1.2, -1.9], observation=[3.0], ps=0.81)
    fields.update(changes)
    return Estimate(**fields)


def status(**changes) -> Status:
    fields = dict(HEADER, step=0, layer="recorder", state="running", pid=4242, received=10, rejected=1,
                  last_error="bad payload", peers_alive=["entity", "system"])
    fields.update(changes)
    return Status(**fields)


ALL_MESSAGES = [
    pytest.param(lambda: particle_set(), id="ParticleSet-propagated"),
    pytest.param(lambda: particle_set(n=6, d=3, kind="preprocessed"), id="ParticleSet-preprocessed"),
    pytest.param(weight_state, id="WeightState"),
    pytest.param(ps_command, id="PSCommand"),
    pytest.param(estimate, id="Estimate"),
    pytest.param(status, id="Status"),
]


def assert_same(a: BaseModel, b: BaseModel) -> None:
    """Field by field; arrays bit for bit, with dtype and shape."""
    assert type(a) is type(b)
    for name in type(a).model_fields:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert y.dtype == np.float64 and x.shape == y.shape, name
            assert x.tobytes() == y.tobytes(), name
        else:
            assert x == y and type(x) is type(y), name


# --- round trips ---

@pytest.mark.parametrize("make", ALL_MESSAGES)
def test_round_trip_every_message(make):
    message = make()
    payload = encode(message)
    assert isinstance(payload, bytes)
    for decoded in (decode(payload), decode(payload, type(message)), decode_for_key(keys.key_for(message), payload)):
        assert_same(decoded, message)
        assert decoded == message


@pytest.mark.parametrize("n", [1, 1000, 100_000])
@pytest.mark.parametrize("d", [1, 3])
def test_particle_set_round_trip_bit_exact(n, d):
    message = particle_set(n=n, d=d, seed=n + d)
    decoded = decode(encode(message), ParticleSet)
    assert decoded.particles.shape == (n, d) and decoded.weights.shape == (n,)
    assert_same(decoded, message)


def test_one_dimensional_particles_become_a_column():
    x = np.array([0.5, -1.0, 2.0])
    message = particle_set(n=3, particles=x)
    assert message.particles.shape == (3, 1)
    assert message.particles[:, 0].tobytes() == x.tobytes()
    assert decode(encode(message)).particles.shape == (3, 1)


def test_round_trip_keeps_awkward_floats_exact():
    weights = np.array([5e-324, 0.1, 0.2, 0.7 - 5e-324])
    particles = np.array([-0.0, 1e308, -1e-308, math.pi])
    message = particle_set(n=4, particles=particles, weights=weights, observation=[1e-300, -0.0])
    decoded = decode(encode(message))
    assert decoded.particles.tobytes() == message.particles.tobytes()
    assert decoded.weights.tobytes() == message.weights.tobytes()
    assert decoded.observation == [1e-300, -0.0]


def test_decoded_arrays_are_read_only_views():
    payload = bytearray(encode(particle_set()))
    decoded = decode(payload)
    for array in (decoded.particles, decoded.weights):
        assert not array.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 1.0
    assert np.shares_memory(decoded.weights, np.frombuffer(payload, np.uint8))  # zero copy, as documented


def test_constructed_arrays_are_read_only_without_touching_the_input():
    x, w = np.arange(4.0), np.full(4, 0.25)
    message = particle_set(n=4, particles=x, weights=w)
    assert not message.weights.flags.writeable and not message.particles.flags.writeable
    assert x.flags.writeable and w.flags.writeable


def test_json_messages_are_plain_json():
    payload = encode(weight_state())
    obj = json.loads(payload)
    assert obj["q99"] == 0.15 and obj["stamp"] == {"sec": 1_700_000_000, "nsec": 123_456_789}
    assert obj["layer"] == "information" and obj["step"] == 7


def test_stamp_and_layer_default_when_built_in_python():
    message = WeightState(**{k: v for k, v in weight_state().model_dump().items() if k not in ("stamp", "layer")})
    assert message.layer == Layer.INFORMATION
    assert abs(message.stamp.to_ns() - Time.now().to_ns()) < 60 * 10**9


def test_time_from_ns_round_trip():
    assert Time.from_ns(1_700_000_000_123_456_789) == Time(sec=1_700_000_000, nsec=123_456_789)
    assert Time.from_ns(1_700_000_000_123_456_789).to_ns() == 1_700_000_000_123_456_789


# --- construction rejects bad values (pydantic ValidationError, a ValueError) ---

@pytest.mark.parametrize("make, match", [
    (lambda: particle_set(weights=np.array([0.5, np.nan, 0.5, 0.0, 0.0])), "weights contain NaN values at index 1"),
    (lambda: particle_set(weights=np.array([0.6, -0.1, 0.5, 0.0, 0.0])), "weights contain negative values at index 1"),
    (lambda: particle_set(weights=np.full(5, 0.3)), "weights must sum to 1"),
    (lambda: particle_set(weights=np.full(4, 0.25)), "particles and weights differ in length: 5 particles, 4 weights"),
    (lambda: particle_set(particles=np.array([0.0, np.inf, 1.0, 2.0, 3.0])), "particles contain non-finite values"),
    (lambda: particle_set(kind="preprocessed", ps=1.5), r"ps must be in \[0, 1\], got 1.5"),
    (lambda: particle_set(kind="preprocessed", ps=None), "must say which ps was used"),
    (lambda: particle_set(ps=0.5), "a propagated particle set carries no preprocessing fields, got ps"),
    (lambda: particle_set(kind="preprocessed", n_mixed=3), "n_mixed \\+ n_plain must equal n_processed"),
    (lambda: particle_set(kind="preprocessed", n_large=3), "n_large \\+ n_processed must be at most N=5"),
    (lambda: particle_set(layer="system"), "ParticleSet is produced by the entity layer, got layer='system'"),
    (lambda: particle_set(kind="sideways"), "kind\n  Input should be 'propagated' or 'preprocessed'"),
    (lambda: particle_set(twin_id="a/b"), "twin_id must be non-empty and use only letters"),
    (lambda: particle_set(run_id=""), "run_id must be non-empty"),
    (lambda: particle_set(step=-1), "step\n  Input should be greater than or equal to 0"),
    (lambda: particle_set(observation=[float("nan")]), "observation.0\n  Input should be a finite number"),
    (lambda: weight_state(ess=float("inf")), "ess\n  Input should be a finite number"),
    (lambda: weight_state(q50=0.5), "weight quantiles must not decrease, got q50=0.5 > q90=0.02"),
    (lambda: weight_state(distinct=101), "distinct must be at most n=100"),
    (lambda: weight_state(layer="entity"), "WeightState is produced by the information layer"),
    (lambda: ps_command(ps=-0.01), r"ps must be in \[0, 1\], got -0.01"),
    (lambda: ps_command(applies_from_step=6), "applies_from_step must be >= step"),
    (lambda: ps_command(policy=""), "policy\n  String should have at least 1 character"),
    (lambda: estimate(var=[0.3]), "var must have length d=2 like mean, got 1"),
    (lambda: estimate(var=[0.3, -1.0]), "var.1\n  Input should be greater than or equal to 0"),
    (lambda: estimate(lower=[3.0, -2.0]), r"lower must not exceed upper, got lower\[0\]=3.0 > upper\[0\]=2.6"),
    (lambda: estimate(mean=[float("nan"), 0.0]), "mean.0\n  Input should be a finite number"),
    (lambda: status(peers_alive=["entity", "kitchen"]), "peers_alive.1\n  Input should be 'entity'"),
    (lambda: status(state="asleep"), "state\n  Input should be 'starting', 'running', 'waiting', 'finished' or 'failed'"),
    (lambda: status(extra_field=1), "extra_field\n  Extra inputs are not permitted"),
    (lambda: Time(sec=1, nsec=10**9), "nsec\n  Input should be less than or equal to 999999999"),
])
def test_construction_rejects(make, match):
    with pytest.raises(ValidationError, match=match):
        make()


# --- decoding rejects bad payloads with a MessageError naming the problem ---

def envelope(header: dict | bytes, data: bytes = b"", version: int = 1, magic: bytes = b"DTPF") -> bytes:
    """Hand-made envelope, independent of the encoder."""
    raw = header if isinstance(header, bytes) else json.dumps(header).encode()
    pad = b"\0" * (-(12 + len(raw)) % 8)
    return struct.pack("<4sB3xI", magic, version, len(raw)) + raw + pad + data


def envelope_parts(message: ParticleSet) -> tuple[dict, int]:
    """(header dict, data start) of an encoded particle set, read by hand."""
    payload = encode(message)
    size = int.from_bytes(payload[8:12], "little")
    return json.loads(payload[12:12 + size]), (12 + size + 7) // 8 * 8


def test_hand_made_envelope_decodes():
    # Guards the tests below: the hand-made envelope is right when its content is.
    message = particle_set(n=3)
    header, _ = envelope_parts(message)
    data = message.particles.tobytes() + message.weights.tobytes()
    assert decode(envelope(header, data)) == message


def with_weights(weights, n=3) -> bytes:
    message = particle_set(n=n)
    header, _ = envelope_parts(message)
    return envelope(header, message.particles.tobytes() + np.asarray(weights, "<f8").tobytes())


@pytest.mark.parametrize("payload, expected, match", [
    (b"\x00\xffgarbage\x13", None, "payload is neither a dtpf-envelope \\(magic b'DTPF'\\) nor JSON"),
    (b"\x00\xffgarbage\x13", WeightState, "invalid WeightState: Invalid JSON"),
    (b"\x00\xffgarbage\x13", ParticleSet, "dtpf-envelope must start with magic b'DTPF', got b'\\\\x00\\\\xffga'"),
    (b"", ParticleSet, "truncated: 0 bytes, shorter than the 12-byte prefix"),
    (b"[1, 2]", None, "JSON payload must be an object, got list"),
    (b'{"x": 1}', None, r"JSON object with keys \['x'\] matches no message class"),
    ("not bytes", None, "payload must be bytes, bytearray or memoryview, got str"),
])
def test_decode_rejects_garbage(payload, expected, match):
    with pytest.raises(MessageError, match=match):
        decode(payload, expected)


def test_truncated_particle_set_is_rejected_at_every_stage():
    message = particle_set(n=4, d=2)
    payload = encode(message)
    _, data_start = envelope_parts(message)
    cases = {
        3: "shorter than the 12-byte prefix",
        11: "shorter than the 12-byte prefix",
        12: "header length \\d+ runs past the end of the 12-byte payload",
        40: "runs past the end of the 40-byte payload",
        data_start - 1: "runs past the end",
        data_start: "truncated: array particles needs bytes",
        data_start + 8 * 8 - 1: "truncated: array particles needs bytes",
        data_start + 8 * 8: "truncated: array weights needs bytes",
        len(payload) - 1: "truncated: array weights needs bytes",
    }
    for cut, match in cases.items():
        with pytest.raises(MessageError, match=match):
            decode(payload[:cut], ParticleSet)
    with pytest.raises(MessageError, match="truncated: array weights"):
        decode_for_key("dtpf/ungm-1/entity/particles", payload[:-8])
    assert decode(payload) == message  # the uncut payload is fine


@pytest.mark.parametrize("mutate, expected, match", [
    (lambda p: b"XTPF" + p[4:], ParticleSet, "must start with magic b'DTPF', got b'XTPF'"),
    (lambda p: b"XTPF" + p[4:], None, "neither a dtpf-envelope"),
    (lambda p: p[:4] + b"\x02" + p[5:], None, "dtpf-envelope version 2 is not supported"),
    (lambda p: p[:5] + b"\x01" + p[6:], None, "reserved bytes 5-7 must be zero"),
    (lambda p: p[:8] + struct.pack("<I", 2**32 - 1) + p[12:], None, "header length 4294967295 runs past the end"),
    (lambda p: p + b"\0" * 8, None, "length mismatch: header and arrays need \\d+ bytes, payload has"),
])
def test_decode_rejects_broken_envelope(mutate, expected, match):
    payload = encode(particle_set())
    with pytest.raises(MessageError, match=match):
        decode(mutate(payload), expected)


@pytest.mark.parametrize("edit, match", [
    (lambda h: h["arrays"].reverse(), r"arrays must be \['particles', 'weights'\] in this order"),
    (lambda h: h["arrays"][1].update(offset=0), "array weights must start at data offset 24, header says 0"),
    (lambda h: h["arrays"][0].update(dtype=">f8"), "arrays.0.dtype: Input should be '<f8'"),
    (lambda h: h["arrays"][0].update(shape=[3]), r"shapes must be \[N, d\] and \[N\]"),
    (lambda h: h["arrays"][0].update(shape=[-3, 1]), "arrays.0.shape.0: Input should be greater than or equal to 0"),
    (lambda h: h.update(message="dtpf.Other"), "message: Input should be 'dtpf.ParticleSet'"),
    (lambda h: h["fields"].update(step="7"), "fields.step: Input should be a valid integer"),
    (lambda h: h["fields"].update(ps=2.0), r"ps must be in \[0, 1\]"),
    (lambda h: h["fields"].update(twin_id="x*"), "twin_id must be non-empty"),
    (lambda h: h["fields"].pop("stamp"), "fields.stamp: Field required"),
    (lambda h: h["fields"].update(observation=[None]), "fields.observation.0: Input should be a valid number"),
])
def test_decode_rejects_bad_envelope_header(edit, match):
    message = particle_set(n=3)
    header, _ = envelope_parts(message)
    edit(header)
    payload = envelope(header, message.particles.tobytes() + message.weights.tobytes())
    with pytest.raises(MessageError, match=match):
        decode(payload)


def test_decode_rejects_nonzero_padding():
    for n in range(3, 40):  # a set whose header length needs padding
        payload = bytearray(encode(particle_set(n=n)))
        size = int.from_bytes(payload[8:12], "little")
        start = 12 + size
        if start % 8:
            break
    assert start % 8, "this header needs padding"
    payload[start] = 1
    with pytest.raises(MessageError, match=f"padding bytes {start}-"):
        decode(bytes(payload))


def test_decode_rejects_header_that_is_not_json():
    with pytest.raises(MessageError, match="invalid dtpf-envelope header: Invalid JSON"):
        decode(envelope(b"{not json", b"\0" * 16))


@pytest.mark.parametrize("weights, match", [
    ([0.5, np.nan, 0.5], "weights contain NaN values at index 1"),
    ([0.5, np.inf, 0.5], "weights contain infinite values at index 1"),
    ([0.6, -0.1, 0.5], "weights contain negative values at index 1"),
    ([0.5, 0.5, 0.5], "weights must sum to 1 .*got sum 1.5"),
])
def test_decode_rejects_bad_weights(weights, match):
    with pytest.raises(MessageError, match=f"invalid ParticleSet: weights: Value error, {match}") as info:
        decode(with_weights(weights))
    assert info.value.step == 7


def _reference_weights_verdict(w, normalised):
    """What check_weights decided before its two-reduction fast path: the error's first words, or None."""
    if not np.isfinite(w).all():
        return "NaN" if np.isnan(w).any() else "infinite"
    if (w < 0).any():
        return "negative"
    total = float(w.sum())
    if total <= 0.0:
        return "all zero"
    if normalised and abs(total - 1.0) > 1e-6:
        return "sum to 1"
    return None


@pytest.mark.parametrize("values", [
    [0.5, 0.5], [np.nan, 1.0], [1.0, np.nan], [np.inf, 0.0], [-np.inf, 1.0], [np.inf, -np.inf],
    [-0.0, 1.0], [-1e-300, 1.0], [0.0, 0.0], [1e308, 1e308], [0.7, 0.7], [np.nan, -1.0], [-1.0, np.inf],
])
@pytest.mark.parametrize("normalised", [True, False])
def test_check_weights_decides_as_the_full_passes_do(values, normalised):
    w = np.array(values)
    expected = _reference_weights_verdict(w, normalised)
    if expected is None:
        assert check_weights(w, normalised=normalised) is not None
    else:
        with pytest.raises(ValueError, match=expected):
            check_weights(w, normalised=normalised)


@pytest.mark.parametrize("values, ok", [
    ([[0.0], [1.0]], True), ([[1e308], [1e308]], True), ([[np.nan], [0.0]], False), ([[np.inf], [-np.inf]], False),
    ([[0.0, -np.inf]], False),
])
def test_check_particles_finds_every_non_finite_value(values, ok):
    x = np.array(values)
    if ok:
        assert check_particles(x) is not None
    else:
        with pytest.raises(ValueError, match="non-finite values at index"):
            check_particles(x)


def test_decode_rejects_nan_particles():
    message = particle_set(n=3)
    header, _ = envelope_parts(message)
    particles = np.array([0.0, np.nan, 1.0])
    with pytest.raises(MessageError, match="particles contain non-finite values at index 1"):
        decode(envelope(header, particles.tobytes() + message.weights.tobytes()))


def test_decode_rejects_length_mismatch():
    message = particle_set(n=3)
    header, _ = envelope_parts(message)
    header["arrays"][1].update(shape=[4])
    weights = np.full(4, 0.25)
    with pytest.raises(MessageError, match="particles and weights differ in length: 3 particles, 4 weights"):
        decode(envelope(header, message.particles.tobytes() + weights.tobytes()))


def json_payload(message: BaseModel, **changes) -> bytes:
    obj = json.loads(encode(message))
    obj.update(changes)
    return json.dumps(obj).encode()


@pytest.mark.parametrize("payload, cls, match", [
    (json_payload(weight_state(), step="7"), WeightState, r"step: Input should be a valid integer \(got '7'\)"),
    (json_payload(weight_state(), n=100.5), WeightState, "n: Input should be a valid integer"),
    (json_payload(weight_state(), ps="0.5"), WeightState, "ps: Input should be a valid number"),
    (json_payload(weight_state(), ess=None), WeightState, "ess: Input should be a valid number"),
    (json_payload(estimate(), resampled="yes"), Estimate, "resampled: Input should be a valid boolean"),
    (json_payload(estimate(), mean=1.0), Estimate, "mean: Input should be a valid array \\(got 1.0\\)"),
    (json_payload(status(), stamp={"sec": -1, "nsec": 0}), Status, "stamp.sec: Input should be greater than"),
    (json_payload(ps_command(), ps=1.5), PSCommand, r"ps: Value error, ps must be in \[0, 1\], got 1.5"),
    (json_payload(ps_command(), twin_id="a b"), PSCommand, "twin_id must be non-empty .*got 'a b'"),
    (json_payload(ps_command(), layer="system2"), PSCommand, "layer: Input should be 'entity'"),
    (json_payload(ps_command(), mood=1), PSCommand, "mood: Extra inputs are not permitted"),
    (encode(weight_state()).replace(b'"ess":42.5', b'"ess":NaN'), WeightState, "ess: Input should be a finite number"),
    (encode(weight_state()).replace(b'"ess":42.5', b'"ess":1e999'), WeightState, "ess: Input should be a finite"),
    (encode(weight_state())[:-1], WeightState, "invalid WeightState: Invalid JSON: EOF"),
])
def test_decode_rejects_bad_json(payload, cls, match):
    with pytest.raises(MessageError, match=match):
        decode(payload, cls)


def test_decoded_json_must_carry_stamp_and_layer():
    obj = json.loads(encode(ps_command()))
    for name in ("stamp", "layer"):
        payload = json.dumps({k: v for k, v in obj.items() if k != name}).encode()
        with pytest.raises(MessageError, match=f"{name}: Field required"):
            decode(payload, PSCommand)


def test_decode_rejects_the_wrong_class():
    with pytest.raises(MessageError, match="expected a JSON WeightState payload, got a dtpf-envelope payload"):
        decode(encode(particle_set()), WeightState)
    with pytest.raises(MessageError, match="must start with magic"):
        decode(encode(weight_state()), ParticleSet)
    with pytest.raises(MessageError, match="PSCommand: .*Extra inputs are not permitted"):
        decode(encode(weight_state()), PSCommand)


@pytest.mark.parametrize("key, make, match", [
    ("dtpf/other/information/weight_state", weight_state, "twin_id 'ungm-1' \\(key says 'other'\\)"),
    ("dtpf/ungm-1/information/preprocessed", particle_set,
     "layer 'entity' \\(key says 'information'\\), kind 'propagated' \\(key says 'preprocessed'\\)"),
    ("dtpf/ungm-1/system/status", status, "layer 'recorder' \\(key says 'system'\\)"),
    ("dtpf/ungm-1/system/weather", ps_command, "unknown topic system/weather"),
    ("dtpf/ungm-1/kitchen/ps", ps_command, "unknown layer 'kitchen'"),
    ("dtpf/ungm-1/system/ps", weight_state, "invalid PSCommand"),
])
def test_decode_for_key_rejects_messages_on_the_wrong_key(key, make, match):
    with pytest.raises(MessageError, match=match) as info:
        decode_for_key(key, encode(make()))
    assert info.value.key == key
    assert key in str(info.value)


def test_message_error_carries_fields_and_pickles():
    error = MessageError("weights contain NaN", key="dtpf/a/entity/particles", step=3)
    assert isinstance(error, ValueError)
    assert (error.reason, error.key, error.step) == ("weights contain NaN", "dtpf/a/entity/particles", 3)
    assert str(error) == "weights contain NaN (key dtpf/a/entity/particles, step 3)"
    clone = pickle.loads(pickle.dumps(error))
    assert (clone.reason, clone.key, clone.step) == (error.reason, error.key, error.step)


def test_encode_rejects_non_messages():
    with pytest.raises(TypeError, match="encode\\(\\) takes a dtpf message, got dict"):
        encode({"step": 1})


# --- keys ---

@pytest.mark.parametrize("twin", ["ungm-1", "A.b_c-9", "x"])
@pytest.mark.parametrize("topic", list(keys.TOPICS.values()), ids=lambda t: f"{t.layer.value}/{t.name}")
def test_keys_round_trip(twin, topic):
    key = keys.key(twin, topic.layer, topic.name)
    assert key == f"dtpf/{twin}/{topic.layer.value}/{topic.name}"
    assert keys.parse(key) == (twin, topic.layer, topic.name)
    assert keys.topic_of(key) is topic


def test_topic_table():
    table = {(layer.value, name): (t.message, t.kind and t.kind.value) for (layer, name), t in keys.TOPICS.items()}
    assert table[("entity", "particles")] == (ParticleSet, "propagated")
    assert table[("information", "preprocessed")] == (ParticleSet, "preprocessed")
    assert table[("information", "weight_state")] == (WeightState, None)
    assert table[("system", "ps")] == (PSCommand, None)
    assert table[("entity", "estimate")] == (Estimate, None)
    for layer in ("entity", "information", "system", "recorder"):
        assert table[(layer, "status")] == (Status, None)
    assert table[("entity", "frame")] == (CompressedImage, None)
    assert table[("sensor", "observation")] == (Observation, None)
    assert table[("sensor", "control")] == (Control, None)
    assert table[("sensor", "status")] == (Status, None)
    assert table[("recorder", "rejected")] == (Rejected, None)
    assert table[("recorder", "missed")] == (Missed, None)
    assert table[("entity", "cloud")] == (PointCloud, None)
    assert table[("entity", "annotations")] == (ImageAnnotations, None)
    from dtpf.messages.models import ForecastBand

    assert table[("entity", "forecast_band")] == (ForecastBand, None)
    assert len(table) == 18


@pytest.mark.parametrize("make, key", [
    (particle_set, "dtpf/ungm-1/entity/particles"),
    (lambda: particle_set(kind="preprocessed"), "dtpf/ungm-1/information/preprocessed"),
    (weight_state, "dtpf/ungm-1/information/weight_state"),
    (ps_command, "dtpf/ungm-1/system/ps"),
    (estimate, "dtpf/ungm-1/entity/estimate"),
    (status, "dtpf/ungm-1/recorder/status"),
])
def test_key_for_message(make, key):
    assert keys.key_for(make()) == key


@pytest.mark.parametrize("key, match", [
    ("", "must start with 'dtpf/'"),
    ("zenoh/ungm-1/entity/particles", "must start with 'dtpf/', got 'zenoh/"),
    ("dtpf/ungm-1/entity", "4 chunks\\), got 3 chunks"),
    ("dtpf/ungm-1/entity/particles/extra", "got 5 chunks"),
    ("dtpf//entity/particles", "twin id must be non-empty"),
    ("dtpf/a*b/entity/particles", "twin id must be non-empty .*got 'a\\*b'"),
    ("dtpf/**", "got 2 chunks"),
    ("dtpf/a$b/entity/particles", "got 'a\\$b'"),
    ("dtpf/a?/entity/particles", "got 'a\\?'"),
    ("dtpf/a#/entity/particles", "got 'a#'"),
    ("dtpf/ungm-1/Entity/particles", "unknown layer 'Entity'; expected one of entity, information, system, recorder"),
    ("dtpf/ungm-1/entity/", "topic must be non-empty"),
    ("dtpf/ungm-1/entity/par ticles", "topic must be non-empty .*got 'par ticles'"),
    (None, "key expression must be a string, got None"),
])
def test_parse_rejects_bad_keys(key, match):
    with pytest.raises(ValueError, match=match):
        keys.parse(key)


def test_parse_caches_good_keys_within_a_bound_and_never_bad_ones():
    keys._PARSED.clear()
    good = "dtpf/cache-1/entity/particles"
    assert keys.parse(good) == keys.parse(good) == ("cache-1", Layer.ENTITY, "particles")
    assert good in keys._PARSED
    with pytest.raises(ValueError):
        keys.parse("dtpf/a*b/entity/particles")
    assert "dtpf/a*b/entity/particles" not in keys._PARSED
    for i in range(3 * keys._PARSED_MAX):  # a flood of made-up keys
        keys.parse(f"dtpf/flood-{i}/entity/particles")
    assert 0 < len(keys._PARSED) <= keys._PARSED_MAX
    keys._PARSED.clear()


def test_key_for_remembers_keys_within_a_bound_and_gives_each_message_its_own():
    keys._KEYS.clear()
    propagated, preprocessed = particle_set(), particle_set(kind="preprocessed")
    assert keys.key_for(propagated) == keys.key_for(propagated) == f"dtpf/{propagated.twin_id}/entity/particles"
    assert keys.key_for(preprocessed) == f"dtpf/{preprocessed.twin_id}/information/preprocessed"
    assert keys.key_for(estimate(twin_id="other")) == "dtpf/other/entity/estimate"
    for i in range(2 * keys._PARSED_MAX):  # a fleet of many twins
        assert keys.key_for(status(twin_id=f"t-{i}")) == f"dtpf/t-{i}/recorder/status"
    assert 0 < len(keys._KEYS) <= keys._PARSED_MAX
    keys._KEYS.clear()


@pytest.mark.parametrize("twin, layer, topic, match", [
    ("a/b", "entity", "particles", "twin id .*got 'a/b'"),
    ("", "entity", "particles", "twin id must be non-empty"),
    ("a", "sensors", "particles", "unknown layer 'sensors'"),
    ("a", "entity", "x/y", "topic must be non-empty .*got 'x/y'"),
])
def test_key_rejects_bad_parts(twin, layer, topic, match):
    with pytest.raises(ValueError, match=match):
        keys.key(twin, layer, topic)


def test_subscribe_patterns():
    assert keys.twin_pattern("ungm-1") == "dtpf/ungm-1/**"
    assert keys.ALL == "dtpf/**"
    with pytest.raises(ValueError, match="twin id"):
        keys.twin_pattern("*")


# --- JSON Schemas: the Foxglove subset ---

def forbidden_constructs(node, path="$") -> list[str]:
    """Every $ref, $defs, anyOf/oneOf/allOf, null type and array of arrays, recursively."""
    found = []
    if isinstance(node, list):
        for i, item in enumerate(node):
            found += forbidden_constructs(item, f"{path}[{i}]")
        return found
    if not isinstance(node, dict):
        return found
    for key in ("$ref", "$defs", "anyOf", "oneOf", "allOf"):
        if key in node:
            found.append(f"{path}.{key}")
    kind = node.get("type")
    if kind == "null" or (isinstance(kind, list) and "null" in kind):
        found.append(f"{path}.type null")
    if node.get("default", 0) is None:
        found.append(f"{path}.default null")
    if kind == "array" and isinstance(node.get("items"), dict) and node["items"].get("type") == "array":
        found.append(f"{path} array of arrays")
    if isinstance(node.get("properties"), dict):
        for name, sub in node["properties"].items():
            if "type" not in sub:
                found.append(f"{path}.{name} without type")
    for key, value in node.items():
        found += forbidden_constructs(value, f"{path}.{key}")
    return found


SCHEMA_MODELS = [cls for cls in MESSAGE_CLASSES.values() if cls is not ParticleSet] + [
    EnvelopeHeader, ParticleSetHeader, Time]


@pytest.mark.parametrize("cls", SCHEMA_MODELS, ids=lambda c: c.__name__)
def test_json_schema_is_foxglove_readable(cls):
    raw = cls.model_json_schema(mode="serialization")
    schema = json_schema(cls)
    assert schema["type"] == "object"
    assert forbidden_constructs(schema) == []
    assert foxglove_problems(schema) == []
    assert set(schema["properties"]) == set(raw["properties"])  # nothing lost
    json.dumps(schema)


def test_forbidden_constructs_are_found():
    # The checks above can fail: pydantic's own output has every construct.
    found = " ".join(forbidden_constructs(WeightState.model_json_schema()))
    assert "$defs" in found and "$ref" in found and "anyOf" in found and "type null" in found
    assert foxglove_problems(WeightState.model_json_schema())


def test_optional_fields_collapse_and_leave_required():
    schema = json_schema(WeightState)
    assert schema["properties"]["n_large"]["type"] == "integer"
    assert schema["properties"]["n_large"]["description"].startswith("M: particles")
    assert "n_large" not in schema["required"] and "ess" in schema["required"]
    assert schema["properties"]["stamp"]["properties"]["nsec"]["type"] == "integer"
    assert schema["properties"]["layer"]["enum"] == ["entity", "information", "system", "recorder", "sensor"]
    estimate_schema = json_schema(Estimate)
    assert estimate_schema["properties"]["truth"] == {
        "type": "array", "items": {"type": "number"}, "description": "(d,) true state, when simulated.",
        "title": "Truth"}


def test_json_schema_refuses_what_foxglove_cannot_read():
    class Union(BaseModel):
        value: int | str

    with pytest.raises(ValueError, match="Union.value: a union of 2 types"):
        json_schema(Union)
    with pytest.raises(ValueError, match="ParticleSet.particles\\[\\]: arrays of arrays"):
        json_schema(ParticleSet)


@pytest.mark.parametrize("cls", list(MESSAGE_CLASSES.values()), ids=lambda c: c.__name__)
def test_schema_for_mcap(cls):
    record = schema_for(cls)
    expected_name = {CompressedImage: "foxglove.CompressedImage", PointCloud: "foxglove.PointCloud",
                     ImageAnnotations: "foxglove.ImageAnnotations"}.get(
        cls, f"dtpf.{cls.__name__}")
    assert record.name == expected_name and record.encoding == "jsonschema"
    schema = json.loads(record.data)
    assert forbidden_constructs(schema) == []
    if cls is ParticleSet:
        assert message_encoding(cls) == ENVELOPE_ENCODING
        assert json.loads(schema["$comment"])["magic"] == "DTPF"
        assert "little-endian float64" in schema["description"]
        assert set(schema["properties"]) == {"message", "fields", "arrays"}
    else:
        assert message_encoding(cls) == "json"
        assert set(schema["properties"]) == set(cls.model_fields)


def test_a_recording_of_many_twins_makes_each_schema_once(tmp_path, monkeypatch):
    # A fleet's recorder opens a channel per twin and topic; pydantic's JSON Schema took 10 ms each time,
    # 8.3 s of a 100-twin recorder's 38.7 s of CPU.
    import dtpf.messages.codec as codec
    from dtpf.recording.writer import McapRecording
    made = []
    real = codec.json_schema
    monkeypatch.setattr(codec, "json_schema", lambda cls: made.append(cls) or real(cls))
    clear = getattr(codec.schema_for, "cache_clear", lambda: None)
    clear()
    try:
        with McapRecording(tmp_path / "fleet.mcap") as recording:
            for twin in range(30):
                for message in (estimate(twin_id=f"t-{twin}"), status(twin_id=f"t-{twin}")):
                    recording.write(keys.key_for(message), encode(message))
    finally:
        clear()  # the next test makes them with the real function again
    assert sorted(cls.__name__ for cls in made) == ["Estimate", "Status"]
    with open(tmp_path / "fleet.mcap", "rb") as log:
        summary = make_reader(log).get_summary()
    assert len(summary.channels) == 60 and len(summary.schemas) == 2


# --- MCAP: self-describing files ---

def record(messages) -> io.BytesIO:
    out = io.BytesIO()
    writer = Writer(out)
    writer.start()
    channels = {}
    for message in messages:
        key, cls = keys.key_for(message), type(message)
        if key not in channels:
            schema_id = writer.register_schema(*schema_for(cls))
            channels[key] = writer.register_channel(key, message_encoding(cls), schema_id)
        writer.add_message(channels[key], log_time=message.stamp.to_ns(), data=encode(message),
                           publish_time=message.stamp.to_ns(), sequence=message.step)
    writer.finish()
    out.seek(0)
    return out


def test_mcap_round_trip_with_decoder_factory():
    messages = [particle_set(n=50, d=2), particle_set(kind="preprocessed"), weight_state(), ps_command(),
                estimate(), status()]
    reader = make_reader(record(messages), decoder_factories=[McapDecoderFactory()])
    decoded = [message for _, channel, _, message in reader.iter_decoded_messages()]
    assert len(decoded) == len(messages)
    for got, want in zip(decoded, messages):
        assert_same(got, want)


def test_mcap_file_decodes_with_only_mcap_json_and_numpy():
    # The recipe of docs/guides/encoding.md, without importing dtpf.
    message = particle_set(n=20, d=3, kind="preprocessed")
    reader = make_reader(record([message, weight_state()]))
    seen = {}
    for schema, channel, raw in reader.iter_messages():
        if channel.message_encoding == "dtpf-envelope":
            assert json.loads(json.loads(schema.data)["$comment"])["version"] == raw.data[4] == 1
            p = raw.data
            assert p[:4] == b"DTPF"
            h = int.from_bytes(p[8:12], "little")
            header = json.loads(p[12:12 + h])
            start = (12 + h + 7) // 8 * 8
            arrays = {a["name"]: np.frombuffer(p, a["dtype"], count=math.prod(a["shape"]),
                                               offset=start + a["offset"]).reshape(a["shape"])
                      for a in header["arrays"]}
            seen[channel.topic] = (header["fields"], arrays)
        else:
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            seen[channel.topic] = json.loads(raw.data)
    fields, arrays = seen["dtpf/ungm-1/information/preprocessed"]
    assert fields["ps"] == 0.81 and fields["kind"] == "preprocessed"
    assert arrays["particles"].tobytes() == message.particles.tobytes()
    assert arrays["weights"].tobytes() == message.weights.tobytes()
    assert seen["dtpf/ungm-1/information/weight_state"]["q99"] == 0.15


def test_arrays_checked_context_skips_only_the_value_scan():
    from dtpf.messages.models import ARRAYS_CHECKED

    fields = dict(run_id="r", twin_id="t", step=1, kind="propagated")
    bad = np.array([0.5, np.nan, 0.5])
    x = np.zeros((3, 1))
    # A layer's own, already checked output: the values are not scanned again ...
    trusted = ParticleSet.model_validate(dict(fields, particles=x, weights=bad), context=ARRAYS_CHECKED)
    assert not trusted.weights.flags.writeable and not trusted.particles.flags.writeable
    # ... but without the context (every receiver) they are, and the rest is always checked.
    with pytest.raises(ValidationError, match="weights contain NaN values at index 1"):
        ParticleSet.model_validate(dict(fields, particles=x, weights=bad))
    with pytest.raises(ValidationError, match="particles and weights differ in length"):
        ParticleSet.model_validate(dict(fields, particles=np.zeros((4, 1)), weights=np.full(3, 1 / 3)),
                                   context=ARRAYS_CHECKED)
    with pytest.raises(ValidationError, match="ps must be in"):
        ParticleSet.model_validate(dict(fields, kind="preprocessed", ps=1.5, particles=x, weights=np.full(3, 1 / 3)),
                                   context=ARRAYS_CHECKED)
    # Not float64 or not the right rank: checked in full, context or not.
    with pytest.raises(ValidationError, match="weights must be 1-D"):
        ParticleSet.model_validate(dict(fields, particles=x, weights=np.full((3, 1), 1 / 3)), context=ARRAYS_CHECKED)
    as_list = ParticleSet.model_validate(dict(fields, particles=[[0.0], [1.0]], weights=[0.5, 0.5]),
                                         context=ARRAYS_CHECKED)
    assert as_list.particles.dtype == np.float64 and as_list.particles.shape == (2, 1)


def test_check_set_trusts_only_float64_arrays_of_the_right_shapes():
    from dtpf.messages.arrays import check_set

    x, w = np.zeros((3, 2)), np.array([0.5, np.nan, 0.5])
    px, pw = check_set(x, w, checked=True)
    assert px is x and pw is w  # passed through, not scanned
    with pytest.raises(ValueError, match="weights contain NaN values at index 1"):
        check_set(x, w)
    with pytest.raises(ValueError, match="particles and weights differ in length: 4 particles, 3 weights"):
        check_set(np.zeros((4, 2)), np.full(3, 1 / 3), checked=True)
    with pytest.raises(ValueError, match="weights must sum to 1"):
        check_set(x, np.ones(3, dtype=np.float32), checked=True)  # float32: checked in full


def test_streams_are_the_seed_sequences_generators():
    # stream() computes SeedSequence's state in a compiled pass: the generator must be numpy's own.
    from dtpf.messages import streams

    for seed in (0, 7, 2 ** 32 - 1, 2 ** 32, 2 ** 70 + 3):
        for twin in ("ungm-1", "", "a-twin-with-a-long-name-" * 3):
            for step in (0, 1, 99, 2 ** 33 + 1):
                for layer in streams.LAYERS:
                    expected = np.random.Generator(np.random.PCG64(streams.seed_sequence(seed, twin, step, layer)))
                    got = streams.stream(seed, twin, step, layer)
                    np.testing.assert_array_equal(got.integers(0, 2 ** 63, 4), expected.integers(0, 2 ** 63, 4))


@pytest.mark.parametrize("check", [
    "check_particles(np.array([[np.inf], [-np.inf]]))",  # the fast path's sum is NaN
    "check_weights(np.array([np.inf, -np.inf, 1.0]))",
    "check_particles(np.array([[1e308], [1e308]]))",  # the sum overflows; every value is finite
])
def test_hostile_arrays_are_named_without_a_numpy_warning(check):
    # A service would print numpy's "invalid value encountered in reduce" to its log for every first bad
    # set; with warnings as errors (a fresh process, the filter of dtpf.messages.arrays in force) none comes.
    import subprocess
    import sys

    from conftest import ROOT
    code = ("import numpy as np\nfrom dtpf.messages.arrays import check_particles, check_weights\n"
            f"try:\n    {check}\nexcept ValueError as error:\n    print('ValueError:', error)\nelse:\n    print('ok')\n")
    done = subprocess.run([sys.executable, "-W", "error::RuntimeWarning", "-c", code], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-1500:]
    assert done.stdout.startswith("ok" if "1e308" in check else "ValueError:"), done.stdout


def _b64decode_takes(text) -> bool:
    import base64
    import binascii
    try:
        base64.b64decode(text, validate=True)
        return True
    except (binascii.Error, ValueError, TypeError):
        return False


@pytest.mark.parametrize("text", ["", "=", "==", "A", "AA", "AA=", "AA==", "AAA=", "AAAA", "AAAA=", "AAAA==",
                                  "AAAA===", "AA===", "AAAAAA=====", "AA=A", "A=AA", "AAAAA", "AAAAAA==", "AAAAAAA=", "AAAA AAAA",
                                  "AAAA\n", "AA-_", "AAé=", "+/+/", "AAAAAA=="[::-1]])
def test_is_base64_takes_what_b64decode_takes(text):
    from dtpf.messages.models import is_base64
    assert is_base64(text) == _b64decode_takes(text)


def test_is_base64_agrees_with_b64decode_on_random_texts():
    """Texts of the base64 alphabet with a few '=', spaces, URL-safe and non-ASCII characters mixed in, of
    every length up to 40: the fast check takes exactly what b64decode(validate=True) takes."""
    import base64

    from dtpf.messages.models import is_base64
    rng = np.random.default_rng(5)
    alphabet = list("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/")
    odd = list("= -_\né\x00")
    taken = 0
    for _ in range(20_000):
        n = int(rng.integers(0, 41))
        chars = [alphabet[i] for i in rng.integers(0, len(alphabet), n)]
        if rng.random() < 0.5 and n:  # one odd character somewhere
            chars[int(rng.integers(0, n))] = odd[int(rng.integers(0, len(odd)))]
        text = "".join(chars) + "=" * int(rng.integers(0, 6))
        assert is_base64(text) == _b64decode_takes(text), repr(text)
        taken += is_base64(text)
    assert 1_000 < taken < 19_000  # both kinds were tried
    assert is_base64(base64.b64encode(np.arange(4000.0).tobytes()).decode())


@pytest.mark.parametrize("change", [
    {}, {"weights": [0.5, np.nan, 0.5]}, {"weights": [0.5, -0.1, 0.6]}, {"weights": [0.2, 0.2]},
    {"particles": [[0.0], [np.inf], [1.0]]}, {"particles": np.zeros((3, 1, 1))}, {"parents": 4},
    {"n_large": 2, "n_processed": 2, "n_mixed": 1, "n_plain": 1},
])
def test_a_set_from_a_validated_header_is_refused_or_taken_as_the_constructor_does(change):
    """ParticleSet.from_header (what decoding uses, the scalar fields validated once) refuses what the
    constructor refuses, with the same words, and builds an equal set otherwise."""
    header = {"run_id": "r", "twin_id": "t", "step": 3, "stamp": {"sec": 5, "nsec": 0}, "kind": "preprocessed",
              "ps": 0.5, "threshold": 0.1,
              "n_large": 1, "n_processed": 2, "n_mixed": 1, "n_plain": 1, "parents": 2}
    arrays = {"particles": [[0.0], [1.0], [2.0]], "weights": [0.2, 0.3, 0.5]}
    for name, value in change.items():
        (arrays if name in arrays else header)[name] = value
    try:
        built = ParticleSet(**header, **arrays)
    except ValidationError as error:
        expected = error.errors()[0]["msg"]
        with pytest.raises(ValueError) as info:
            ParticleSet.from_header(ParticleSetHeader(**header), **arrays)
        assert str(info.value).endswith(expected), (str(info.value), expected)
        return
    assert ParticleSet.from_header(ParticleSetHeader(**header), **arrays) == built


def test_a_payload_with_its_base64_spliced_in_is_the_payload_pydantic_writes():
    """encode_with_base64 (the entity's point cloud) gives the bytes of encode() with data = base64(raw),
    for raw bytes of every length mod 3 (the padding), and refuses a message whose data is not empty."""
    import base64

    from dtpf.messages.codec import encode_with_base64
    from dtpf.messages.foxglove import PackedElementField

    rng = np.random.default_rng(5)
    fields = [PackedElementField(name=name, offset=8 * i, type=8) for i, name in enumerate("xyz")]
    for size in (0, 1, 2, 3, 24, 32_000, 32_001):
        raw = rng.bytes(size)
        header = dict(run_id="r", twin_id="t", step=7, stamp={"sec": 3, "nsec": 4}, timestamp={"sec": 1, "nsec": 2},
                      frame_id='st"ate', point_stride=24, fields=fields)
        spliced = encode_with_base64(PointCloud(**header, data=""), raw)
        assert spliced == encode(PointCloud(**header, data=base64.b64encode(raw).decode("ascii")))
        assert base64.b64decode(decode(spliced, PointCloud).data) == raw
    with pytest.raises(ValueError, match="data="):
        encode_with_base64(PointCloud(**header, data="AAAA"), b"x")
