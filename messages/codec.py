"""The one way messages become bytes and bytes become messages.

::

    from dtpf.messages.codec import encode, decode, decode_for_key, MessageError
    payload = encode(message)                       # bytes
    message = decode(payload)                       # any message
    message = decode(payload, expected=WeightState) # or fail
    message = decode_for_key("dtpf/ungm-1/system/ps", payload)

Two encodings:

- JSON messages (everything but :class:`~dtpf.messages.models.ParticleSet`):
  the UTF-8 JSON of the model, every field present (``null`` for absent
  optionals). MCAP message encoding ``json``, schema encoding ``jsonschema``.
- :class:`~dtpf.messages.models.ParticleSet`: the binary envelope, MCAP message
  encoding ``dtpf-envelope``. All integers little-endian::

      offset  size  content
      0       4     magic b"DTPF"
      4       1     version, uint8 = 1
      5       3     reserved, zero
      8       4     H = length of the JSON header in bytes, uint32
      12      H     JSON header, UTF-8:
                      {"message": "dtpf.ParticleSet",
                       "fields": {all scalar fields of the ParticleSet},
                       "arrays": [{"name": "particles", "dtype": "<f8", "shape": [N, d], "offset": 0},
                                  {"name": "weights", "dtype": "<f8", "shape": [N], "offset": 8*N*d}]}
      12+H    P     zero padding, P = (-(12 + H)) mod 8, so the data starts 8-byte aligned
      D=12+H+P      data: each array's raw little-endian float64 bytes, C order,
                    at D + offset; the arrays tile the data exactly and the
                    payload ends with the last one (total = D + 8*N*d + 8*N).

Decoding never returns half a message: any problem (not bytes, truncated,
bad magic or version, header not JSON, lengths that do not add up, a field
or array that fails validation, a message on the wrong key) raises
:class:`MessageError` whose text names what is wrong.

Zero copy: the arrays of a decoded ParticleSet are ``np.frombuffer`` views of
the payload, marked read-only. For a ``bytes`` payload that is safe. For a
``bytearray`` or writable ``memoryview`` the arrays alias the caller's
buffer: do not modify or reuse it while the message is in use (or pass
``bytes(payload)``); ``message.particles.copy()`` gives a writable array.
"""
from __future__ import annotations

import base64
import functools
import json
import math
import struct
import sys
from typing import Annotated, Any, Literal, NamedTuple

import numpy as np
from mcap.decoder import DecoderFactory
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from dtpf.messages import keys
from dtpf.messages.errors import DtpfError
from dtpf.messages.keys import MESSAGE_CLASSES
from dtpf.messages.models import Message, ParticleSet, ParticleSetHeader
from dtpf.messages.schema import json_schema

MAGIC = b"DTPF"
#: How a reference to a set in shared memory starts (:mod:`dtpf.shell.slots`): not a message.
SET_REFERENCE = b"DTPFREF\x01"
VERSION = 1
#: MCAP message encodings.
JSON_ENCODING = "json"
ENVELOPE_ENCODING = "dtpf-envelope"
#: MCAP schema encoding of every dtpf schema (the envelope's is the JSON Schema of its header).
SCHEMA_ENCODING = "jsonschema"
SCHEMA_PREFIX = "dtpf."

_PREFIX = struct.Struct("<4sB3sI")  # magic, version, reserved, header length
_ALIGN = 8
_DTYPE = "<f8"
_ENVELOPE_ARRAYS = ("particles", "weights")
_ENVELOPE_CLASSES: dict[str, type[Message]] = {SCHEMA_PREFIX + "ParticleSet": ParticleSet}
_MAX_INPUT_REPR = 60
#: Schemas named after a well-known type rather than ``dtpf.<class>``, so that Foxglove's panels pick them up.
FOREIGN_SCHEMA_NAMES = {"CompressedImage": "foxglove.CompressedImage", "PointCloud": "foxglove.PointCloud",
                        "ImageAnnotations": "foxglove.ImageAnnotations"}


