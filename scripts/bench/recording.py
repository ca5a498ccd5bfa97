"""Cost of recording one lockstep step to MCAP: the two particle sets of a step.

Per step the recorder writes the propagated and the preprocessed particle
set, each an envelope of N x (d + 1) float64 (d = 1 here). Rows:

- crc32 zlib     CPython's ``zlib.crc32`` of one payload (what the mcap package uses)
- crc32 zlib-ng  ``dtpf.recording.crc.crc32`` (zlib-ng, the same function)
- write, mcap as shipped   ``McapRecording.write`` of both sets with mcap's own zlib CRCs
- write, dtpf              the same with :func:`dtpf.recording.crc.use_fast_crc` (the recorder's setting)

Chunks are uncompressed, as the recorder's ``auto`` picks above 64 KiB.
Methods alternate within every repetition; the file is rewritten from empty
for each and deleted after. Medians.

Run from the repository root::

    python -m dtpf.scripts.bench.recording                    # N = 1e3 .. 1e6
    python -m dtpf.scripts.bench.recording --sizes 1e5 --steps 50
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
import zlib
from pathlib import Path

import mcap

from dtpf.recording import crc
from dtpf.recording.writer import McapRecording
from dtpf.scripts.bench.pipeline import fmt_n, parse_size

KEYS = ("dtpf/bench/entity/particles", "dtpf/bench/information/preprocessed")


def payload_of(n: int) -> bytes:
    """Random bytes the size of a one-dimensional particle set's envelope (a header of about 300 bytes)."""
    return os.urandom(16 * n + 304)


def time_crc(fn, payload: bytes, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn(payload)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def time_writes(payload: bytes, steps: int, fast: bool, folder: Path) -> float:
    """Median seconds to record one step (both sets), over ``steps`` steps."""
    crc.use_fast_crc(fast)
    path = folder / f"bench-{fast}.mcap"
    times = []
    with McapRecording(path, compression="none") as recording:
        for _ in range(steps):
            start = time.perf_counter()
            for key in KEYS:
                recording.write(key, payload)
            times.append(time.perf_counter() - start)
    path.unlink()
    return statistics.median(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.recording", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=[1_000, 10_000, 100_000, 1_000_000],
                        help="particle counts N (default: 1e3 1e4 1e5 1e6)")
    parser.add_argument("--steps", type=int, default=100, help="steps recorded per method and repetition "
                                                                 "(default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=3, help="repetitions (default: %(default)s)")
    args = parser.parse_args(argv)
    if not crc.FAST:
        parser.exit(1, "zlib-ng is not installed: nothing to compare (pip install zlib-ng)\n")
    print(f"# python {platform.python_version()}, mcap {mcap.__version__}, {os.cpu_count()} CPUs")
    rows = []
    with tempfile.TemporaryDirectory(prefix="dtpf-bench-recording-") as folder:
        for n in args.sizes:
            payload = payload_of(n)
            steps = max(5, min(args.steps, int(args.steps * 1e5 / n)))
            crcs = {"zlib": [], "zlib-ng": []}
            writes = {False: [], True: []}
            for repeat in range(args.repeats):
                for fast in ((False, True) if repeat % 2 == 0 else (True, False)):
                    writes[fast].append(time_writes(payload, steps, fast, Path(folder)))
                crcs["zlib"].append(time_crc(zlib.crc32, payload, 50))
                crcs["zlib-ng"].append(time_crc(crc.crc32, payload, 50))
            crc.use_fast_crc()
            row = dict(n=n, mb=len(payload) / 1e6, **{k: statistics.median(v) * 1e3 for k, v in crcs.items()},
                       plain=statistics.median(writes[False]) * 1e3, fast=statistics.median(writes[True]) * 1e3)
            rows.append(row)
            print(f"# N={fmt_n(n)} done", flush=True)
    print()
    print("| N | payload MB | crc32 zlib ms | crc32 zlib-ng ms | step, mcap as shipped ms | step, dtpf ms | dtpf / shipped |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {fmt_n(r['n'])} | {r['mb']:.3g} | {r['zlib']:.3g} | {r['zlib-ng']:.3g} | {r['plain']:.3g} | "
              f"{r['fast']:.3g} | {r['fast'] / r['plain']:.2f} |")
    print()
    print("A step is both particle sets written by McapRecording (uncompressed chunks); medians over "
          f"{args.repeats} repetitions, methods alternating.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
