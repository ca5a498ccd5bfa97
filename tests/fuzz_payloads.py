"""Hypothesis strategies for tests/test_fuzz.py: valid dtpf messages, and payloads and logs mutated from them.

Layers, each a small named strategy:

- **valid messages** of every class of :data:`dtpf.messages.keys.MESSAGE_CLASSES`, built
  with the real models (so they are valid by construction) from random but valid
  field values; particle sets with random N (1..64) and d (1..4). Two builders: the
  strategies (:data:`MESSAGE_STRATEGIES`, every field a hypothesis draw) and, for the
  10,000 starting points of the mutations, :func:`seeded_message` (hypothesis draws
  the class and a seed; a seeded RNG fills in edge-biased valid values; 20 times cheaper);
- **mutations** of their payloads: of the JSON tree (a value replaced by a wrong
  type, a wrong enum string, NaN, Infinity, a huge int or string, deep nesting;
  wrong run ids and steps; keys deleted, added, duplicated, reordered), of the binary
  envelope (claimed header size, version, reserved bytes, padding, array names,
  dtypes, shapes and offsets, the data section), and of the bytes (truncation,
  bit flips, splices, huge little-endian sizes);
- **raw** bytes and JSON-looking text from nowhere;
- **MCAP logs**: the messages of a recording (steps duplicated and out of order)
  and edits of its bytes, record by record (lengths, chunk fields, whole records
  duplicated, dropped, swapped).

JSON is re-serialised by :func:`dump_json` rather than :func:`json.dumps`, so that
objects may hold duplicate keys in any order, and a value may be raw text that no
Python object prints as (``1e999``, 5,000-digit integers, 10,000 nested ``[``).
"""
from __future__ import annotations

import base64
import json
import math
import random
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from hypothesis import strategies as st

from dtpf.messages import foxglove, keys, models
from dtpf.messages.codec import encode
from dtpf.messages.foxglove import CompressedImage
from dtpf.messages.models import (
    UINT32_MAX,
    Control,
    Estimate,
    ForecastBand,
    Layer,
    Message,
    Observation,
    ParticleSet,
    ParticleSetKind,
    PSCommand,
    Missed,
    Rejected,
    ServiceState,
    Status,
    Time,
    WeightState,
)
from dtpf.recording.logfile import MAGIC

MAX_REJECTED_SAMPLE = models.MAX_REJECTED_SAMPLE
STATUS_TALLIES = tuple(name for name in ("rejections", "rejected_on") if name in Status.model_fields)

#: The twin of every key the decoders are fuzzed on; valid messages often carry it, so they can succeed.
TWIN = "t-1"
ID_ALPHABET = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-"
MAX_PARTICLES = 64
MAX_DIM = 4

#: Sizes "too big to be honest": around 2**31, 2**32, 2**62, 2**63, 2**64.
HUGE_INTS = (2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**40, 2**53 + 1, 2**62, 2**63 - 1, 2**63, 2**64 - 1, 2**64,
             10**30)
#: A step one past the uint32 range, the last valid one, and negative ones.
STEP_EDGES = (-1, 0, 1, UINT32_MAX, UINT32_MAX + 1, -(2**63), 2**64)
LONG_TEXT = 100_000
DEEP = 10_000


@dataclass
class Case:
    """One payload to throw at the decoders, and where it came from."""

    payload: bytes
    #: The valid message the payload was made from (None for raw bytes).
    origin: Message | None = None
    #: What was done to it, in order; empty for the untouched encoding of ``origin``.
    mutations: list[str] = field(default_factory=list)

    def __repr__(self) -> str:
        shown = self.payload if len(self.payload) <= 300 else self.payload[:300] + b"..."
        return f"Case({len(self.payload)} bytes, mutations={self.mutations}, payload={shown!r})"


# --- JSON trees that keep duplicate keys and raw tokens ---

class Obj(list):
    """A JSON object as a list of (key, value) pairs: duplicates and order kept."""


@dataclass(frozen=True)
class Raw:
    """JSON text written as it is (tokens no Python value prints as, or unbalanced nesting)."""

    text: str


def load_json(text: str | bytes) -> Any:
    """Parse JSON into :class:`Obj` objects and lists."""
    return json.loads(text, object_pairs_hook=Obj)