class MessageError(DtpfError, ValueError):
    """A payload that cannot be decoded into a valid message.

    Attributes
    ----------
    reason : str
        What is wrong, naming the field or byte range and the value.
    key : str or None
        Key expression the payload arrived on, when known.
    step : int or None
        Filter step of the message, when it could be read.
    """

    def __init__(self, reason: str, *, key: str | None = None, step: int | None = None):
        self.reason = reason
        self.key = key
        self.step = step
        context = [f"{name} {value}" for name, value in (("key", key), ("step", step)) if value is not None]
        super().__init__(reason + (f" ({', '.join(context)})" if context else ""))

    def __reduce__(self):
        return _rebuild_error, (self.reason, self.key, self.step)


def _rebuild_error(reason: str, key: str | None, step: int | None) -> MessageError:
    return MessageError(reason, key=key, step=step)


# --- the envelope header, as a model (its JSON Schema is the MCAP schema) ---

class ArrayDescriptor(BaseModel):
    """Where one array sits in the data section of the envelope."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(description="Field name: 'particles' or 'weights'.")
    dtype: Literal["<f8"] = Field(description="numpy dtype string: little-endian float64.")
    shape: list[Annotated[int, Field(ge=0)]] = Field(description="Array shape: [N, d] for particles, [N] for weights.")
    offset: int = Field(ge=0, description="Byte offset from the start of the data section (a multiple of 8).")


class EnvelopeHeader(BaseModel):
    """The JSON header of a binary envelope."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    message: Literal["dtpf.ParticleSet"] = Field(description="Schema name of the message in the envelope.")
    fields: ParticleSetHeader = Field(description="Every field of the message except its arrays.")
    arrays: list[ArrayDescriptor] = Field(description="The arrays, in data-section order.")


# --- encode ---

def encode(message: Message) -> bytes:
    """The payload of ``message``: JSON, or the binary envelope for a ParticleSet."""
    if isinstance(message, ParticleSet):
        return _encode_envelope(message)
    if isinstance(message, Message):
        # Absent, not null: the schemas (Foxglove's subset, dtpf.messages.schema) give an optional field its
        # plain type and leave it out of "required", so a null would fail them.
        return message.model_dump_json(exclude_none=True).encode("utf-8")
    raise TypeError(f"encode() takes a dtpf message, got {type(message).__name__}")


def encode_with_base64(message: Message, raw: bytes) -> bytes:
    """The payload of ``message`` with its ``data`` field set to the standard base64 of ``raw``.

    ``message`` is built with ``data=""``: pydantic validates and writes every other field, and the base64
    text goes into the JSON as it is made (its alphabet needs no escaping). The same bytes as
    ``encode(message)`` with ``data=base64(raw)``, without validating the text and writing it through pydantic
    again, which cost more than making the text.
    """
    empty = b'"data":""'
    payload = encode(message) if getattr(message, "data", None) == "" else b""
    where = payload.find(empty)
    if where < 0 or payload.find(empty, where + 1) >= 0:
        raise ValueError(f"encode_with_base64 takes a {type(message).__name__} built with data=\"\"")
    cut = where + len(empty) - 1
    return b"%s%s%s" % (payload[:cut], base64.b64encode(raw), payload[cut:])


def _little_endian(array: np.ndarray) -> np.ndarray:
    return array if sys.byteorder == "little" else array.astype(_DTYPE)


_EXCLUDED_ARRAYS = frozenset(_ENVELOPE_ARRAYS)


@functools.lru_cache(maxsize=64)  # one entry per set shape a process sends: a run has one or two
def _arrays_json(particles_shape: tuple[int, ...], weights_shape: tuple[int, ...]) -> bytes:
    """The ``arrays`` member of an envelope header whose arrays have these shapes."""
    return json.dumps([
        {"name": "particles", "dtype": _DTYPE, "shape": list(particles_shape), "offset": 0},
        {"name": "weights", "dtype": _DTYPE, "shape": list(weights_shape), "offset": 8 * math.prod(particles_shape)},
    ], separators=(",", ":")).encode("ascii")


