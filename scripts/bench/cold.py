"""What one message's Python costs when the process did something else in between.

A layer handles one message per step and then waits for the next (a live sensor's
gap, the other layers' work). Microbenchmarks call the same code back to back,
with everything hot in the caches. This benchmark times the per-message work of
the hot path (building and encoding a particle set, decoding it) three ways:
back to back, after sleeping ``--gap`` seconds, and after spinning in Python for
the same time, and prints a table of medians and the ratio to back to back.

Beside the decoding, its floor: reading the same payload with no check at all
(the prefix unpacked, the JSON header parsed by ``json.loads``, the two arrays
as ``np.frombuffer`` views), what any admission of the envelope must at least do.

Run ``python -m dtpf.scripts.bench.cold --help`` for the options.
"""
from __future__ import annotations

import argparse
import json
import statistics
import struct
import time

import numpy as np

from dtpf.messages.codec import decode_for_key, encode
from dtpf.messages.models import ARRAYS_CHECKED, ParticleSet, ParticleSetKind

KEY = "dtpf/t/entity/particles"


def _build(particles: np.ndarray, weights: np.ndarray, step: int) -> bytes:
    """The entity's particle set of one step, built and encoded as the entity does."""
    return encode(ParticleSet.model_validate(dict(
        run_id="r", twin_id="t", step=step, kind=ParticleSetKind.PROPAGATED, particles=particles,
        weights=weights, observation=[1.0]), context=ARRAYS_CHECKED))


#: The envelope's prefix: magic, version, reserved, header length (dtpf.messages.codec).
_PREFIX = struct.Struct("<4sB3sI")


def _read_unchecked(payload: bytes) -> tuple[dict, np.ndarray, np.ndarray]:
    """The header and arrays of an envelope, read without any check (the floor of decoding one)."""
    header_size = _PREFIX.unpack_from(payload)[3]
    header = json.loads(payload[_PREFIX.size:_PREFIX.size + header_size])
    start = _PREFIX.size + header_size + (-(_PREFIX.size + header_size) % 8)
    n, d = header["arrays"][0]["shape"]
    particles = np.frombuffer(payload, "<f8", n * d, start).reshape(n, d)
    return header, particles, np.frombuffer(payload, "<f8", n, start + 8 * n * d)


def _between(mode: str, gap: float) -> None:
    if mode == "sleep":
        time.sleep(gap)
    elif mode == "spin":
        end = time.perf_counter() + gap
        while time.perf_counter() < end:
            pass


def measure(n: int, calls: int, gap: float, mode: str) -> dict[str, float]:
    """Median microseconds of building+encoding, decoding, and reading unchecked one set of ``n`` particles."""
    rng = np.random.default_rng(0)
    particles = rng.normal(size=(n, 1))
    weights = np.full(n, 1.0 / n)
    built, decoded, read = [], [], []
    for step in range(1, calls + 1):
        _between(mode, gap)
        start = time.perf_counter()
        payload = _build(particles, weights, step)
        middle = time.perf_counter()
        decode_for_key(KEY, payload)
        built.append(middle - start)
        decoded.append(time.perf_counter() - middle)
        _between(mode, gap)
        start = time.perf_counter()
        _read_unchecked(payload)
        read.append(time.perf_counter() - start)
    return {"build": statistics.median(built) * 1e6, "decode": statistics.median(decoded) * 1e6,
            "read": statistics.median(read) * 1e6}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.cold", description=__doc__.split("\n\n")[1],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--particles", type=int, default=1000, help="N (default: %(default)s)")
    parser.add_argument("--calls", type=int, default=300, help="calls per mode (default: %(default)s)")
    parser.add_argument("--gap", type=float, default=0.02,
                        help="seconds between calls in the sleep and spin modes (default: %(default)s, a 50 Hz "
                             "sensor)")
    args = parser.parse_args(argv)
    measure(args.particles, 50, 0.0, "tight")  # imports and first calls
    rows = {mode: measure(args.particles, args.calls, args.gap, mode) for mode in ("tight", "sleep", "spin")}
    print(f"`python -m dtpf.scripts.bench.cold --particles {args.particles} --calls {args.calls} --gap {args.gap:g}`\n")
    print("| between calls | build + encode us | ratio | decode us | ratio | read unchecked us | decode / read |")
    print("|---|---|---|---|---|---|---|")
    for mode, label in (("tight", "nothing (back to back)"), ("sleep", f"sleep {args.gap * 1e3:g} ms"),
                        ("spin", f"spin {args.gap * 1e3:g} ms")):
        row = rows[mode]
        print(f"| {label} | {row['build']:.1f} | {row['build'] / rows['tight']['build']:.1f} | "
              f"{row['decode']:.1f} | {row['decode'] / rows['tight']['decode']:.1f} | {row['read']:.1f} | "
              f"{row['decode'] / row['read']:.1f} |")
    print("\nMedians of each mode's calls. 'read unchecked': the same payload read with no check (json.loads of "
          "its header, its arrays as views), after a pause of its own.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
