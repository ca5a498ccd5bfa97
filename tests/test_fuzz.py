"""Fuzzing the decoders: every payload decodes to a valid message or raises MessageError, nothing else.

Everything that arrives over Zenoh or sits in an MCAP log goes through
``dtpf.messages.codec.decode`` / ``decode_for_key`` (and ``dtpf.recording.logfile.read_log``
for logs), so those must be total: for any bytes, a valid message of the class
asked for, or :class:`~dtpf.messages.codec.MessageError`; for any file, a
:class:`~dtpf.recording.logfile.Log` or :class:`~dtpf.recording.logfile.LogError`. Another
exception there would kill a layer's receive loop or the log inspector on one bad
packet or file.

What is thrown (strategies in ``tests/fuzz_payloads.py``), in-process:

- valid messages of every class, built with the real models from random valid
  field values (particle sets with random N <= 64 and d <= 4);
- the same payloads mutated: the JSON tree (wrong types, wrong enum strings,
  NaN/Infinity, huge ints and strings, 10,000-deep nesting, keys deleted, added,
  duplicated, reordered; wrong run ids and steps), the envelope layout (claimed
  header size, version, padding, dtypes, shapes and offsets up to 2**64, the data
  section), the bytes (truncation anywhere, bit flips, splices);
- raw bytes and JSON-looking text.

Each payload goes to every decoder: ``decode(p)``, ``decode(p, expected=C)`` for
each message class, ``decode_for_key(k, p)`` for each topic key (and a few keys
that are not topics), ``decode(bytearray(p))``. The four payload families have
quotas adding up to 10,000 distinct payloads, so each decoder sees at least that
many. A decoded message must be of the class asked for, belong on its key, and
re-encode to itself. Hypothesis runs derandomized, without a database, so CI
sees the same payloads every time.

A stream of payloads with steps duplicated and out of order decodes as each
payload would alone: the decoders keep no state.

Nothing is timed. Memory is guarded by claimed sizes instead: envelopes that
claim arrays of 2**31 to 2**64 elements, and log chunks that claim 8 GiB, must be
refused (or read) while the traced allocations stay small (tracemalloc counts
what was asked of the allocator, even when the pages are never touched). A
decoder that allocated what such a claim says would show it there, or run the
test out of memory.

MCAP logs (a few hundred cases: they are slower) are written with McapRecording,
uncompressed, lz4 and zstd, with duplicate and out-of-order steps and now and
then a damaged payload, then cut, flipped and lied about record by record;
``read_log`` must return a Log or raise LogError, ``Log.decoded()`` must give a
message or a MessageError for each message, a cut log keeps a prefix of the
messages, and ``write_log`` writes back a sound file with the same messages.
"""
from __future__ import annotations

import hashlib
import tempfile
import tracemalloc
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import zstandard
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from dtpf.messages import keys
from dtpf.messages.codec import MessageError, decode, decode_for_key, encode
from dtpf.messages.keys import MESSAGE_CLASSES
from dtpf.messages.models import Message, ParticleSet
from dtpf.recording.logfile import Log, LogError, read_log, write_log
from dtpf.recording.writer import McapRecording

from fuzz_payloads import (
    MESSAGE_STRATEGIES,
    TWIN,
    Case,
    Envelope,
    byte_mutated_cases,
    chunk_record,
    envelope_mutated_cases,
    first_chunk,
    json_mutated_cases,
    log_mutation,
    log_payloads,
    lz4_with_content_size,
    raw_cases,
    topic_keys,
    valid_cases,
)

#: Distinct payloads each family must throw at every decoder (together at least 10,000), and how many
#: examples to draw per payload needed: a derandomized run draws some payloads again (short cuts, mostly).
QUOTAS = {"json": 3_000, "envelope": 3_000, "bytes": 3_000, "raw": 1_000}
MARGINS = {"json": 1.35, "envelope": 1.25, "bytes": 1.5, "raw": 1.2}
LOG_CASES = 300


