"""Cost of recording one lockstep step to MCAP: the two particle sets of a step.

Per step the recorder writes the propagated and the preprocessed particle
set, each an envelope of N x (d + 1) float64 (d = 1 here). Rows:

- crc32 zlib     CPython's ``zlib.crc32`` of one payload (what the mcap package uses)
- crc32 zlib-ng  ``dtpf.recording.crc.crc32`` (zlib-ng, the same function)
- write, mcap as shipped   ``mcap.writer.Writer.add_message`` of both sets, with mcap's own zlib CRCs
- write, dtpf              ``McapRecording.write`` of both sets (the recorder's writer,
                           :class:`dtpf.recording.mcap_file.McapWriter`, zlib-ng CRCs)

Chunks are uncompressed, as the recorder's ``auto`` picks above 64 KiB. The process keeps freed large
blocks on its heap, as the recorder does (:func:`dtpf.shell.service.keep_large_blocks`).
Methods alternate within every repetition; the file is rewritten from empty
for each and deleted after. Medians.

``--replay LOG`` instead times the recorder's own work on a log's real messages, in this process, with no
Zenoh: the recorder's admission (each message decoded and checked as a service would, :class:`Admission`)
and the MCAP writer, with lz4 chunks and without, per step (the log's messages / its estimates).

Run from the repository root::

    python -m dtpf.scripts.bench.recording                    # N = 1e3 .. 1e6
    python -m dtpf.scripts.bench.recording --sizes 1e5 --steps 50
    python -m dtpf.scripts.bench.recording --replay runs/ungm.mcap
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
from mcap.writer import CompressionType, Writer

from dtpf.recording import crc
from dtpf.recording.writer import McapRecording
from dtpf.scripts.bench.pipeline import fmt_n, parse_size
from dtpf.shell.service import keep_large_blocks

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


def time_writes(payload: bytes, steps: int, ours: bool, folder: Path) -> float:
    """Median seconds to record one step (both sets), over ``steps`` steps: with the recorder's writer
    (``ours``) or with the mcap package's, as shipped."""
    path = folder / f"bench-{ours}.mcap"
    times = []
    if ours:
        with McapRecording(path, compression="none") as recording:
            for _ in range(steps):
                start = time.perf_counter()
                for key in KEYS:
                    recording.write(key, payload)
                times.append(time.perf_counter() - start)
    else:
        crc.use_fast_crc(False)
        with open(path, "wb") as stream:
            writer = Writer(stream, chunk_size=1 << 20, compression=CompressionType.NONE)
            writer.start(profile="", library="bench")
            channels = [writer.register_channel(topic=key, message_encoding="dtpf-envelope", schema_id=0)
                        for key in KEYS]
            for _ in range(steps):
                start = time.perf_counter()
                for channel in channels:
                    now = time.time_ns()
                    writer.add_message(channel, log_time=now, data=payload, publish_time=now)
                times.append(time.perf_counter() - start)
            writer.finish()
    path.unlink()
    return statistics.median(times)


class _Shell:
    """What :class:`~dtpf.recording.admission.Admission` asks of its service: counts, the run, no shape; a message
    it rejects is counted here (a log the recorder wrote holds none it would reject)."""

    def __init__(self):
        self.received = self.rejected = 0
        self.shape = None
        self.config = None

    def reject(self, reason: str, detail: str = "", key=None) -> None:
        self.rejected += 1


def replay(path: Path, repeats: int) -> list[str]:
    """The table of ``--replay``: ms per step of each part of the recorder's work on the log's messages."""
    from types import SimpleNamespace

    from dtpf.messages.codec import decode_for_key
    from dtpf.recording.logfile import read_log
    from dtpf.recording.admission import Admission

    items = [SimpleNamespace(key=m.topic, payload=bytes(m.data)) for m in read_log(path).messages]
    steps = sum(1 for item in items if item.key.endswith("/entity/estimate"))
    if not steps:
        raise SystemExit(f"{path}: no estimate in the log: nothing to count steps by")
    crc.use_fast_crc()

    def admit_and_write(compression: str, folder: Path) -> float:
        admission = Admission(_Shell(), all_twins=True)
        start = time.perf_counter()
        with McapRecording(folder / "replay.mcap", compression=compression) as recording:
            for item in items:
                admission.record(recording, item)
        return time.perf_counter() - start

    def write(compression: str, folder: Path) -> float:
        start = time.perf_counter()
        with McapRecording(folder / "replay.mcap", compression=compression) as recording:
            for item in items:
                recording.write(item.key, item.payload)
        return time.perf_counter() - start

    def decode(_: str, folder: Path) -> float:
        start = time.perf_counter()
        for item in items:
            decode_for_key(item.key, item.payload)
        return time.perf_counter() - start

    parts = [("decode (the admission's part)", decode, "-"), ("write, lz4 chunks", write, "lz4"),
             ("write, no compression", write, "none"), ("admission and write, lz4 (the recorder while a set is at most 64 KiB)",
                                                        admit_and_write, "lz4"),
             ("admission and write, no compression", admit_and_write, "none")]
    times: dict[str, list[float]] = {name: [] for name, _, _ in parts}
    with tempfile.TemporaryDirectory(prefix="dtpf-bench-replay-") as folder:
        for repeat in range(repeats):
            for name, fn, compression in (parts if repeat % 2 == 0 else parts[::-1]):
                times[name].append(fn(compression, Path(folder)))
    lines = [f"{path}: {len(items):,} messages, {steps:,} steps ({len(items) / steps:.1f} messages a step, "
             f"{sum(len(i.payload) for i in items) / steps / 1e3:.1f} kB a step); medians over {repeats} "
             f"repetitions", "", "| part | ms / step |", "|---|---|"]
    lines += [f"| {name} | {statistics.median(t) / steps * 1e3:.3f} |" for name, t in times.items()]
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dtpf.scripts.bench.recording", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=[1_000, 10_000, 100_000, 1_000_000],
                        help="particle counts N (default: 1e3 1e4 1e5 1e6)")
    parser.add_argument("--steps", type=int, default=100, help="steps recorded per method and repetition "
                                                                 "(default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=3, help="repetitions (default: %(default)s)")
    parser.add_argument("--replay", type=Path, default=None, metavar="LOG",
                        help="time the recorder's admission and writer on this log's messages instead")
    args = parser.parse_args(argv)
    # The recorder's allocator (run_service): freed sets stay on the heap. Without it every 1.6 MB buffer of
    # mcap's copies is mapped afresh and its pages fault: a step of N = 1e5 took 5.4 ms to write, not 0.92.
    keep_large_blocks()
    if args.replay is not None:
        print("\n".join(replay(args.replay, args.repeats)))
        return 0
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
                for ours in ((False, True) if repeat % 2 == 0 else (True, False)):
                    writes[ours].append(time_writes(payload, steps, ours, Path(folder)))
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
    print("A step is both particle sets written with mcap's writer (zlib CRCs) and with the recorder's "
          "(McapRecording, zlib-ng CRCs), uncompressed chunks; medians over "
          f"{args.repeats} repetitions, methods alternating.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
