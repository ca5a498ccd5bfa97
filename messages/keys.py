"""Zenoh key expressions ``dtpf/<twin>/<layer>/<topic>`` and what travels on them.

The key expression of a message is also its MCAP topic. Build and read keys
here rather than with f-strings, so a bad twin id or an unknown layer fails
with a message that says so::

    from dtpf.messages import keys
    keys.key("ungm-1", "entity", "particles")   # 'dtpf/ungm-1/entity/particles'
    keys.parse("dtpf/ungm-1/entity/particles")  # ('ungm-1', Layer.ENTITY, 'particles')
    keys.topic_of("dtpf/ungm-1/entity/particles").message   # ParticleSet
    keys.twin_pattern("ungm-1")                 # 'dtpf/ungm-1/**'

:data:`TOPICS` is the table of known topics and their message class.
"""
from __future__ import annotations

from typing import NamedTuple

from dtpf.messages.foxglove import CompressedImage, ImageAnnotations, PointCloud
from dtpf.messages.models import (
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
    Status,
    WeightState,
    check_id,
)

#: First chunk of every dtpf key expression.
PREFIX = "dtpf"
#: Subscribe pattern for every message of every twin.
ALL = f"{PREFIX}/**"


class Topic(NamedTuple):
    """One known topic: where it lives and what travels on it."""

    layer: Layer
    name: str
    message: type[Message]
    kind: ParticleSetKind | None = None  #: for ParticleSet topics, the kind they carry

    def key(self, twin: str) -> str:
        """The key expression of this topic for one twin."""
        return key(twin, self.layer, self.name)


#: The known topics, by (layer, topic name).
TOPICS: dict[tuple[Layer, str], Topic] = {
    (t.layer, t.name): t
    for t in (
        Topic(Layer.ENTITY, "particles", ParticleSet, ParticleSetKind.PROPAGATED),
        Topic(Layer.INFORMATION, "preprocessed", ParticleSet, ParticleSetKind.PREPROCESSED),
        Topic(Layer.INFORMATION, "weight_state", WeightState),
        Topic(Layer.SYSTEM, "ps", PSCommand),
        Topic(Layer.ENTITY, "estimate", Estimate),
        Topic(Layer.ENTITY, "forecast_band", ForecastBand),  # the forecast of each step (--forecast H)
        Topic(Layer.ENTITY, "frame", CompressedImage),  # the video scenario's frames
        Topic(Layer.ENTITY, "cloud", PointCloud),  # the particle set as Foxglove draws it
        Topic(Layer.ENTITY, "annotations", ImageAnnotations),  # the video scenario's particles over its frame
        Topic(Layer.SENSOR, "observation", Observation),  # the physical system's measurements
        Topic(Layer.SENSOR, "control", Control),  # a driven machine's control input
        Topic(Layer.RECORDER, "rejected", Rejected),  # a sample of what the recorder did not record
        Topic(Layer.RECORDER, "missed", Missed),  # what the recorder missed and could not recover
        *(Topic(layer, "status", Status) for layer in Layer),
    )
}

#: Every message class, by name.
MESSAGE_CLASSES: dict[str, type[Message]] = {
    cls.__name__: cls for cls in (ParticleSet, WeightState, PSCommand, Estimate, Status, CompressedImage,
                                  Observation, Control, Rejected, Missed, PointCloud, ImageAnnotations,
                                  ForecastBand)
}


def check_layer(layer: str) -> Layer:
    """``layer`` as a :class:`Layer`, or ValueError listing the valid ones."""
    try:
        return Layer(layer)
    except ValueError:
        valid = ", ".join(item.value for item in Layer)
        raise ValueError(f"unknown layer {layer!r}; expected one of {valid}") from None


def check_topic_name(topic: str) -> str:
    """``topic`` if it is a valid topic chunk (same characters as ids), else ValueError."""
    return check_id(topic, "topic")


def key(twin: str, layer: str, topic: str) -> str:
    """The key expression ``dtpf/<twin>/<layer>/<topic>``.

    ``topic`` need not be in :data:`TOPICS` (e.g. liveliness tokens), but
    must be a single chunk of letters, digits, '_', '.', '-'.
    """
    return f"{PREFIX}/{check_id(twin, 'twin id')}/{check_layer(layer).value}/{check_topic_name(topic)}"