def fuzz_settings(examples: int) -> settings:
    return settings(max_examples=examples, deadline=None, database=None, derandomize=True,
                    phases=[Phase.explicit, Phase.generate, Phase.shrink],
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.filter_too_much, HealthCheck.large_base_example])


# --- the decoders, and what a successful decode must look like ---

NOT_TOPIC_KEYS = [f"dtpf/{TWIN}/entity/unknown", f"dtpf/{TWIN}/kitchen/particles", "dtpf/t 1/entity/particles",
                  f"zenoh/{TWIN}/entity/particles", ""]


def _decoders() -> list[tuple[str, object, object]]:
    """(name, decode function, what the result must be: None any message, a class, or a key's topic)."""
    out = [("decode", decode, None)]
    out += [(f"decode[{cls.__name__}]", partial(decode, expected=cls), cls) for cls in MESSAGE_CLASSES.values()]
    out += [(f"decode_for_key[{key}]", partial(decode_for_key, key), key) for key in topic_keys() + NOT_TOPIC_KEYS]
    return out


DECODERS = _decoders()


def assert_same(a: Message, b: Message) -> None:
    """Field by field; arrays bit for bit, with shape."""
    assert type(a) is type(b), (type(a), type(b))
    for name in type(a).model_fields:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert y.dtype == np.float64 and x.shape == y.shape and x.tobytes() == y.tobytes(), name
        else:
            assert x == y and type(x) is type(y), (name, x, y)


def assert_belongs(message: Message, want) -> None:
    """A decoded message is of the class asked for and, on a key, belongs there."""
    assert isinstance(message, Message) and type(message) in MESSAGE_CLASSES.values()
    if isinstance(want, type):
        assert type(message) is want
    elif isinstance(want, str):
        topic = keys.topic_of(want)  # a key that is not a topic never decodes
        assert type(message) is topic.message
        assert (message.twin_id, message.layer, getattr(message, "kind", None)) == (TWIN, topic.layer, topic.kind)


def assert_re_encodes(message: Message) -> None:
    payload = encode(message)
    again = decode(payload)
    assert_same(again, message)
    assert encode(again) == payload


def throw(case: Case) -> dict[str, Message | None]:
    """Every decoder on ``case.payload``: the message each returned, or None for a MessageError.

    Any other exception fails, naming the decoder and the payload.
    """
    outcomes: dict[str, Message | None] = {}
    for name, decoder, want in DECODERS:
        try:
            message = decoder(case.payload)
        except MessageError as error:
            assert isinstance(error.reason, str) and error.reason, f"{name}: MessageError without a reason"
            if isinstance(want, str):
                assert error.key == want, f"{name}: MessageError names key {error.key!r}"
            outcomes[name] = None
            continue
        except Exception as error:
            raise AssertionError(f"{name} raised {type(error).__name__}: {error}\n  on {case!r}") from error
        assert_belongs(message, want)
        outcomes[name] = message
    try:
        aliased = decode(bytearray(case.payload))
    except MessageError:
        aliased = None
    except Exception as error:
        raise AssertionError(f"decode(bytearray) raised {type(error).__name__}: {error}\n  on {case!r}") from error
    assert (aliased is None) == (outcomes["decode"] is None), f"bytes and bytearray decode differently: {case!r}"
    check_outcomes(outcomes, case)
    return outcomes


def check_outcomes(outcomes: dict[str, Message | None], case: Case) -> None:
    """What succeeded agrees across decoders and re-encodes to itself."""
    for name, message in outcomes.items():
        if message is not None:
            same_class = outcomes[f"decode[{type(message).__name__}]"]
            assert same_class is not None, f"{name} decoded a {type(message).__name__}, expected= did not: {case!r}"
            assert_same(same_class, message)
    for cls in MESSAGE_CLASSES.values():
        if outcomes[f"decode[{cls.__name__}]"] is not None:
            assert_re_encodes(outcomes[f"decode[{cls.__name__}]"])
    if not case.mutations:  # the untouched encoding of a valid message decodes back to it, on its own key
        assert outcomes["decode"] is not None, f"a valid message did not decode: {case!r}"
        assert_same(outcomes["decode"], case.origin)
        if case.origin.twin_id == TWIN:
            assert_same(outcomes[f"decode_for_key[{keys.key_for(case.origin)}]"], case.origin)


