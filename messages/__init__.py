"""Everything that crosses Zenoh: message models, key expressions, one codec.

The recommended import is::

    from dtpf.messages import ParticleSet, WeightState, encode, decode, keys

Publish::

    message = WeightState(run_id="r1", twin_id="ungm-1", step=k, ...)  # validated here
    session.put(keys.key_for(message), encode(message))

Receive::

    message = decode_for_key(str(sample.key_expr), sample.payload.to_bytes())
    # MessageError (a ValueError) on anything malformed or on the wrong key

Record (MCAP): the key expression is the topic;
``writer.register_schema(*schema_for(cls))`` and
``writer.register_channel(key, message_encoding(cls), schema_id)``. Read back
with ``make_reader(f, decoder_factories=[McapDecoderFactory()])``.

Particle sets travel in a binary envelope (JSON header + raw little-endian
float64; layout in :mod:`dtpf.messages.codec` and ``docs/guides/encoding.md``), every other
message as plain JSON that Foxglove can plot. Array validation shared with the
algorithms lives in :mod:`dtpf.messages.arrays`, per-step random streams in
:mod:`dtpf.messages.streams`, the names a configuration may use in
:mod:`dtpf.messages.names`.

The wire contract is the ground floor: it imports no layer (entity,
information, system) and no command; every other package may import it.
"""
__all__ = [
    "Estimate", "Layer", "Message", "ParticleSet", "ParticleSetKind", "PSCommand", "ServiceState",
    "Status", "Time", "WeightState", "Observation",
    "MessageError", "encode", "decode", "decode_for_key",
    "McapDecoderFactory", "SchemaRecord", "message_encoding", "schema_for", "json_schema",
    "keys",
]

# Names are imported on first use (PEP 562), so that ``import dtpf.messages.arrays``
# from the numeric code does not pull in pydantic, mcap and the codec.
_HOMES = {
    **dict.fromkeys(["Estimate", "Layer", "Message", "ParticleSet", "ParticleSetKind", "PSCommand",
                     "ServiceState", "Status", "Time", "WeightState", "Observation"], "dtpf.messages.models"),
    **dict.fromkeys(["MessageError", "encode", "decode", "decode_for_key", "McapDecoderFactory",
                     "SchemaRecord", "message_encoding", "schema_for"], "dtpf.messages.codec"),
    "json_schema": "dtpf.messages.schema",
}


def __getattr__(name: str):
    import importlib

    if name == "keys":
        return importlib.import_module("dtpf.messages.keys")
    if name in _HOMES:
        return getattr(importlib.import_module(_HOMES[name]), name)
    raise AttributeError(f"module 'messages' has no attribute {name!r}")
