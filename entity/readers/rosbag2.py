"""rosbag2 logs (a folder or an .mcap file): one step per message of a topic (:mod:`dtpf.entity.rosbag`)."""
from __future__ import annotations

from dtpf.messages.family import READERS

__all__ = ["read_rosbag2"]


@READERS.builtin("rosbag2")
def read_rosbag2(source, *, obs_dim=None, state_dim=None, steps=None, topic=None, fields=None, model=None,
             partial=False):
    """A rosbag2 log (folder or .mcap) read on --topic, each message mapped by --ros2-fields."""
    from dtpf.entity import rosbag

    return rosbag.read_bag(source, topic, fields, obs_dim=obs_dim, state_dim=state_dim, steps=steps, model=model,
                          partial=partial)
