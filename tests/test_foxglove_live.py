"""dtpf launch --foxglove: a client of Foxglove's WebSocket protocol sees every estimate of the run."""
from __future__ import annotations

import json
import struct
import time

from websockets.sync.client import connect

from dtpf.shell.bus import free_port

#: Opcode of a binary message-data frame: opcode u8, subscription id u32, log time u64, payload.
MESSAGE_DATA = 0x01


def test_a_protocol_client_is_advertised_the_channels_subscribes_and_receives_every_estimate(processes, tmp_path):
    port = free_port()
    launcher = processes.start("launcher", ["-m", "dtpf.scripts.cli", "launch", "--steps", "50", "--rate", "15", "-q",
                                            "--foxglove", str(port), "--twin", "t-fox", "-o",
                                            str(tmp_path / "fox.mcap")])
    deadline = time.monotonic() + 60
    while True:
        try:
            client = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                             open_timeout=2)
            break
        except OSError:
            assert time.monotonic() < deadline and launcher.poll() is None, processes.output(launcher)
            time.sleep(0.1)
    topics, steps, subscribed = {}, set(), False
    with client:
        while len(steps) < 50 and time.monotonic() < deadline + 60:
            try:
                frame = client.recv(timeout=5)
            except TimeoutError:
                if launcher.poll() is not None:
                    break
                continue
            if isinstance(frame, str):
                message = json.loads(frame)
                if message["op"] == "advertise":
                    topics.update({channel["id"]: channel for channel in message["channels"]})
                    estimate = [cid for cid, c in topics.items() if c["topic"] == "dtpf/t-fox/entity/estimate"]
                    if estimate and not subscribed:
                        client.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": estimate[0]}]}))
                        subscribed = True
            elif frame[0] == MESSAGE_DATA:
                subscription, _ = struct.unpack_from("<IQ", frame, 1)
                assert subscription == 1
                steps.add(json.loads(frame[13:])["step"])
    launcher.wait(timeout=60)
    assert launcher.returncode == 0, processes.output(launcher)
    assert steps == set(range(1, 51)), sorted(steps)
    by_topic = {c["topic"]: c for c in topics.values()}
    assert by_topic["dtpf/t-fox/entity/cloud"]["schemaName"] == "foxglove.PointCloud"
    assert by_topic["dtpf/t-fox/entity/estimate"]["encoding"] == "json"
    assert "dtpf/t-fox/entity/particles" not in by_topic  # the envelope: Foxglove cannot decode it