def _encode_envelope(message: ParticleSet) -> bytes:
    # One copy of each array, straight into the result.
    return b"".join(encode_parts(message))


def encode_parts(message: ParticleSet) -> tuple[bytes, np.ndarray, np.ndarray]:
    """The envelope of a particle set in three pieces whose concatenation is :func:`encode`'s bytes: the
    prefix, header and padding, then the particles and the weights as little-endian float64 arrays (the
    message's own arrays on a little-endian machine: no copy), for a writer that copies them once, straight
    into its buffer (a shared-memory slot)."""
    particles, weights = message.particles, message.weights
    # The fields go through the same pydantic serializer as JSON messages.
    fields = message.model_dump_json(exclude=_EXCLUDED_ARRAYS, exclude_none=True).encode("utf-8")
    header = b'{"message":"dtpf.ParticleSet","fields":%s,"arrays":%s}' % (
        fields, _arrays_json(particles.shape, weights.shape))
    padding = b"\0" * (-(_PREFIX.size + len(header)) % _ALIGN)
    prefix = _PREFIX.pack(MAGIC, VERSION, b"\0\0\0", len(header))
    return prefix + header + padding, _little_endian(particles), _little_endian(weights)


# --- decode ---

def decode(payload: bytes | bytearray | memoryview, expected: type[Message] | None = None) -> Message:
    """The message in ``payload``, validated.

    Parameters
    ----------
    payload : bytes, bytearray or memoryview
        What :func:`encode` produced.
    expected : message class, optional
        Fail unless the payload holds this class. Without it, a JSON payload
        is matched to the one class whose fields are exactly its keys.

    Raises
    ------
    MessageError
        On any problem; nothing is returned half-decoded.
    """
    try:
        view = memoryview(payload).cast("B")
    except TypeError:
        raise MessageError(f"payload must be bytes, bytearray or memoryview, got {type(payload).__name__}") from None
    if expected is not None and expected not in MESSAGE_CLASSES.values():
        raise TypeError(f"expected must be a dtpf message class, got {expected!r}")
    if bytes(view[:len(SET_REFERENCE)]) == SET_REFERENCE:
        raise MessageError("a reference to a particle set in a publisher's shared memory, not the set: read it "
                           "with dtpf.shell.bus.Inbox, or have the publishers send sets as bytes "
                           "(DTPF_SHARED_SETS=0; docs/guides/encoding.md)")
    envelope = bytes(view[:len(MAGIC)]) == MAGIC
    if expected is ParticleSet or (expected is None and envelope):
        return _decode_envelope(view)
    if envelope:
        raise MessageError(f"expected a JSON {expected.__name__} payload, got a {ENVELOPE_ENCODING} payload")
    return _decode_json(view, expected)


def decode_for_key(key: str, payload: bytes | bytearray | memoryview) -> Message:
    """Decode a payload received on ``key``, with the class the topic table gives.

    Also checks that the message belongs where it arrived: same twin, same
    layer and, for particle sets, the kind of the topic.
    """
    try:
        topic = keys.topic_of(key)
        twin = keys.parse(key)[0]
    except ValueError as exc:
        raise MessageError(str(exc), key=key) from None
    try:
        message = decode(payload, topic.message)
    except MessageError as exc:
        raise MessageError(exc.reason, key=key, step=exc.step) from None
    kind, want_kind = getattr(message, "kind", None), topic.kind
    mismatches = [f"{name} {got!r} (key says {want!r})"
                  for name, got, want in (("twin_id", message.twin_id, twin),
                                          ("layer", message.layer.value, topic.layer.value),
                                          ("kind", kind and kind.value, want_kind and want_kind.value))
                  if got != want]
    if mismatches:
        raise MessageError(f"{type(message).__name__} does not belong on this key: " + ", ".join(mismatches),
                           key=key, step=message.step)
    return message