def fuzz(strategy, quota: int, margin: float) -> int:
    """Throw at least ``quota`` distinct payloads of ``strategy`` at every decoder; returns how many."""
    seen: set[bytes] = set()

    @fuzz_settings(int(quota * margin))
    @given(strategy)
    def throw_one(case: Case) -> None:
        digest = hashlib.blake2b(case.payload, digest_size=16).digest()
        if digest in seen:  # drawn again (short cuts often are): thrown already
            return
        throw(case)
        seen.add(digest)

    throw_one()
    assert len(seen) >= quota, f"only {len(seen)} distinct payloads of {quota}"
    return len(seen)


# --- in-process fuzzing of the decoders ---

def test_quotas_give_every_decoder_ten_thousand_payloads():
    assert sum(QUOTAS.values()) >= 10_000
    assert len(DECODERS) == 1 + len(MESSAGE_CLASSES) + len(keys.TOPICS) + len(NOT_TOPIC_KEYS)


def test_valid_messages_of_every_class_decode_back_exactly():
    # Guards the generator: the payloads the mutations start from are valid, of every class.
    classes = set()

    @fuzz_settings(300)
    @given(valid_cases())
    def round_trip(case: Case) -> None:
        classes.add(type(case.origin))
        outcomes = throw(case)
        assert outcomes["decode"] is not None

    round_trip()
    assert classes == set(MESSAGE_CLASSES.values())


def test_decoders_are_total_on_mutated_json():
    fuzz(json_mutated_cases(), QUOTAS["json"], MARGINS["json"])


def test_decoders_are_total_on_mutated_envelopes():
    fuzz(envelope_mutated_cases(), QUOTAS["envelope"], MARGINS["envelope"])


def test_decoders_are_total_on_byte_level_mutations():
    fuzz(byte_mutated_cases(), QUOTAS["bytes"], MARGINS["bytes"])


def test_decoders_are_total_on_raw_bytes():
    fuzz(raw_cases(), QUOTAS["raw"], MARGINS["raw"])


@fuzz_settings(100)
@given(cls=st.sampled_from(list(MESSAGE_STRATEGIES)), data=st.data())
def test_decoding_is_stateless_across_duplicate_and_reordered_steps(cls, data):
    # A stream with steps repeated and out of order: each payload decodes as it would alone.
    messages = data.draw(st.lists(MESSAGE_STRATEGIES[cls], min_size=1, max_size=5))
    order = data.draw(st.lists(st.integers(0, len(messages) - 1), min_size=2, max_size=12))
    payloads = [encode(m) for m in messages]
    alone = [decode_for_key(keys.key_for(m), p) for m, p in zip(messages, payloads)]
    for i in order:
        got = decode_for_key(keys.key_for(messages[i]), payloads[i])
        assert_same(got, alone[i])
        assert_same(got, messages[i])


# --- claimed sizes: refused without allocating them ---

def traced_peak(function) -> tuple[int, object]:
    """(peak bytes allocated while ``function`` ran, its result or the exception it raised)."""
    tracemalloc.start()
    try:
        try:
            outcome = function()
        except Exception as error:  # returned, so the caller can say which
            outcome = error
        return tracemalloc.get_traced_memory()[1], outcome
    finally:
        tracemalloc.stop()


def _envelope_with(edit) -> bytes:
    message = ParticleSet(run_id="r", twin_id=TWIN, step=1, kind="propagated", particles=np.zeros((4, 2)),
                          weights=np.full(4, 0.25))
    envelope = Envelope.parse(encode(message))
    edit(envelope, dict(envelope.header)["arrays"])
    return envelope.build()


