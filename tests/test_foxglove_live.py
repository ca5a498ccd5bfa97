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


def test_a_client_offering_only_the_old_subprotocol_is_refused_with_one_line_per_host(processes, tmp_path):
    """foxglove-sdk's server speaks foxglove.sdk.v1 only: a client offering only foxglove.websocket.v1 gets HTTP
    400 on every attempt. The launcher says so once for that host (why, and what to offer), not 'handshake
    failed' once per attempt; a client offering foxglove.sdk.v1 is still served."""
    from websockets.exceptions import InvalidStatus

    port = free_port()
    launcher = processes.start("launcher", ["-m", "dtpf.scripts.cli", "launch", "--policy", "fixed", "--steps", "40", "--rate", "10", "-n",
                                            "100", "--foxglove", str(port), "--twin", "t-old", "-o",
                                            str(tmp_path / "old.mcap")])
    refused, deadline = 0, time.monotonic() + 60
    while refused < 5:
        assert time.monotonic() < deadline and launcher.poll() is None, processes.output(launcher)
        try:
            connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"], open_timeout=2).close()
        except InvalidStatus as error:
            assert error.response.status_code == 400
            refused += 1
        except OSError:
            time.sleep(0.1)
    with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5) as client:
        assert client.subprotocol == "foxglove.sdk.v1"
    launcher.wait(timeout=120)
    said = processes.output(launcher)
    assert launcher.returncode == 0, said
    assert "handshake failed (this server speaks the subprotocol foxglove.sdk.v1" in said, said
    assert said.count("refused a Foxglove client at 127.0.0.1") == 1 and "Dropping client" not in said, said