def _explain(exc: ValidationError) -> str:
    """pydantic's errors as one line: 'field: message (input ...)'."""
    parts = []
    for error in exc.errors(include_url=False):
        loc = ".".join(str(item) for item in error["loc"])
        text = error["msg"]
        if error["type"] not in ("value_error", "missing", "json_invalid"):
            shown = repr(error.get("input"))
            if len(shown) > _MAX_INPUT_REPR:
                shown = shown[:_MAX_INPUT_REPR] + "..."
            text += f" (got {shown})"
        parts.append(f"{loc}: {text}" if loc else text)
    return "; ".join(parts)


def _peek_step(data: Any) -> int | None:
    """The step of a rejected message, if its JSON had a plausible one."""
    step = data.get("step") if isinstance(data, dict) else None
    return step if isinstance(step, int) and not isinstance(step, bool) else None


def _json_loads(data: bytes) -> Any:
    """``json.loads``, with nesting too deep for Python's parser as a ValueError like any bad JSON."""
    try:
        return json.loads(data)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None


def _decode_json(view: memoryview, expected: type[Message] | None) -> Message:
    data = bytes(view)
    cls = expected or _class_of_json(data)
    try:
        return cls.model_validate_json(data, strict=True)
    except ValidationError as exc:
        try:
            step = _peek_step(_json_loads(data))
        except ValueError:
            step = None
        raise MessageError(f"invalid {cls.__name__}: {_explain(exc)}", step=step) from None