def parse(key_expr: str) -> tuple[str, Layer, str]:
    """Split ``dtpf/<twin>/<layer>/<topic>`` into (twin, layer, topic).

    Raises
    ------
    ValueError
        Naming what is wrong: not a string, wrong prefix, wrong number of
        chunks, bad twin id, unknown layer or bad topic.
    """
    parsed = _PARSED.get(key_expr) if isinstance(key_expr, str) else None
    if parsed is None:
        parsed = _parse(key_expr)
        if len(_PARSED) >= _PARSED_MAX:  # a flood of made-up keys cannot grow the cache
            _PARSED.clear()
        _PARSED[key_expr] = parsed
    return parsed


#: Keys parsed before (a service sees the same few keys at every step): at most _PARSED_MAX of them.
_PARSED: dict[str, tuple[str, Layer, str]] = {}
_PARSED_MAX = 4096


def _parse(key_expr: str) -> tuple[str, Layer, str]:
    if not isinstance(key_expr, str):
        raise ValueError(f"key expression must be a string, got {key_expr!r}")
    chunks = key_expr.split("/")
    if chunks[0] != PREFIX:
        raise ValueError(f"key expression must start with '{PREFIX}/', got {key_expr!r}")
    if len(chunks) != 4:
        raise ValueError(f"key expression must be '{PREFIX}/<twin>/<layer>/<topic>' (4 chunks), "
                         f"got {len(chunks)} chunks in {key_expr!r}")
    _, twin, layer, topic = chunks
    return check_id(twin, "twin id"), check_layer(layer), check_topic_name(topic)


def topic_of(key_expr: str) -> Topic:
    """The :data:`TOPICS` entry of a key expression, or ValueError if it is not a known topic."""
    _, layer, topic = parse(key_expr)
    try:
        return TOPICS[(layer, topic)]
    except KeyError:
        known = ", ".join(f"{t.layer.value}/{t.name}" for t in TOPICS.values())
        raise ValueError(f"unknown topic {layer.value}/{topic} in {key_expr!r}; known topics: {known}") from None


def key_for(message: Message) -> str:
    """The key expression a message is published on (from its class, layer, kind and twin)."""
    kind = getattr(message, "kind", None)
    layer = message.layer
    known = (type(message), layer, kind, message.twin_id)
    key = _KEYS.get(known)
    if key is not None:
        return key
    for topic in TOPICS.values():
        if isinstance(message, topic.message) and topic.layer == layer and topic.kind == kind:
            key = topic.key(message.twin_id)
            if len(_KEYS) >= _PARSED_MAX:  # as _PARSED: a fleet of made-up twin ids cannot grow it
                _KEYS.clear()
            _KEYS[known] = key
            return key
    raise ValueError(f"no topic carries a {type(message).__name__} from the {layer.value} layer")


#: The keys of messages published before, by (class, layer, kind, twin): a service publishes the same few
#: at every step, and finding one went through every topic, a visible share of an entity's time.
_KEYS: dict[tuple, str] = {}


def twin_pattern(twin: str) -> str:
    """Subscribe pattern for every message of one twin: ``dtpf/<twin>/**``."""
    return f"{PREFIX}/{check_id(twin, 'twin id')}/**"


def twins_chunk(pattern: str) -> str:
    """The Zenoh chunk of a twin pattern: ``*`` (every twin), a twin id, or an id with ``*`` in it
    (``line-1-*``: the twins whose id starts so; Zenoh spells it ``line-1-$*``). ValueError otherwise."""
    if pattern == "*":
        return pattern
    if not isinstance(pattern, str) or not pattern or "$" in pattern:
        raise ValueError(f"a twin pattern uses letters, digits, '_', '.', '-' and '*'; got {pattern!r}")
    parts = pattern.split("*")
    for part in parts:
        if part:
            check_id(part, "twin pattern")
    if "" in parts[1:-1]:
        raise ValueError(f"a twin pattern may not have '**'; got {pattern!r}")
    return "$*".join(parts)


def any_layer_pattern(twin: str, topic: str) -> str:
    """Subscribe pattern for one topic of every layer of one twin: ``dtpf/<twin>/*/<topic>``."""
    return f"{PREFIX}/{check_id(twin, 'twin id')}/*/{check_topic_name(topic)}"
