"""A ROS 2 stamp whose nanosec is not below 1e9 becomes the same instant with nanosec carried into sec, so the
observation the bridge sends is one the entity takes (it refused ``nsec`` 1,500,000,000 and lost the measurement)."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from dtpf.messages.codec import decode
from dtpf.messages.models import Observation
from dtpf.scripts.ros2.bridge import Inbound, normalized_stamp


@pytest.mark.parametrize("stamp, expected", [
    ((1, 1_500_000_000), (2, 500_000_000)),
    ((7, 999_999_999), (7, 999_999_999)),
    ((0, 4_294_967_295), (4, 294_967_295)),  # the largest uint32 nanosec
    ((3, 0), (3, 0)),
    (None, None),
])
def test_nanosec_is_carried_into_sec(stamp, expected):
    assert normalized_stamp(stamp) == expected


def test_the_bridges_observation_of_an_unnormalised_stamp_decodes(monkeypatch):
    sent = []
    shell = SimpleNamespace(header=lambda step: {"run_id": "run", "twin_id": "t-1", "step": step}, session=None,
                            received=0, reject=lambda *a, **k: pytest.fail(f"rejected: {a}"))
    monkeypatch.setattr("dtpf.scripts.ros2.bridge.publisher", lambda session, key: SimpleNamespace(put=sent.append))
    monkeypatch.setattr("dtpf.entity.rosbag.stamp_of", lambda message: (1, 1_500_000_000))
    inbound = Inbound(shell, mapper=lambda message: [2.5], start=1, stamps={})
    inbound(object())
    (payload,) = sent
    observation = decode(payload, Observation)
    assert (observation.stamp.sec, observation.stamp.nsec) == (2, 500_000_000)
    assert observation.values == [2.5] and observation.step == 1