def _class_of_json(data: bytes) -> type[Message]:
    """The JSON message class whose field names are exactly the keys of ``data``."""
    try:
        obj = _json_loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise MessageError(f"payload is neither a {ENVELOPE_ENCODING} (magic {MAGIC!r}) nor JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise MessageError(f"JSON payload must be an object, got {type(obj).__name__}")
    keys = set(obj)
    matches = [cls for cls in MESSAGE_CLASSES.values() if cls is not ParticleSet
               and _required(cls) <= keys <= set(cls.model_fields)]
    if len(matches) == 1:
        return matches[0]
    which = "matches no message class" if not matches else \
        f"matches {', '.join(cls.__name__ for cls in matches)}"
    raise MessageError(f"JSON object with keys {sorted(obj)[:20]} {which}; pass expected= or use decode_for_key",
                       step=_peek_step(obj))


def _required(cls: type[Message]) -> set[str]:
    """The fields a JSON message of ``cls`` must carry (the others may be left out)."""
    return {name for name, field in cls.model_fields.items() if field.is_required()}


def _decode_envelope(view: memoryview) -> ParticleSet:
    size = len(view)
    head = bytes(view[:len(MAGIC)])
    if head != MAGIC[:len(head)]:
        raise MessageError(f"{ENVELOPE_ENCODING} must start with magic {MAGIC!r}, got {head!r}")
    if size < _PREFIX.size:
        raise MessageError(f"{ENVELOPE_ENCODING} truncated: {size} bytes, shorter than the {_PREFIX.size}-byte prefix")
    _, version, reserved, header_size = _PREFIX.unpack_from(view)
    if version != VERSION:
        raise MessageError(f"{ENVELOPE_ENCODING} version {version} is not supported (this reader knows {VERSION})")
    if reserved != b"\0\0\0":
        raise MessageError(f"{ENVELOPE_ENCODING} reserved bytes 5-7 must be zero, got {reserved!r}")
    header_end = _PREFIX.size + header_size
    data_start = header_end + (-header_end % _ALIGN)
    if data_start > size:
        raise MessageError(f"{ENVELOPE_ENCODING} header length {header_size} runs past the end of the "
                           f"{size}-byte payload")
    if any(view[header_end:data_start]):
        raise MessageError(f"{ENVELOPE_ENCODING} padding bytes {header_end}-{data_start - 1} must be zero")
    header_bytes = bytes(view[_PREFIX.size:header_end])
    try:
        header = EnvelopeHeader.model_validate_json(header_bytes, strict=True)
    except ValidationError as exc:
        try:
            step = _peek_step(_json_loads(header_bytes).get("fields"))
        except (ValueError, AttributeError):
            step = None
        raise MessageError(f"invalid {ENVELOPE_ENCODING} header: {_explain(exc)}", step=step) from None
    step = header.fields.step
    arrays = _read_arrays(view, header, data_start, step)
    try:  # the header's fields were validated above: only the arrays and their lengths are left
        return ParticleSet.from_header(header.fields, **arrays)
    except ValueError as exc:
        raise MessageError(f"invalid ParticleSet: {exc}", step=step) from None


def _read_arrays(view: memoryview, header: EnvelopeHeader, data_start: int, step: int) -> dict[str, np.ndarray]:
    """The arrays the header describes, as read-only views; checks they tile the data exactly."""
    names = [array.name for array in header.arrays]
    if names != list(_ENVELOPE_ARRAYS):
        raise MessageError(f"{ENVELOPE_ENCODING} arrays must be {list(_ENVELOPE_ARRAYS)} in this order, got {names}",
                           step=step)
    particles_shape, weights_shape = header.arrays[0].shape, header.arrays[1].shape
    if len(particles_shape) != 2 or len(weights_shape) != 1:
        raise MessageError(f"{ENVELOPE_ENCODING} shapes must be [N, d] and [N], got particles {particles_shape}, "
                           f"weights {weights_shape}", step=step)
    # No axis can be longer than the payload has float64s (a zero-length axis beside a 2**62 one
    # would pass the size check and break numpy's reshape).
    most = len(view) // 8
    for array in header.arrays:
        if any(length > most for length in array.shape):
            raise MessageError(f"{ENVELOPE_ENCODING} array {array.name} claims shape {array.shape}, longer than "
                               f"the {len(view)}-byte payload can hold", step=step)
    out, position = {}, 0
    for array in header.arrays:
        if array.offset != position:
            raise MessageError(f"{ENVELOPE_ENCODING} array {array.name} must start at data offset {position}, "
                               f"header says {array.offset}", step=step)
        count = math.prod(array.shape)
        start = data_start + position
        end = start + 8 * count
        if end > len(view):
            raise MessageError(f"{ENVELOPE_ENCODING} truncated: array {array.name} needs bytes {start}-{end - 1}, "
                               f"payload has {len(view)}", step=step)
        # Read-only views of the payload; the model keeps them read-only.
        out[array.name] = np.frombuffer(view, dtype=_DTYPE, count=count, offset=start).reshape(array.shape)
        position += 8 * count
    if data_start + position != len(view):
        raise MessageError(f"{ENVELOPE_ENCODING} length mismatch: header and arrays need {data_start + position} "
                           f"bytes, payload has {len(view)}", step=step)
    return out


# --- MCAP: what a recorder registers, and how a reader decodes ---

class SchemaRecord(NamedTuple):
    """Arguments of ``mcap.writer.Writer.register_schema(name, encoding, data)``."""

    name: str
    encoding: str
    data: bytes


def message_encoding(cls: type[Message]) -> str:
    """MCAP message encoding of a message class: 'json' or 'dtpf-envelope'."""
    return _encoding_of(cls)


def _encoding_of(cls: type[Message]) -> str:
    if cls is ParticleSet:
        return ENVELOPE_ENCODING
    if cls in MESSAGE_CLASSES.values():
        return JSON_ENCODING
    raise TypeError(f"not a dtpf message class: {cls!r}")


def envelope_layout() -> dict:
    """The byte layout of the particle-set envelope, as its schema records it."""
    return {"magic": MAGIC.decode("ascii"), "version": VERSION, "byte_order": "little",
            "prefix": "magic[4] version:uint8 reserved[3]=0 header_length:uint32",
            "prefix_size": _PREFIX.size, "alignment": _ALIGN, "dtype": _DTYPE, "arrays": list(_ENVELOPE_ARRAYS)}


@functools.cache  # one per message class (a few dozen); pydantic's JSON Schema is slow to build, and a
# fleet's recorder asks once per new channel: a large share of its CPU for 100 twins without the cache
def schema_for(cls: type[Message]) -> SchemaRecord:
    """MCAP schema record of a message class (an immutable tuple, made once per class).

    JSON messages: the Foxglove-ready JSON Schema of the model. ParticleSet:
    the JSON Schema of the envelope header, with the byte layout in its
    ``description`` and, machine-readable, as JSON text in ``$comment``
    (:func:`envelope_layout`).
    """
    encoding = message_encoding(cls)
    if encoding == JSON_ENCODING:
        schema = json_schema(cls)
    else:
        schema = json_schema(EnvelopeHeader)
        schema["title"] = SCHEMA_PREFIX + cls.__name__
        schema["description"] = ENVELOPE_LAYOUT
        # The layout as JSON text in $comment, JSON Schema's own annotation: strict validators (ajv in strict
        # mode refused the former "x-dtpf-envelope" keyword) compile the schema, and Foxglove reads no $defs.
        schema["$comment"] = json.dumps(envelope_layout(), separators=(",", ":"))
    data = json.dumps(schema, separators=(",", ":"), sort_keys=False).encode("utf-8")
    return SchemaRecord(schema_name(cls), SCHEMA_ENCODING, data)


def schema_name(cls: type[Message]) -> str:
    """MCAP schema name of a message class: ``dtpf.<class>`` or its well-known name."""
    return FOREIGN_SCHEMA_NAMES.get(cls.__name__, SCHEMA_PREFIX + cls.__name__)


def class_for_schema(name: str) -> type[Message] | None:
    """The message class whose MCAP schema is named ``name``, or None if it is not a dtpf schema."""
    for cls in MESSAGE_CLASSES.values():
        if schema_name(cls) == name:
            return cls
    return None


#: The layout, in words, as embedded in the ParticleSet schema of every MCAP file.
ENVELOPE_LAYOUT = (
    "dtpf-envelope v1 (a ParticleSet). All integers little-endian. "
    "Bytes 0-3: magic 'DTPF'. Byte 4: version (uint8, 1). Bytes 5-7: zero. "
    "Bytes 8-11: H, the length of the JSON header (uint32). Bytes 12 to 12+H: the JSON header (UTF-8), "
    "an object described by this schema: 'fields' holds every scalar field of the message, 'arrays' "
    "lists name, dtype '<f8', shape and byte offset of 'particles' [N, d] then 'weights' [N]. "
    "Then zero padding up to D, the next multiple of 8. Array a starts at byte D + a.offset and holds "
    "prod(a.shape) little-endian float64 values in C order; the payload ends after the last array. "
    "Python: h = int.from_bytes(p[8:12], 'little'); header = json.loads(p[12:12+h]); "
    "D = (12 + h + 7) // 8 * 8; numpy.frombuffer(p, '<f8', count=prod(shape), offset=D + offset)."
)


class McapDecoderFactory(DecoderFactory):
    """Lets ``mcap`` readers decode dtpf channels: ``make_reader(f, decoder_factories=[McapDecoderFactory()])``."""

    def decoder_for(self, message_encoding: str, schema: Any):
        if schema is None or message_encoding not in (JSON_ENCODING, ENVELOPE_ENCODING):
            return None
        cls = class_for_schema(schema.name)
        if cls is None or _encoding_of(cls) != message_encoding:
            return None
        return lambda data: decode(data, cls)