def _set(descriptor, key, value):
    descriptor[[name for name, _ in descriptor].index(key)] = (key, value)


HUGE_CLAIMS = {
    "header size 2**32-1": lambda e, a: setattr(e, "header_size", 2**32 - 1),
    "header size 2**31": lambda e, a: setattr(e, "header_size", 2**31),
    "particles 2**20 x 2**20": lambda e, a: _set(a[0], "shape", [2**20, 2**20]),
    "particles 2**31 x 2": lambda e, a: _set(a[0], "shape", [2**31, 2]),
    "particles 2**62 x 2**62": lambda e, a: _set(a[0], "shape", [2**62, 2**62]),
    "weights 2**40": lambda e, a: _set(a[1], "shape", [2**40]),
    "weights 2**64": lambda e, a: _set(a[1], "shape", [2**64]),
    "weights offset 2**62": lambda e, a: _set(a[1], "offset", 2**62),
    "particles 0 x 2**40": lambda e, a: _set(a[0], "shape", [0, 2**40]),
    "particles 0 x 2**62": lambda e, a: _set(a[0], "shape", [0, 2**62]),
    "particles 2**62 x 0": lambda e, a: _set(a[0], "shape", [2**62, 0]),
    "particles 0 x 2**63": lambda e, a: _set(a[0], "shape", [0, 2**63]),
}


@pytest.mark.parametrize("claim", HUGE_CLAIMS)
def test_envelopes_claiming_huge_arrays_are_refused_without_allocating_them(claim):
    payload = _envelope_with(HUGE_CLAIMS[claim])
    for name, decoder, _ in DECODERS:
        peak, outcome = traced_peak(lambda: decoder(payload))
        assert isinstance(outcome, MessageError), f"{name} on {claim}: {type(outcome).__name__}: {outcome}"
        assert peak < (1 << 20), f"{name} on {claim}: allocated {peak:,} bytes for a {len(payload)}-byte payload"


# --- MCAP logs ---

def record_log(path: Path, payloads: list[tuple[str, bytes]], compression: str, chunk_size: int) -> bytes:
    with McapRecording(path, compression=compression, chunk_size=chunk_size, flush_interval=1e9) as recording:
        for i, (key, payload) in enumerate(payloads):
            recording.write(key, payload, 1_700_000_000_000_000_000 + i)
    return path.read_bytes()


def as_tuples(log: Log) -> list[tuple]:
    return [(m.topic, m.log_time, m.publish_time, m.sequence, m.data) for m in log.messages]


def test_read_log_is_total_on_damaged_recordings():
    seen: set[bytes] = set()
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        source, damaged, rewritten = folder / "source.mcap", folder / "damaged.mcap", folder / "rewritten.mcap"

        @fuzz_settings(int(LOG_CASES * 1.5))
        @given(payloads=log_payloads(), compression=st.sampled_from(["none", "lz4", "zstd"]),
               chunk_size=st.sampled_from([64, 512, 1 << 20]), data=st.data())
        def read_damaged(payloads, compression, chunk_size, data):
            original = record_log(source, payloads, compression, chunk_size)
            mutated, truncated = data.draw(log_mutation(original))
            digest = hashlib.blake2b(mutated, digest_size=16).digest()
            if digest in seen:  # the empty file, mostly
                return
            damaged.write_bytes(mutated)
            try:
                log = read_log(damaged)
                decoded = [message for _, message in log.decoded()]
            except LogError:
                seen.add(digest)
                return
            except Exception as error:
                raise AssertionError(f"reading raised {type(error).__name__}: {error} on {len(mutated)} bytes "
                                     f"({compression}): {mutated[:200]!r}") from error
            assert isinstance(log, Log) and (log.problem is None or isinstance(log.problem, str))
            assert all(isinstance(message, (Message, MessageError)) for message in decoded)
            if truncated:  # a cut log keeps a prefix of the messages, in file order
                intact = read_log(source)
                assert intact.complete and intact.problem is None
                assert as_tuples(log) == as_tuples(intact)[:len(log.messages)]
            write_log(log, rewritten)
            again = read_log(rewritten)
            assert again.complete and again.problem is None, again.problem
            assert as_tuples(again) == as_tuples(log)
            seen.add(digest)

        read_damaged()
    assert len(seen) >= LOG_CASES, f"only {len(seen)} distinct files of {LOG_CASES}"


