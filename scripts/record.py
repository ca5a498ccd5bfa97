"""Recorder service: every dtpf message of a twin (or of all twins) into MCAP.

Subscribes to ``dtpf/<twin>/**`` (``--all-twins``: ``dtpf/**``) and writes
each message as received, bytes untouched, one channel per key expression,
schemas embedded. SIGINT or SIGTERM: the messages already received are
written and the file is finished (summary and footer), so the log stays
readable; a SIGKILL loses at most the last ``--flush-interval`` seconds.

Run ``python -m scripts.record --help`` for the options.
"""
from __future__ import annotations

import argparse
import time

import zenoh

from messages import keys
from messages.bus import Inbox, add_zenoh_arguments
from messages.codec import encode
from messages.models import ServiceState
from messages.config import RunConfig, add_run_arguments
from entity import model_ref
from messages.recording import COMPRESSION, McapRecording, auto_compression
from messages.service import ServiceShell, add_service_arguments, run_service

__all__ = ["main"]


def main(config: RunConfig, zenoh_config: zenoh.Config, args: argparse.Namespace) -> int:
    """Record until SIGINT/SIGTERM."""
    pattern = keys.ALL if args.all_twins else keys.twin_pattern(config.twin)
    compression = args.compression
    if compression == "auto":
        compression = auto_compression(config.particles * (model_ref.resolve(config.model_ref).dim + 1) * 8)
    # The file is finished before the Zenoh session closes, so a session slow to close (the
    # launcher SIGKILLs a service after 10 s) cannot cost the log its summary and footer.
    with ServiceShell("recorder", config, zenoh_config) as shell:
        try:
            recording = McapRecording(args.output, compression=compression, flush_interval=args.flush_interval)
        except OSError as error:
            shell.state, shell.last_error = ServiceState.FAILED, f"cannot write the log {args.output}: {error}"
            shell.log.error("%s", shell.last_error)
            return 2
        with recording:
            return _record(shell, recording, pattern, compression, args)


def _record(shell: ServiceShell, recording: McapRecording, pattern: str, compression: str,
            args: argparse.Namespace) -> int:
    """Write what arrives on ``pattern`` until SIGINT/SIGTERM, then what is still in flight."""
    # A live twin may follow another twin's sensor: its observations are recorded too.
    sensor = shell.config.observation_key()
    extra = [sensor] if sensor and not args.all_twins and not sensor.startswith(pattern[:-2]) else []
    inbox = Inbox(shell.session, pattern, *extra)
    shell.running()
    shell.log.info("recording %s into %s (%s chunks)", pattern, args.output, compression)
    while not shell.stopping:
        item = inbox.get(timeout=0.2)
        if item is not None:
            recording.write(item.key, item.payload)
            shell.received += 1
        else:
            recording.flush_if_due()
    # Stopping: write what already arrived (a short grace period for messages in flight).
    inbox_deadline = time.monotonic() + args.drain
    while time.monotonic() < inbox_deadline:
        item = inbox.get(timeout=0.05)
        if item is None:
            break
        recording.write(item.key, item.payload)
        shell.received += 1
    inbox.close()
    # The recorder's own last word goes into its log too (its published one would arrive too late).
    shell.state = ServiceState.FINISHED
    final = shell.status()
    recording.write(keys.key_for(final), encode(final))
    shell.log.info("wrote %d messages to %s", recording.messages, args.output)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m scripts.record",
        description="dtpf recorder: writes every message of a twin into an MCAP file, one channel per key "
                    "expression, schemas embedded.")
    parser.add_argument("--output", "-o", required=True, help="MCAP file to write")
    parser.add_argument("--all-twins", action="store_true", help="record dtpf/** instead of one twin")
    parser.add_argument("--compression", default="auto", choices=["auto", *sorted(COMPRESSION)],
                        help="chunk compression; 'auto': lz4 while a particle set (N x (d + 1) float64) "
                             "is at most 64 KiB, none above, where random states do not compress "
                             "(default: %(default)s)")
    parser.add_argument("--flush-interval", type=float, default=1.0, metavar="SECONDS",
                        help="flush the open chunk at least this often (default: %(default)s)")
    parser.add_argument("--drain", type=float, default=2.0, metavar="SECONDS",
                        help="on SIGINT/SIGTERM, keep writing messages still arriving for at most this "
                             "long (default: %(default)s)")
    add_run_arguments(parser)
    add_service_arguments(parser)
    add_zenoh_arguments(parser)
    return parser


if __name__ == "__main__":
    raise SystemExit(run_service("recorder", main, build_parser()))
