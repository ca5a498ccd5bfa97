"""Encode/decode time and size of one ParticleSet, three ways.

(a) envelope  dtpf's binary envelope: JSON header + raw little-endian float64
              (``dtpf.messages.codec.encode`` / ``decode``; decode includes full
              validation of the arrays and fields).
(b) base64    pydantic JSON, the arrays as ``bytes`` fields in base64
              (``ser_json_bytes='base64'``, pydantic's URL-safe alphabet).
(c) lists     pydantic JSON, the arrays as ``list[float]``.

All three decode into the same validated :class:`~dtpf.messages.models.ParticleSet`,
so the comparison is about the encoding; the row "validation" is that common
step alone (constructing a ParticleSet from fields and arrays already in
memory, which checks every field and array). Methods are interleaved within every
repetition (order rotated), each decode is checked bit-exact once, and the
table shows medians.

Run from the repository root::

    python -m dtpf.scripts.bench.encoding                 # N = 1e3 .. 1e6
    python -m dtpf.scripts.bench.encoding --sizes 1000 10000 --scale 0.2
"""
from __future__ import annotations

import argparse
import gc
import platform
import statistics
import time
from typing import Callable

import numpy as np
import pydantic
from pydantic import BaseModel, ConfigDict

from dtpf.messages.codec import decode, encode
from dtpf.messages.models import ParticleSet, Time

#: Repetitions per N at --scale 1 (fewer for the large sizes).
REPEATS = {1_000: 201, 10_000: 101, 100_000: 21, 1_000_000: 7}


class _Header(BaseModel):
    run_id: str
    twin_id: str
    step: int
    stamp: Time
    layer: str
    kind: str
    observation: list[float]


class Base64ParticleSet(_Header):
    """(b): arrays as base64 ``bytes`` in JSON."""

    model_config = ConfigDict(ser_json_bytes="base64", val_json_bytes="base64")
    shape: list[int]
    particles: bytes
    weights: bytes


class ListParticleSet(_Header):
    """(c): arrays as JSON lists of numbers."""

    particles: list[list[float]]
    weights: list[float]


def _header(message: ParticleSet) -> dict:
    return dict(run_id=message.run_id, twin_id=message.twin_id, step=message.step, stamp=message.stamp,
                layer=message.layer.value, kind=message.kind.value, observation=message.observation)


def make_message(n: int, seed: int = 0) -> ParticleSet:
    rng = np.random.default_rng(seed)
    weights = rng.random(n)
    weights /= weights.sum()
    return ParticleSet(run_id="bench", twin_id="ungm-1", step=1, kind="propagated",
                       particles=rng.normal(size=n), weights=weights, observation=[0.5])


def _validate(header: _Header, particles, weights) -> ParticleSet:
    fields = {name: getattr(header, name) for name in _Header.model_fields}
    return ParticleSet(**fields, particles=particles, weights=weights)


# Each method: encode(ParticleSet) -> bytes, decode(bytes) -> ParticleSet.
def _envelope_encode(m: ParticleSet) -> bytes:
    return encode(m)


def _envelope_decode(b: bytes):
    return decode(b, ParticleSet)


def _base64_encode(m: ParticleSet) -> bytes:
    return Base64ParticleSet(**_header(m), shape=list(m.particles.shape), particles=m.particles.tobytes(),
                             weights=m.weights.tobytes()).model_dump_json().encode()


def _base64_decode(b: bytes):
    m = Base64ParticleSet.model_validate_json(b)
    particles = np.frombuffer(m.particles, "<f8").reshape(m.shape)
    return _validate(m, particles, np.frombuffer(m.weights, "<f8"))


def _lists_encode(m: ParticleSet) -> bytes:
    return ListParticleSet(**_header(m), particles=m.particles.tolist(),
                           weights=m.weights.tolist()).model_dump_json().encode()


def _lists_decode(b: bytes):
    m = ListParticleSet.model_validate_json(b)
    return _validate(m, np.array(m.particles), np.array(m.weights))