def dump_json(value: Any) -> str:
    """JSON text of a tree of Obj, list, str, int, float (NaN/Infinity spelled as such), bool, None, Raw."""
    if isinstance(value, Raw):
        return value.text
    if isinstance(value, Obj):
        return "{" + ",".join(json.dumps(k) + ":" + dump_json(v) for k, v in value) + "}"
    if isinstance(value, list):
        return "[" + ",".join(dump_json(v) for v in value) + "]"
    if isinstance(value, bool) or value is None:
        return json.dumps(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return json.dumps(value)  # 'NaN', 'Infinity', '-Infinity' for the non-finite
    if isinstance(value, str):
        return json.dumps(value)
    raise TypeError(f"not a JSON tree value: {value!r}")


def json_paths(tree: Any, path: tuple = (), key: str | None = None) -> list[tuple[tuple, str | None]]:
    """Every (path, nearest object key) in the tree, the root included; paths index pairs and items."""
    out = [(path, key)]
    if isinstance(tree, Obj):
        for i, (name, value) in enumerate(tree):
            out += json_paths(value, path + (i,), name)
    elif isinstance(tree, list):
        for i, value in enumerate(tree):
            out += json_paths(value, path + (i,), key)
    return out


def get_at(tree: Any, path: tuple) -> Any:
    for i in path:
        tree = tree[i][1] if isinstance(tree, Obj) else tree[i]
    return tree


def set_at(tree: Any, path: tuple, value: Any) -> Any:
    """The tree with the value at ``path`` replaced (in place below the root; returns the root)."""
    if not path:
        return value
    parent = get_at(tree, path[:-1])
    i = path[-1]
    if isinstance(parent, Obj):
        parent[i] = (parent[i][0], value)
    else:
        parent[i] = value
    return tree


def nested(depth: int, opener: str = "[", closed: bool = True) -> Raw:
    """``depth`` nested arrays or objects, balanced or not."""
    if opener == "[":
        return Raw("[" * depth + ("]" * depth if closed else ""))
    return Raw('{"a":' * depth + "1" + ("}" * depth if closed else ""))


# --- choices hypothesis can shrink, from strategies it builds once ---

def one(draw, options):
    """One of ``options``, by an index drawn from a strategy hypothesis builds once per length."""
    return options[index(draw, len(options))]


def index(draw, size: int) -> int:
    """An index below ``size`` (>= 1), drawn with a strategy hypothesis builds once per size."""
    return draw(st.integers(0, size - 1))


def position(draw, size: int) -> int:
    """A position in 0..size, as often near the end as near the start (hypothesis favours small numbers)."""
    at = draw(st.integers(0, size))
    return size - at if draw(st.booleans()) else at


# --- valid messages from the real models ---

identifiers = st.text(alphabet=ID_ALPHABET, min_size=1, max_size=12)
twin_ids = st.one_of(st.just(TWIN), identifiers)
steps = st.one_of(st.integers(0, 100), st.integers(0, UINT32_MAX), st.sampled_from([0, 1, UINT32_MAX]))
counts = st.integers(0, UINT32_MAX)
stamps = st.builds(Time, sec=st.integers(0, UINT32_MAX), nsec=st.integers(0, 999_999_999))
finite_floats = st.floats(allow_nan=False, allow_infinity=False)
non_negative_floats = st.floats(min_value=0.0, allow_nan=False, allow_infinity=False)
unit_floats = st.floats(min_value=0.0, max_value=1.0)
short_texts = st.text(max_size=20)


def optional(strategy):
    return st.one_of(st.none(), strategy)


@st.composite
def headers(draw) -> dict:
    """The fields every message carries (layer aside)."""
    return dict(run_id=draw(identifiers), twin_id=draw(twin_ids), step=draw(steps), stamp=draw(stamps))


@st.composite
def particle_arrays(draw) -> tuple[np.ndarray, np.ndarray]:
    """(N, d) finite particles and N normalised weights, N in 1..64, d in 1..4."""
    n = draw(st.integers(1, MAX_PARTICLES))
    d = draw(st.integers(1, MAX_DIM))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    scale = one(draw, [1.0, 1e-300, 1e300, 0.0])
    particles = rng.normal(size=(n, d)) * scale
    shape = one(draw, ["random", "uniform", "one-hot", "denormal"])
    if shape == "uniform":
        weights = np.full(n, 1.0 / n)
    elif shape == "one-hot":
        weights = np.zeros(n)
        weights[draw(st.integers(0, n - 1))] = 1.0
    elif shape == "denormal":
        weights = np.full(n, 5e-324)
        weights[0] = 1.0
    else:
        weights = rng.random(n) + 1e-12
        weights /= weights.sum()
    return particles, weights


@st.composite
def preprocessing_counts(draw, n: int | None) -> dict:
    """n_large, n_processed, n_mixed, n_plain, consistent (and at most ``n`` in all, when given)."""
    if draw(st.booleans()):
        return dict(n_large=None, n_processed=None, n_mixed=None, n_plain=None)
    top = UINT32_MAX if n is None else n
    large = draw(st.integers(0, top))
    processed = draw(st.integers(0, top - large if n is not None else UINT32_MAX))
    mixed = draw(st.integers(0, processed))
    return dict(n_large=large, n_processed=processed, n_mixed=mixed, n_plain=processed - mixed)


@st.composite
def particle_sets(draw) -> ParticleSet:
    particles, weights = draw(particle_arrays())
    n = len(weights)
    kind = draw(st.sampled_from(list(ParticleSetKind)))
    fields = dict(draw(headers()), kind=kind, particles=particles, weights=weights,
                  layer=Layer.ENTITY if kind == ParticleSetKind.PROPAGATED else Layer.INFORMATION,
                  observation=draw(st.lists(finite_floats, max_size=4)),
                  parents=draw(optional(st.integers(1, n))))
    if kind == ParticleSetKind.PREPROCESSED:
        fields.update(ps=draw(unit_floats), threshold=draw(optional(unit_floats)), **draw(preprocessing_counts(n)))
    return ParticleSet(**fields)


@st.composite
def weight_states(draw) -> WeightState:
    n = draw(st.one_of(st.integers(1, 1000), st.integers(1, UINT32_MAX)))
    q10, q50, q90, q99, max_weight = sorted(draw(st.lists(unit_floats, min_size=5, max_size=5)))
    return WeightState(
        **draw(headers()), layer=Layer.INFORMATION, n=n, ess=draw(non_negative_floats),
        ess_ratio=draw(non_negative_floats), entropy=draw(non_negative_floats),
        entropy_ratio=draw(non_negative_floats), max_weight=max_weight, threshold=draw(unit_floats),
        n_above_threshold=draw(st.integers(0, n)), distinct=draw(st.integers(1, n)),
        q10=q10, q50=q50, q90=q90, q99=q99, ps=draw(unit_floats), **draw(preprocessing_counts(n)))


@st.composite
def ps_commands(draw) -> PSCommand:
    header = draw(headers())
    return PSCommand(
        **header, layer=Layer.SYSTEM, ps=draw(unit_floats),
        applies_from_step=draw(st.integers(header["step"], UINT32_MAX)),
        policy=draw(st.text(min_size=1, max_size=20)), reason=draw(short_texts),
        predicted_ess_ratio=draw(optional(non_negative_floats)),
        predicted_distinct_ratio=draw(optional(unit_floats)),
        predicted_spread=draw(optional(non_negative_floats)), predicted_error=draw(optional(non_negative_floats)),
        surprise=draw(optional(finite_floats)), preprocess=draw(st.booleans()), evidence=draw(optional(finite_floats)))


@st.composite
def estimates(draw) -> Estimate:
    d = draw(st.integers(1, MAX_DIM))
    vectors = st.lists(finite_floats, min_size=d, max_size=d)
    bounds = [sorted(pair) for pair in zip(draw(vectors), draw(vectors))]
    return Estimate(
        **draw(headers()), layer=Layer.ENTITY, mean=draw(vectors),
        var=draw(st.lists(non_negative_floats, min_size=d, max_size=d)),
        lower=[low for low, _ in bounds], upper=[high for _, high in bounds],
        ess=draw(non_negative_floats), ess_ratio=draw(non_negative_floats), resampled=draw(st.booleans()),
        degraded=draw(st.booleans()), truth=draw(optional(vectors)),
        observation=draw(optional(st.lists(finite_floats, max_size=3))), ps=draw(optional(unit_floats)),
        log_predictive=draw(optional(finite_floats)), innovation=draw(optional(non_negative_floats)),
        covariance=draw(optional(st.lists(finite_floats, min_size=d * (d - 1) // 2, max_size=d * (d - 1) // 2))))


observation_counts = st.fixed_dictionaries({name: counts for name in (
    "accepted", "duplicate", "out_of_order", "wrong_length", "malformed", "missed", "last_sequence")})


@st.composite
def statuses(draw) -> Status:
    return Status(
        **draw(headers()), layer=draw(st.sampled_from(list(Layer))), state=draw(st.sampled_from(list(ServiceState))),
        pid=draw(counts), received=draw(counts), rejected=draw(counts), last_error=draw(optional(short_texts)),
        peers_alive=draw(st.lists(st.sampled_from(list(Layer)), max_size=5)),
        config_json=draw(optional(st.just('{"particles": 200, "steps": 40}'))),
        detail=draw(optional(short_texts)), observations=draw(optional(observation_counts)),
        **{name: draw(st.lists(named_counts, max_size=3)) for name in STATUS_TALLIES})


named_counts = st.fixed_dictionaries({"name": st.text(max_size=30), "count": counts})


@st.composite
def rejecteds(draw):
    return Rejected(
        **draw(headers()), layer=Layer.RECORDER, key=draw(st.text(max_size=40)), reason=draw(short_texts),
        size=draw(counts), sample=base64.b64encode(draw(st.binary(max_size=MAX_REJECTED_SAMPLE))).decode("ascii"))


@st.composite
def misseds(draw):
    return Missed(**draw(headers()), layer=Layer.RECORDER, key=draw(st.text(max_size=40)),
                  source=draw(st.text(max_size=40)), count=draw(counts), after_step=draw(optional(counts)),
                  before_step=draw(optional(counts)))


def _cloud_fields(names) -> list:
    return [foxglove.PackedElementField(name=name, offset=8 * i, type=8) for i, name in enumerate(names)]


@st.composite
def point_clouds(draw):
    points = draw(st.integers(0, 8))
    return foxglove.PointCloud(
        **draw(headers()), layer=Layer.ENTITY, timestamp=draw(stamps), frame_id=draw(short_texts)[:64],
        point_stride=32, fields=_cloud_fields(["x", "y", "z", "weight"]),
        data=base64.b64encode(draw(st.binary(min_size=32 * points, max_size=32 * points))).decode("ascii"))


def _annotations(stamp, xs, colour) -> list:
    point = [foxglove.Point2(x=x, y=-x) for x in xs]
    return dict(circles=[foxglove.CircleAnnotation(timestamp=stamp, position=point[0], diameter=3.0, thickness=1.0,
                                                 fill_color=colour, outline_color=colour)] if point else [],
                points=[foxglove.PointsAnnotation(timestamp=stamp, type=1, points=point, outline_color=colour,
                                                fill_color=colour, thickness=2.0)])


@st.composite
def image_annotations(draw):
    colour = foxglove.Color(r=draw(st.floats(0, 1)), g=0.5, b=0.0, a=1.0)
    return foxglove.ImageAnnotations(**draw(headers()), layer=Layer.ENTITY,
                                   **_annotations(draw(stamps), draw(st.lists(finite_floats, max_size=5)), colour))


@st.composite
def compressed_images(draw) -> CompressedImage:
    return CompressedImage(
        **draw(headers()), layer=Layer.ENTITY, timestamp=draw(stamps), frame_id=draw(short_texts),
        data=base64.b64encode(draw(st.binary(max_size=48))).decode("ascii"),
        format=one(draw, ["jpeg", "png"]))


@st.composite
def observations(draw) -> Observation:
    end = draw(st.booleans())
    return Observation(
        **draw(headers()), layer=Layer.SENSOR, values=draw(st.lists(finite_floats, min_size=0 if end else 1,
                                                                    max_size=6)),
        truth=draw(optional(st.lists(finite_floats, max_size=6))), end=end,
        sensor=draw(optional(st.sampled_from(["gps", "beacons", "lidar-2"]))))


@st.composite
def controls(draw) -> Control:
    return Control(**draw(headers()), layer=Layer.SENSOR, control=draw(st.lists(finite_floats, min_size=1, max_size=6)))


@st.composite
def forecast_bands(draw) -> ForecastBand:
    d = draw(st.integers(1, MAX_DIM))
    vectors = st.lists(finite_floats, min_size=d, max_size=d)
    ahead = []
    for _ in range(draw(st.integers(1, 4))):
        bounds = [sorted(pair) for pair in zip(draw(vectors), draw(vectors))]
        ahead.append(dict(step=draw(counts), mean=draw(vectors),
                          var=draw(st.lists(non_negative_floats, min_size=d, max_size=d)),
                          lower=[low for low, _ in bounds], upper=[high for _, high in bounds]))
    return ForecastBand(**draw(headers()), layer=Layer.ENTITY, ahead=ahead)


#: A valid message of each class, by class.
MESSAGE_STRATEGIES = {
    ParticleSet: particle_sets(), WeightState: weight_states(), PSCommand: ps_commands(), Estimate: estimates(),
    Status: statuses(), CompressedImage: compressed_images(), Observation: observations(), Control: controls(),
    Rejected: rejecteds(), Missed: misseds(), foxglove.PointCloud: point_clouds(),
    foxglove.ImageAnnotations: image_annotations(), ForecastBand: forecast_bands(),
}
valid_messages = st.one_of(*MESSAGE_STRATEGIES.values())


# --- valid messages from a seed: the cheap start of every mutated payload ---
#
# Hypothesis spends about 0.1 ms per draw; a message of the strategies above takes 20-40 draws.
# The mutation families need 10,000 starting points, so there hypothesis draws only the class
# and a seed, and these builders fill in random, valid, edge-biased field values from the seed.

EDGE_FLOATS = (0.0, -0.0, 5e-324, -5e-324, 1e-300, 1.0, -1.0, 0.1, math.pi, 1e308, -1e308, 2.0**53 + 1)
UNIT_EDGES = (0.0, 1.0, 0.5, 5e-324, 1.0 - 2.0**-53)
TEXT_CHARACTERS = "abcXYZ09 _-./\\\"'\n\t\x00\x7fé—😀{}[]:,"


class Seeded:
    """Random valid field values from one seed, often at the edges of their ranges."""

    def __init__(self, seed: int):
        self.rng = random.Random(seed)

    def float(self) -> float:
        r = self.rng.random()
        if r < 0.3:
            return self.rng.choice(EDGE_FLOATS)
        if r < 0.7:
            return self.rng.uniform(-1e3, 1e3)
        return self.rng.gauss(0.0, 1.0) * 10.0 ** self.rng.randint(-300, 300)

    def non_negative(self) -> float:
        return abs(self.float())

    def unit(self) -> float:
        return self.rng.choice(UNIT_EDGES) if self.rng.random() < 0.3 else self.rng.random()

    def count(self, low: int = 0, high: int = UINT32_MAX) -> int:
        r = self.rng.random()
        if r < 0.3:
            return self.rng.choice([low, high, min(low + 1, high)])
        return self.rng.randint(low, min(high, low + 100) if r < 0.6 else high)

    def maybe(self, make):
        return None if self.rng.random() < 0.4 else make()

    def floats(self, low: int, high: int, make=None) -> list[float]:
        return [(make or self.float)() for _ in range(self.rng.randint(low, high))]

    def identifier(self) -> str:
        return "".join(self.rng.choices(ID_ALPHABET, k=self.rng.randint(1, 12)))

    def text(self, low: int = 0, high: int = 20) -> str:
        return "".join(self.rng.choices(TEXT_CHARACTERS, k=self.rng.randint(low, high)))

    def header(self) -> dict:
        return dict(run_id=self.identifier(), twin_id=TWIN if self.rng.random() < 0.7 else self.identifier(),
                    step=self.count(), stamp=Time(sec=self.count(), nsec=self.count(0, 999_999_999)))

    def counts(self, n: int | None) -> dict:
        if self.rng.random() < 0.4:
            return dict(n_large=None, n_processed=None, n_mixed=None, n_plain=None)
        large = self.count(0, UINT32_MAX if n is None else n)
        processed = self.count(0, UINT32_MAX if n is None else n - large)
        mixed = self.count(0, processed)
        return dict(n_large=large, n_processed=processed, n_mixed=mixed, n_plain=processed - mixed)


def _seeded_particle_set(v: Seeded) -> ParticleSet:
    n, d = v.count(1, MAX_PARTICLES), v.rng.randint(1, MAX_DIM)
    rng = np.random.default_rng(v.rng.getrandbits(32))
    weights = rng.random(n) + 1e-12
    kind = v.rng.choice(list(ParticleSetKind))
    fields = dict(v.header(), kind=kind, particles=rng.normal(size=(n, d)) * v.rng.choice([1.0, 1e-300, 1e300]),
                  weights=weights / weights.sum(), observation=v.floats(0, 3),
                  layer=Layer.ENTITY if kind == ParticleSetKind.PROPAGATED else Layer.INFORMATION,
                  parents=v.maybe(lambda: v.count(1, n)))
    if kind == ParticleSetKind.PREPROCESSED:
        fields.update(ps=v.unit(), threshold=v.maybe(v.unit), **v.counts(n))
    return ParticleSet(**fields)


def _seeded_weight_state(v: Seeded) -> WeightState:
    n = v.count(1)
    q10, q50, q90, q99, max_weight = sorted(v.unit() for _ in range(5))
    return WeightState(**v.header(), layer=Layer.INFORMATION, n=n, ess=v.non_negative(), ess_ratio=v.non_negative(),
                       entropy=v.non_negative(), entropy_ratio=v.non_negative(), max_weight=max_weight,
                       threshold=v.unit(), n_above_threshold=v.count(0, n), distinct=v.count(1, n), q10=q10, q50=q50,
                       q90=q90, q99=q99, ps=v.unit(), **v.counts(n))


def _seeded_ps_command(v: Seeded) -> PSCommand:
    header = v.header()
    return PSCommand(**header, layer=Layer.SYSTEM, ps=v.unit(), applies_from_step=v.count(header["step"]),
                     policy=v.text(1), reason=v.text(), predicted_ess_ratio=v.maybe(v.non_negative),
                     predicted_distinct_ratio=v.maybe(v.unit), predicted_spread=v.maybe(v.non_negative),
                     predicted_error=v.maybe(v.non_negative), surprise=v.maybe(v.float),
                     preprocess=v.unit() < 0.5, evidence=v.maybe(v.float))


def _seeded_estimate(v: Seeded) -> Estimate:
    d = v.rng.randint(1, MAX_DIM)
    bounds = [sorted((v.float(), v.float())) for _ in range(d)]
    return Estimate(**v.header(), layer=Layer.ENTITY, mean=v.floats(d, d), var=v.floats(d, d, v.non_negative),
                    lower=[low for low, _ in bounds], upper=[high for _, high in bounds], ess=v.non_negative(),
                    ess_ratio=v.non_negative(), resampled=v.rng.random() < 0.5, degraded=v.rng.random() < 0.5,
                    truth=v.maybe(lambda: v.floats(d, d)), observation=v.maybe(lambda: v.floats(0, 3)),
                    ps=v.maybe(v.unit), log_predictive=v.maybe(v.float), innovation=v.maybe(v.non_negative))


def _seeded_forecast_band(v: Seeded) -> ForecastBand:
    d = v.rng.randint(1, MAX_DIM)
    ahead = []
    for _ in range(v.rng.randint(1, 4)):
        bounds = [sorted((v.float(), v.float())) for _ in range(d)]
        ahead.append(dict(step=v.count(), mean=v.floats(d, d), var=v.floats(d, d, v.non_negative),
                          lower=[low for low, _ in bounds], upper=[high for _, high in bounds]))
    return ForecastBand(**v.header(), layer=Layer.ENTITY, ahead=ahead)


def _seeded_status(v: Seeded) -> Status:
    observed = v.maybe(lambda: {name: v.count() for name in (
        "accepted", "duplicate", "out_of_order", "wrong_length", "malformed", "missed", "last_sequence")})
    return Status(**v.header(), layer=v.rng.choice(list(Layer)), state=v.rng.choice(list(ServiceState)),
                  pid=v.count(), received=v.count(), rejected=v.count(), last_error=v.maybe(v.text),
                  peers_alive=v.rng.choices(list(Layer), k=v.rng.randint(0, 4)),
                  config_json=v.maybe(lambda: '{"particles": 200, "steps": 40}'), detail=v.maybe(v.text),
                  observations=observed, **{name: [dict(name=v.text(), count=v.count())
                                                   for _ in range(v.rng.randint(0, 3))] for name in STATUS_TALLIES})


def _seeded_rejected(v: Seeded):
    return Rejected(**v.header(), layer=Layer.RECORDER, key=v.text(0, 40), reason=v.text(), size=v.count(),
                    sample=base64.b64encode(v.rng.randbytes(v.count(0, MAX_REJECTED_SAMPLE))).decode())


def _seeded_missed(v: Seeded):
    return Missed(**v.header(), layer=Layer.RECORDER, key=v.text(0, 40), source=v.text(0, 40), count=v.count(),
                  after_step=v.maybe(v.count), before_step=v.maybe(v.count))


def _seeded_point_cloud(v: Seeded):
    return foxglove.PointCloud(**v.header(), layer=Layer.ENTITY, timestamp=Time(sec=v.count(), nsec=v.count(0, 10**9 - 1)),
                             frame_id=v.text(0, 20), point_stride=v.rng.randint(1, 64),
                             fields=_cloud_fields(v.rng.sample(["x", "y", "z", "weight", "w2"], v.rng.randint(0, 5))),
                             data=base64.b64encode(v.rng.randbytes(v.rng.randint(0, 256))).decode())


def _seeded_image_annotations(v: Seeded):
    colour = foxglove.Color(r=v.unit(), g=v.unit(), b=v.unit(), a=v.unit())
    return foxglove.ImageAnnotations(**v.header(), layer=Layer.ENTITY,
                                   **_annotations(Time(sec=v.count(), nsec=v.count(0, 10**9 - 1)), v.floats(0, 5), colour))


def _seeded_compressed_image(v: Seeded) -> CompressedImage:
    return CompressedImage(**v.header(), layer=Layer.ENTITY, timestamp=Time(sec=v.count(), nsec=v.count(0, 10**9 - 1)),
                           frame_id=v.text(), data=base64.b64encode(v.rng.randbytes(v.rng.randint(0, 48))).decode(),
                           format=v.rng.choice(["jpeg", "png"]))


def _seeded_observation(v: Seeded) -> Observation:
    end = v.rng.random() < 0.3
    return Observation(**v.header(), layer=Layer.SENSOR, values=v.floats(0 if end else 1, 6),
                       truth=v.maybe(lambda: v.floats(0, 6)), end=end, sensor=v.maybe(lambda: "gps"))


def _seeded_control(v: Seeded) -> Control:
    return Control(**v.header(), layer=Layer.SENSOR, control=v.floats(1, 6))


SEEDED_BUILDERS = {
    ParticleSet: _seeded_particle_set, WeightState: _seeded_weight_state, PSCommand: _seeded_ps_command,
    Estimate: _seeded_estimate, Status: _seeded_status, CompressedImage: _seeded_compressed_image,
    Observation: _seeded_observation, Rejected: _seeded_rejected, Missed: _seeded_missed, foxglove.PointCloud: _seeded_point_cloud,
    foxglove.ImageAnnotations: _seeded_image_annotations, Control: _seeded_control,
    ForecastBand: _seeded_forecast_band,
}


def seeded_message(cls: type[Message], seed: int) -> Message:
    """A valid message of ``cls`` with field values drawn from ``seed``."""
    return SEEDED_BUILDERS[cls](Seeded(seed))


seeds = st.integers(0, 2**32 - 1)
#: A valid message of any class, from a class and a seed (two draws).
seeded_messages = st.builds(seeded_message, st.sampled_from(list(SEEDED_BUILDERS)), seeds)
seeded_particle_sets = st.builds(seeded_message, st.just(ParticleSet), seeds)


# --- wrong values for a JSON value, by the key that holds it ---

#: Every value is immutable (containers are Raw text): a drawn value must not carry edits into the next example.
GENERIC_WRONG = (
    None, True, False, 0, -1, 1.5, -0.0, 5e-324, 1e308, "", "x", "7",
    Raw("[]"), Raw("{}"), Raw("[1,2]"), Raw('{"a":1}'), Raw('[{"a":1}]'), Raw('{"a":{"b":[]}}'),
    math.nan, math.inf, -math.inf, *HUGE_INTS, -(2**63) - 1,
    Raw("1e999"), Raw("-1e999"), Raw("9" * 5000), Raw("-" + "9" * 5000), Raw("1" + "0" * 400 + ".5"),
    Raw("0." + "0" * 5000 + "1"), Raw("NaN"), Raw("-NaN"), Raw("nan"), Raw("Infinity"), Raw("-Infinity"),
    Raw("1.0e-400"), Raw("007"), Raw("0x10"), Raw("+1"), Raw(".5"), Raw("1."), Raw('"\\ud800"'),
    Raw('"\\udc00\\ud800"'), Raw('"\\u0000"'), Raw('"\udcff"'), Raw("tru"), Raw(""),
    # one past the longest lists (MAX_OBSERVATION_VALUES = 4096; 101 tallies in a Status)
    "x" * LONG_TEXT, Raw("[" + ",".join(['{"name":"x","count":1}'] * 102) + "]"),
    Raw("[" + ",".join(["0.0"] * 4097) + "]"),
)
#: Wrong values for keys whose value is a count, step, size or offset.
INTEGER_WRONG = (*STEP_EDGES, *HUGE_INTS, 7.0, "7", True, -8, 7, 9, Raw("7.0"), Raw("7e0"), Raw("-0"))
#: Wrong spellings of enum values and literals.
ENUM_WRONG = ("Entity", "ENTITY", "entity ", " entity", "entity\u0000", "sensors", "Propagated", "propagated\n",
              "preprocess", "RUNNING", "asleep", "JPEG", "gif", "dtpf.ParticleSet ", "dtpf.WeightState",
              "foxglove.CompressedImage", "<f4", ">f8", "=f8", "f8", "float64", "<i8", "|u1", "<f16", "O", "<c16",
              "weights", "particles", "Particles", "")
#: Run and twin ids that are not ids.
ID_WRONG = ("", "a/b", "**", "*", "a b", "a$b", "a?", "a#", "é", "t-1/", "/t-1", "t-1\n", "x" * LONG_TEXT)
KEYS_OF_KIND = {
    "int": {"step", "applies_from_step", "n", "pid", "received", "rejected", "n_above_threshold", "distinct",
            "n_large", "n_processed", "n_mixed", "n_plain", "parents", "sec", "nsec", "offset", "shape",
            "accepted", "duplicate", "out_of_order", "wrong_length", "malformed", "missed", "last_sequence",
            "size", "count"},
    "enum": {"layer", "kind", "state", "format", "peers_alive", "message", "dtype", "name"},
    "id": {"run_id", "twin_id"},
    "base64": {"data", "sample"},
}
#: Strings that are not standard base64 (or are, but of a size no sample has).
BASE64_WRONG = ("a", "ab=", "====", "!!!!", "aGVsbG8", "aGVsbG8=\n", "aGVs bG8=", "-_-_", "\u00e9\u00e9\u00e9\u00e9",
                "A" * 2000, "A" * LONG_TEXT)
WRONG_BY_KIND = {"int": INTEGER_WRONG, "enum": ENUM_WRONG, "id": ID_WRONG, "base64": BASE64_WRONG}
#: Keys that exist in some class; added where they do not belong.
FOREIGN_KEYS = ("values", "particles", "weights", "kind", "ps", "extra", "", "step", "arrays", "fields", "\u0000")


NESTINGS = tuple(nested(depth, opener, closed) for depth in (10, 199, 200, 201, 1000, DEEP)
                 for opener, closed in (("[", True), ("{", True), ("[", False)))
_ANY_WRONG = st.sampled_from(GENERIC_WRONG + NESTINGS)
_WRONG_STRATEGIES = {kind: st.one_of(st.sampled_from(values), _ANY_WRONG) for kind, values in WRONG_BY_KIND.items()}
_KIND_OF_KEY = {name: kind for kind, names in KEYS_OF_KIND.items() for name in names}


def wrong_values(key: str | None):
    """A wrong value for the value under ``key``: one for its kind of key, or anything."""
    kind = _KIND_OF_KEY.get(key)
    return _ANY_WRONG if kind is None else _WRONG_STRATEGIES[kind]


OPERATIONS = ("replace", "replace", "replace", "delete", "add", "duplicate", "reorder", "wrap")


@st.composite
def mutated_tree(draw, tree: Any, log: list[str]) -> Any:
    """``tree`` after one to three JSON mutations, each said in ``log``."""
    for _ in range(draw(st.integers(1, 3))):
        paths = json_paths(tree)[1:] or [((), None)]  # the root only when it has nothing inside
        path, key = paths[index(draw, len(paths))]
        target = get_at(tree, path)
        operation = one(draw, OPERATIONS)
        if operation == "replace" or (operation in ("delete", "add", "duplicate", "reorder")
                                      and not isinstance(target, (Obj, list))):
            value = draw(wrong_values(key))
            log.append(f"replace {key}@{path} with {dump_json(value)[:40]}")
            tree = set_at(tree, path, value)
        elif operation == "wrap":
            wrapped = one(draw, ["list", "object"])
            log.append(f"wrap {key}@{path} in a {wrapped}")
            tree = set_at(tree, path, [target] if wrapped == "list" else Obj([("value", target)]))
        elif operation == "delete":
            if target:
                i = draw(st.integers(0, len(target) - 1))
                log.append(f"delete item {i} of {key}@{path}")
                del target[i]
        elif operation == "add":
            if isinstance(target, Obj):
                pair = (draw(st.sampled_from(FOREIGN_KEYS)), draw(wrong_values(None)))
                log.append(f"add key {pair[0]!r} to {key}@{path}")
            else:
                pair = draw(wrong_values(key))
                log.append(f"append to {key}@{path}")
            target.insert(draw(st.integers(0, len(target))), pair)
        elif operation == "duplicate":
            if target:
                i = draw(st.integers(0, len(target) - 1))
                item = target[i]
                if isinstance(target, Obj) and draw(st.booleans()):
                    item = (item[0], draw(wrong_values(item[0])))  # same key, another value
                log.append(f"duplicate item {i} of {key}@{path}")
                target.insert(draw(st.integers(0, len(target))), item)
        else:  # reorder
            if len(target) > 1:
                i, j = index(draw, len(target)), index(draw, len(target))
                target[i], target[j] = target[j], target[i]
            log.append(f"reorder {key}@{path}")
    return tree


# --- the binary envelope, taken apart and put together again ---

@dataclass
class Envelope:
    """The parts of an encoded ParticleSet; :meth:`build` writes them back, lies included."""

    magic: bytes
    version: int
    reserved: bytes
    header: Any          # JSON tree of the header
    data: bytes
    header_size: int | None = None   # claimed H; None: the real one
    padding: bytes | None = None     # None: the zeros that align the data

    @classmethod
    def parse(cls, payload: bytes) -> "Envelope":
        magic, version, reserved, size = struct.unpack_from("<4sB3sI", payload)
        start = (12 + size + 7) // 8 * 8
        return cls(magic, version, reserved, load_json(payload[12:12 + size]), payload[start:])

    def build(self) -> bytes:
        header = dump_json(self.header).encode("utf-8", "surrogatepass")
        size = len(header) if self.header_size is None else self.header_size
        padding = b"\0" * (-(12 + len(header)) % 8) if self.padding is None else self.padding
        return struct.pack("<4sB3sI", self.magic, self.version & 0xFF, self.reserved, size & UINT32_MAX) + \
            header + padding + self.data


def header_arrays(header: Any) -> list | None:
    """The 'arrays' list of an envelope header tree, if it still is one."""
    if isinstance(header, Obj):
        for name, value in header:
            if name == "arrays" and isinstance(value, list):
                return value
    return None


def descriptor_pair(descriptor: Any, key: str) -> int | None:
    if isinstance(descriptor, Obj):
        for i, (name, _) in enumerate(descriptor):
            if name == key:
                return i
    return None


def dims(n: int, d: int) -> list[int]:
    """Array dimensions, honest or not."""
    return [0, 1, 2, n, d, n + 1, -1, 2**31, 2**32, 2**40, 2**62, 2**63, 2**64, 10**30]


FLOAT_BITS = [struct.pack("<d", v) for v in (math.nan, math.inf, -math.inf, -1.0, 1e308, -0.0, 5e-324, 2.0)] + [
    b"\xff" * 8, b"\x00\x00\x00\x00\x00\x00\xf8\x7f", b"\x01\x00\x00\x00\x00\x00\xf0\x7f"]  # qNaN, sNaN


@st.composite
def envelope_mutation(draw, envelope: Envelope, n: int, d: int, log: list[str]) -> None:
    """One lie in the envelope's prefix, arrays or data (in place)."""
    part = one(draw, ["header_size", "version", "reserved", "magic", "padding", "shape", "shape", "shape",
                      "offset", "offset", "dtype", "name", "arrays", "data", "data_value"])
    arrays = header_arrays(envelope.header)
    if part == "header_size":
        real = len(dump_json(envelope.header).encode("utf-8", "surrogatepass"))
        envelope.header_size = one(draw, [0, 1, real - 1, real + 1, real + 8, real - 8, 2**31, 2**31 - 1,
                                          UINT32_MAX, 2**24, real + len(envelope.data)])
        log.append(f"claim header size {envelope.header_size}")
    elif part == "version":
        envelope.version = one(draw, [0, 2, 127, 255])
        log.append(f"version {envelope.version}")
    elif part == "reserved":
        envelope.reserved = one(draw, [b"\0\0\1", b"\1\0\0", b"\xff\xff\xff"])
        log.append(f"reserved {envelope.reserved!r}")
    elif part == "magic":
        envelope.magic = one(draw, [b"DTPf", b"dtpf", b"DTP\0", b"\0TPF", b"DTPD"])
        log.append(f"magic {envelope.magic!r}")
    elif part == "padding":
        real = -(12 + len(dump_json(envelope.header).encode("utf-8", "surrogatepass"))) % 8
        envelope.padding = one(draw, [b"", b"\0" * (real + 8), b"\1" * real, b"\0" * max(real - 1, 0),
                                      b"\0" * max(real - 1, 0) + b"\x80"])
        log.append(f"padding {envelope.padding!r}")
    elif part in ("shape", "offset", "dtype", "name") and arrays:
        i = draw(st.integers(0, len(arrays) - 1))
        j = descriptor_pair(arrays[i], part)
        if part == "shape":
            options = dims(n, d)
            old = get_at(arrays[i], (j,)) if j is not None else None
            if isinstance(old, list) and draw(st.booleans()):  # some dims of the shape it has
                value = [one(draw, options) if draw(st.booleans()) else dim for dim in old]
            else:  # a new shape, of any rank
                value = [options[k] for k in draw(st.lists(st.integers(0, len(options) - 1), max_size=3))]
        elif part == "offset":
            value = one(draw, [0, 8, 7, -8, 8 * n * d, 8 * n * d + 8, 8 * n * d - 8, 8 * n, *HUGE_INTS])
        elif part == "dtype":
            value = one(draw, ENUM_WRONG + ("<f8",))
        else:
            value = one(draw, ["weights", "particles", "observation", "", "Particles"])
        log.append(f"arrays[{i}].{part} = {value!r}")
        if j is None:
            if isinstance(arrays[i], Obj):
                arrays[i].append((part, value))
        else:
            arrays[i][j] = (part, value)
    elif part == "arrays" and arrays is not None:
        how = one(draw, ["reverse", "drop", "duplicate", "extra", "empty"])
        log.append(f"arrays {how}")
        if how == "reverse":
            arrays.reverse()
        elif how == "drop" and arrays:
            del arrays[draw(st.integers(0, len(arrays) - 1))]
        elif how == "duplicate" and arrays:
            arrays.append(arrays[draw(st.integers(0, len(arrays) - 1))])
        elif how == "extra":
            arrays.append(Obj([("name", "extra"), ("dtype", "<f8"), ("shape", [n]), ("offset", 8 * n * (d + 1))]))
        else:
            arrays.clear()
    elif part == "data":
        how = one(draw, ["cut", "extend", "empty"])
        k = one(draw, [1, 7, 8, 16, 8 * n])
        log.append(f"data {how} {k}")
        if how == "cut":
            envelope.data = envelope.data[:-k]
        elif how == "extend":
            envelope.data += b"\0" * k
        else:
            envelope.data = b""
    else:  # data_value
        slots = max(len(envelope.data) // 8, 1)
        i = draw(st.integers(0, slots - 1))
        which = one(draw, ["one", "weights-zero", "weights-double"])
        data = bytearray(envelope.data)
        if which == "one":
            data[8 * i:8 * i + 8] = one(draw, FLOAT_BITS)
        elif len(data) >= 8 * n and len(data) % 8 == 0:  # weights that are no longer normalised
            with np.errstate(all="ignore"):
                weights = np.frombuffer(bytes(data[-8 * n:]), "<f8") * (0.0 if which == "weights-zero" else 2.0)
            data[-8 * n:] = weights.tobytes()
        envelope.data = bytes(data)
        log.append(f"data value {which} at slot {i}")


# --- bytes ---

@st.composite
def byte_mutation(draw, payload: bytes, log: list[str]) -> bytes:
    """One edit of the bytes: cut, flip, overwrite, insert, delete, duplicate, splice nesting, huge ints."""
    size = len(payload)
    at = position(draw, size)
    operation = one(draw, ["truncate", "truncate", "flip", "overwrite", "insert", "delete", "duplicate", "nest",
                           "huge"])
    if operation == "truncate":
        log.append(f"truncate at {at}")
        return payload[:at]
    if operation == "flip" and size:
        at = min(at, size - 1)
        bit = draw(st.integers(0, 7))
        log.append(f"flip bit {bit} of byte {at}")
        return payload[:at] + bytes([payload[at] ^ (1 << bit)]) + payload[at + 1:]
    if operation == "overwrite":
        new = draw(st.binary(min_size=1, max_size=8))
        log.append(f"overwrite at {at} with {new!r}")
        return payload[:at] + new + payload[at + len(new):]
    if operation == "insert":
        new = draw(st.one_of(st.binary(min_size=1, max_size=16),
                             st.sampled_from([b"\0", b"\xff", b"{", b"}", b"[", b"]", b",", b'"', b"\\", b"\xc3"])))
        log.append(f"insert {new!r} at {at}")
        return payload[:at] + new + payload[at:]
    if operation == "delete":
        end = draw(st.integers(at, size))
        log.append(f"delete {at}:{end}")
        return payload[:at] + payload[end:]
    if operation == "duplicate":
        end = draw(st.integers(at, min(size, at + 64)))
        log.append(f"duplicate {at}:{end}")
        return payload[:end] + payload[at:end] + payload[end:]
    if operation == "nest":
        depth = one(draw, [200, 1000, DEEP])
        opener = one(draw, [b"[", b'{"a":', b'[{"a":'])
        log.append(f"splice {depth} x {opener!r} at {at}")
        return payload[:at] + opener * depth + payload[at:]
    # huge: an unsigned little-endian int where a size might be (always one at byte 8 of an envelope)
    width = one(draw, [4, 8])
    at = one(draw, [8, at])
    value = one(draw, [v for v in HUGE_INTS if v < 2**(8 * width)])
    log.append(f"uint{8 * width} {value} at {at}")
    return payload[:at] + value.to_bytes(width, "little") + payload[at + width:]


# --- the payload families of the fuzz tests ---

@st.composite
def valid_cases(draw) -> Case:
    """The untouched encoding of a valid message, from the strategies or from a seed."""
    cls = draw(st.sampled_from(list(MESSAGE_STRATEGIES)))  # a class first: every class is as likely
    message = draw(st.one_of(MESSAGE_STRATEGIES[cls], st.builds(seeded_message, st.just(cls), seeds)))
    return Case(encode(message), message)


def _json_mutated(draw, message: Message, payload: bytes) -> Case:
    log: list[str] = []
    if isinstance(message, ParticleSet):
        envelope = Envelope.parse(payload)
        envelope.header = draw(mutated_tree(envelope.header, log))
        new = envelope.build()
    else:
        new = dump_json(draw(mutated_tree(load_json(payload), log))).encode("utf-8", "surrogatepass")
    return Case(new, message, log)


@st.composite
def json_mutated_cases(draw) -> Case:
    """A message (JSON, or the JSON header of an envelope) with its JSON tree mutated."""
    message = draw(seeded_messages)
    return _json_mutated(draw, message, encode(message))


def _envelope_mutated(draw, message: ParticleSet, payload: bytes) -> Case:
    envelope = Envelope.parse(payload)
    log: list[str] = []
    for _ in range(draw(st.integers(1, 3))):
        draw(envelope_mutation(envelope, message.n, message.dim, log))
    return Case(envelope.build(), message, log)


@st.composite
def envelope_mutated_cases(draw) -> Case:
    """An encoded ParticleSet with one to three lies in its layout."""
    message = draw(seeded_particle_sets)
    return _envelope_mutated(draw, message, encode(message))


def _byte_mutated(draw, message: Message, payload: bytes) -> Case:
    log: list[str] = []
    for _ in range(draw(st.integers(1, 4))):
        payload = draw(byte_mutation(payload, log))
    return Case(payload, message, log)


@st.composite
def byte_mutated_cases(draw) -> Case:
    """A valid payload with one to four byte-level edits."""
    message = draw(seeded_messages)
    return _byte_mutated(draw, message, encode(message))


json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=10)),
    lambda children: st.one_of(st.lists(children, max_size=4),
                               st.dictionaries(st.sampled_from(["step", "run_id", "twin_id", "layer", "kind", "stamp",
                                                                "values", "x", ""]), children, max_size=5)),
    max_leaves=12)


@st.composite
def raw_cases(draw) -> Case:
    """Bytes from nowhere: random, behind a real envelope prefix, random JSON, deep nesting."""
    family = one(draw, ["binary", "magic", "prefix", "json", "nesting"])
    if family == "binary":
        payload = draw(st.binary(max_size=512))
    elif family == "magic":
        payload = b"DTPF" + draw(st.binary(max_size=64))
    elif family == "prefix":
        size = draw(st.one_of(st.integers(0, 64), st.sampled_from(HUGE_INTS).map(lambda v: v & UINT32_MAX)))
        payload = struct.pack("<4sB3sI", b"DTPF", 1, b"\0\0\0", size) + draw(st.binary(max_size=96))
    elif family == "json":
        payload = json.dumps(draw(json_values)).encode()
    else:
        payload = one(draw, [b"[", b"{", b'{"a":', b'{"step":'])
        payload = payload * one(draw, [1, 199, 200, 1000, DEEP, 100_000])
    return Case(payload, None, [f"raw {family}"])


def topic_keys(twin: str = TWIN) -> list[str]:
    """The key of every topic of the table, for one twin."""
    return [topic.key(twin) for topic in keys.TOPICS.values()]


# --- MCAP files, record by record ---

#: Opcode of a chunk record.
CHUNK = 0x06


def mcap_records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, end) of every top-level record of an intact MCAP file."""
    out, position = [], len(MAGIC)
    while position + 9 <= len(data) - len(MAGIC):
        opcode, length = struct.unpack_from("<BQ", data, position)
        end = position + 9 + length
        out.append((position, opcode, end))
        position = end
    return out


def xxh32(data: bytes, seed: int = 0) -> int:
    """xxHash32, for the header checksum of an lz4 frame."""
    p1, p2, p3, p4, p5, mask = 2654435761, 2246822519, 3266489917, 668265263, 374761393, 0xFFFFFFFF

    def rotl(x, r):
        return ((x << r) | (x >> (32 - r))) & mask

    n, i = len(data), 0
    if n >= 16:
        v = [(seed + p1 + p2) & mask, (seed + p2) & mask, seed & mask, (seed - p1) & mask]
        while i + 16 <= n:
            for j in range(4):
                v[j] = (rotl((v[j] + struct.unpack_from("<I", data, i + 4 * j)[0] * p2) & mask, 13) * p1) & mask
            i += 16
        h = (rotl(v[0], 1) + rotl(v[1], 7) + rotl(v[2], 12) + rotl(v[3], 18)) & mask
    else:
        h = (seed + p5) & mask
    h = (h + n) & mask
    while i + 4 <= n:
        h = (rotl((h + struct.unpack_from("<I", data, i)[0] * p3) & mask, 17) * p4) & mask
        i += 4
    while i < n:
        h = (rotl((h + data[i] * p5) & mask, 11) * p1) & mask
        i += 1
    h ^= h >> 15
    h = (h * p2) & mask
    h ^= h >> 13
    h = (h * p3) & mask
    return h ^ (h >> 16)


def first_chunk(data: bytes) -> tuple[int, int, dict]:
    start, _, end = next(r for r in mcap_records(data) if r[1] == CHUNK)
    body = start + 9
    _, _, usize, crc, clen = struct.unpack_from("<QQQII", data, body)
    compression = data[body + 32:body + 32 + clen].decode()
    (rlen,) = struct.unpack_from("<Q", data, body + 32 + clen)
    records = data[body + 40 + clen:body + 40 + clen + rlen]
    return start, end, dict(times=data[body:body + 16], usize=usize, crc=crc, compression=compression,
                            records=records)


def chunk_record(times: bytes, usize: int, crc: int, compression: str, records: bytes) -> bytes:
    name = compression.encode()
    body = times + struct.pack("<QI", usize, crc) + struct.pack("<I", len(name)) + name + \
        struct.pack("<Q", len(records)) + records
    return struct.pack("<BQ", CHUNK, len(body)) + body


def lz4_with_content_size(frame: bytes, claim: int) -> bytes:
    """The lz4 frame with its content-size field set to ``claim`` (header checksum recomputed)."""
    assert frame[4] & 0x08, "the frame stores its content size"
    descriptor = frame[4:6] + struct.pack("<Q", claim)
    return frame[:4] + descriptor + bytes([(xxh32(descriptor) >> 8) & 0xFF]) + frame[15:]


@st.composite
def log_payloads(draw) -> list[tuple[str, bytes]]:
    """(key, payload) of a few messages, steps duplicated and out of order; maybe one on a key outside
    the table, maybe a damaged payload on a message's own key (a recorder writes what arrives)."""
    messages = draw(st.lists(seeded_messages, min_size=1, max_size=5))
    order = draw(st.lists(st.integers(0, len(messages) - 1), min_size=1, max_size=8))
    out = [(keys.key_for(messages[i]), encode(messages[i])) for i in order]
    if draw(st.booleans()):
        out.insert(draw(st.integers(0, len(out))), (f"dtpf/{TWIN}/entity/unknown", b"\x00opaque"))
    if draw(st.booleans()):
        message = messages[0]
        damage = one(draw, [_byte_mutated, _json_mutated] + [_envelope_mutated] * isinstance(message, ParticleSet))
        damaged = damage(draw, message, encode(message)).payload
        out.insert(draw(st.integers(0, len(out))), (keys.key_for(message), damaged))
    return out


HUGE_UINTS = (0, 1, 2**31, 2**32 - 1, 2**33, 2**62, 2**64 - 1)


@st.composite
def log_mutation(draw, data: bytes) -> tuple[bytes, bool]:
    """(mutated file, whether it is a plain truncation)."""
    size = len(data)
    records = mcap_records(data)
    # A position inside a record (or either magic), the record picked evenly (hypothesis would mostly pick
    # the first, and the first bytes are alike in every file), the position in it often at its ends.
    spans = [(0, None, len(MAGIC)), *records, (size - len(MAGIC), None, size)]
    span_start, _, span_end = random.Random(draw(seeds)).choice(spans)
    at = span_start + position(draw, span_end - span_start)
    operation = one(draw, ["truncate", "truncate", "truncate", "flip", "overwrite", "insert", "length", "chunk_field",
                           "duplicate_record", "swap_records", "drop_record"])
    if operation == "truncate":
        return data[:at], True
    if operation == "flip":
        at = min(at, size - 1)
        return data[:at] + bytes([data[at] ^ (1 << draw(st.integers(0, 7)))]) + data[at + 1:], False
    if operation == "overwrite":
        new = draw(st.binary(min_size=1, max_size=16))
        return data[:at] + new + data[at + len(new):], False
    if operation == "insert":
        return data[:at] + draw(st.binary(min_size=1, max_size=16)) + data[at:], False
    pick = random.Random(draw(seeds))  # records picked evenly, as the spans above
    start, opcode, end = pick.choice(records)
    if operation == "length":  # the record's uint64 length
        value = one(draw, HUGE_UINTS + (end - start - 9 + 1, end - start - 9 - 1))
        return data[:start + 1] + struct.pack("<Q", value & (2**64 - 1)) + data[start + 9:], False
    if operation == "chunk_field":
        chunks = [r for r in records if r[1] == CHUNK] or [(start, opcode, end)]
        start, opcode, end = pick.choice(chunks)
        body = start + 9
        # uncompressed size (uint64), crc (uint32), compression string length (uint32), records length (uint64)
        compression_length = struct.unpack_from("<I", data, body + 28)[0] if end - body >= 32 else 0
        offset, width = one(draw, [(16, 8), (24, 4), (28, 4), (32 + compression_length, 8)])
        value = one(draw, HUGE_UINTS) & (2**(8 * width) - 1)
        return data[:body + offset] + value.to_bytes(width, "little") + data[body + offset + width:], False
    other_start, _, other_end = pick.choice(records)
    if operation == "duplicate_record":
        return data[:end] + data[start:end] + data[end:], False
    if operation == "drop_record":
        return data[:start] + data[end:], False
    (a, a_end), (b, b_end) = sorted([(start, end), (other_start, other_end)])
    if a_end > b:
        return data, False
    return data[:a] + data[b:b_end] + data[a_end:b] + data[a:a_end] + data[b_end:], False