def test_logs_holding_envelopes_with_huge_claims_are_read():
    # What the recorder wrote is read back whatever it holds: each bad payload is a MessageError of
    # Log.decoded(), and a cut log (whose problem names the last step, so decodes the last messages)
    # reads too.
    good = ParticleSet(run_id="r", twin_id=TWIN, step=1, kind="propagated", particles=np.zeros((4, 2)),
                       weights=np.full(4, 0.25))
    key = keys.key_for(good)
    with tempfile.TemporaryDirectory() as folder:
        path, cut = Path(folder) / "claims.mcap", Path(folder) / "cut.mcap"
        data = record_log(path, [(key, encode(good))] + [(key, _envelope_with(edit)) for edit in HUGE_CLAIMS.values()],
                          "none", 1 << 20)
        cut.write_bytes(data[:-100])  # inside the summary: every message is there, the footer is not
        for log_path in (path, cut):
            try:
                log = read_log(log_path)
                decoded = [message for _, message in log.decoded()]
            except Exception as error:
                raise AssertionError(f"reading {log_path.name}: {type(error).__name__}: {error}") from error
            assert len(decoded) == 1 + len(HUGE_CLAIMS)
            assert_same(decoded[0], good)
            assert all(isinstance(message, MessageError) for message in decoded[1:])


# - chunks that claim huge uncompressed sizes -

CLAIM = 2**33  # 8 GiB, from a file of a few kilobytes


def _claiming_log(folder: Path, compression: str, cut: bool) -> Path:
    """A recording whose first chunk claims CLAIM bytes uncompressed, in the chunk record or the lz4 frame."""
    payloads = [(keys.key_for(m), encode(m)) for m in (
        ParticleSet(run_id="r", twin_id=TWIN, step=k, kind="propagated", particles=np.arange(8.0),
                    weights=np.full(8, 0.125)) for k in (1, 2, 3))]
    data = record_log(folder / f"{compression}.mcap", payloads, compression, 1 << 20)
    start, end, chunk = first_chunk(data)
    if compression == "zstd":  # a frame that does not store its content size (zstd allows it): the chunk's counts
        plain = zstandard.ZstdDecompressor().decompress(chunk["records"])
        chunk["records"] = zstandard.ZstdCompressor(write_content_size=False).compress(plain)
    elif compression == "lz4":
        chunk["records"] = lz4_with_content_size(chunk["records"], CLAIM)
    chunk["usize"] = CLAIM
    record = chunk_record(**chunk)
    path = folder / f"{compression}-claims.mcap"
    path.write_bytes(data[:start] + (record[:len(record) // 2] if cut else record + data[end:]))
    return path


@pytest.mark.parametrize("compression, cut", [("none", False), ("none", True), ("zstd", False), ("zstd", True),
                                               ("lz4", False), ("lz4", True)])
def test_chunks_claiming_huge_sizes_are_read_without_allocating_them(tmp_path, compression, cut):
    path = _claiming_log(tmp_path, compression, cut)
    peak, outcome = traced_peak(lambda: read_log(path))
    assert isinstance(outcome, (Log, LogError)), f"{type(outcome).__name__}: {outcome}"
    assert peak < (64 << 20), (f"read_log allocated {peak:,} bytes for a {path.stat().st_size:,}-byte file "
                               f"whose {compression} chunk claims {CLAIM:,} bytes")