METHODS: dict[str, tuple[Callable, Callable]] = {
    "(a) envelope": (_envelope_encode, _envelope_decode),
    "(b) base64": (_base64_encode, _base64_decode),
    "(c) lists": (_lists_encode, _lists_decode),
}


def _timed(fn, arg):
    gc.disable()
    try:
        start = time.perf_counter_ns()
        out = fn(arg)
        return out, (time.perf_counter_ns() - start) / 1e6
    finally:
        gc.enable()


def bench(n: int, repeats: int) -> list[dict]:
    """Median encode/decode ms and size of every method at one N."""
    message = make_message(n)
    names = list(METHODS)
    for name, (enc, dec) in METHODS.items():  # warm-up and exactness check
        decoded = dec(enc(message))
        if decoded.particles.tobytes() != message.particles.tobytes() or \
                decoded.weights.tobytes() != message.weights.tobytes() or decoded != message:
            raise AssertionError(f"{name} is not bit-exact at N={n}")
    times = {name: ([], []) for name in names + ["validation"]}
    sizes = {}
    for rep in range(repeats):
        order = names[rep % len(names):] + names[:rep % len(names)]
        for name in order:
            enc, dec = METHODS[name]
            payload, t_enc = _timed(enc, message)
            _, t_dec = _timed(dec, payload)
            times[name][0].append(t_enc)
            times[name][1].append(t_dec)
            sizes[name] = len(payload)
            del payload
        _, t_val = _timed(lambda m: ParticleSet(**m.__dict__), message)
        times["validation"][1].append(t_val)
        gc.collect()
    rows = []
    for name in names:
        rows.append(dict(n=n, method=name, size=sizes[name], encode=statistics.median(times[name][0]),
                         decode=statistics.median(times[name][1])))
    rows.append(dict(n=n, method="validation", size=None, encode=None,
                     decode=statistics.median(times["validation"][1])))
    return rows


def _fmt(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.4f}" if value < 0.1 else f"{value:.3f}" if value < 10 else f"{value:.1f}"


def table(rows: list[dict]) -> str:
    """Markdown table: medians in ms, ratios against (a) of the same N."""
    lines = ["| N | method | bytes | encode ms | decode ms | enc+dec ms | size ×(a) | encode ×(a) | decode ×(a) "
             "| enc+dec ×(a) |", "|---|---|---|---|---|---|---|---|---|---|"]
    base = {row["n"]: row for row in rows if row["method"] == "(a) envelope"}
    for row in rows:
        a = base[row["n"]]
        if row["encode"] is None:
            lines.append(f"| {row['n']:.0e} | {row['method']} | - | - | {_fmt(row['decode'])} | - | - | - "
                         f"| ×{row['decode'] / a['decode']:.2f} | - |")
            continue
        total, a_total = row["encode"] + row["decode"], a["encode"] + a["decode"]
        lines.append(
            f"| {row['n']:.0e} | {row['method']} | {row['size']:,} | {_fmt(row['encode'])} | {_fmt(row['decode'])} "
            f"| {_fmt(total)} | ×{row['size'] / a['size']:.2f} | ×{row['encode'] / a['encode']:.1f} "
            f"| ×{row['decode'] / a['decode']:.1f} | ×{total / a_total:.1f} |")
    return "\n".join(lines)


def main(sizes: list[int], scale: float) -> None:
    print(f"# python {platform.python_version()}, numpy {np.__version__}, pydantic {pydantic.VERSION}, "
          f"{platform.machine()}; d = 1; medians")
    rows = []
    for n in sizes:
        repeats = max(3, round(REPEATS.get(n, 11) * scale))
        start = time.perf_counter()
        rows += bench(n, repeats)
        print(f"# N={n:.0e}: {repeats} repetitions in {time.perf_counter() - start:.1f} s", flush=True)
    print(table(rows))


# --- Command line argument parsing ---
if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=list(REPEATS), help="particle counts N")
    parser.add_argument("--scale", type=float, default=1.0, help="multiply the repetition counts")
    args = parser.parse_args()
    main(args.sizes, args.scale)
