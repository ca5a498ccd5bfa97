"""A ROS 2 parameters file gives the bridge's options (--ros2-params): the standard layout, the node's own
entry or the wildcard, the command line winning, and one line for anything the bridge does not know."""
from __future__ import annotations

import argparse

import pytest

pytest.importorskip("ruamel.yaml", reason="ruamel.yaml comes with rosbags (pip install 'dtpf[rosbag]')")

from dtpf.messages.config import RunConfig
from dtpf.scripts.ros2 import Ros2Error, params
from dtpf.scripts.ros2.bridge import bridge_arguments, bridge_words, resolve_options

STACK = """\
amcl:
  ros__parameters:
    base_frame_id: base_footprint   # another node's: left alone
/**:
  ros__parameters:
    frame: world
    depth: 10
/robot/dtpf_rb_1:
  ros__parameters:
    topic: /gps
    fields: point.x,point.y
    child_frame: "{twin}_base"
    best_effort: true
    covariance: diagonal
"""


def test_the_nodes_entries_merge_in_file_order_and_other_nodes_are_left_alone(tmp_path):
    path = tmp_path / "stack.yaml"
    path.write_text(STACK)
    assert params.node_name("rb-1") == "dtpf_rb_1"
    assert params.load(path, "dtpf_rb_1") == {"frame": "world", "depth": 10, "topic": "/gps",
                                              "fields": "point.x,point.y", "child_frame": "{twin}_base",
                                              "best_effort": True, "covariance": "diagonal"}
    assert params.load(path, "dtpf_other") == {"frame": "world", "depth": 10}  # the wildcard only


def test_the_command_line_wins_and_the_defaults_fill_the_rest(tmp_path):
    path = tmp_path / "stack.yaml"
    path.write_text(STACK)
    parser = argparse.ArgumentParser()
    parser.add_argument("--topic")
    bridge_arguments(parser)
    args = parser.parse_args(["--ros2-params", str(path), "--ros2-frame", "odom"])
    args.ros2_fields = None
    resolve_options(args, RunConfig(twin="rb-1"))
    assert (args.topic, args.ros2_fields, args.ros2_frame, args.ros2_child_frame, args.ros2_depth,
            args.ros2_best_effort, args.ros2_covariance) == ("/gps", "point.x,point.y", "odom", "{twin}_base", 10,
                                                             True, "diagonal")
    # --observations ros2:TOPIC names the topic: the file's is not taken.
    args = parser.parse_args(["--ros2-params", str(path)])
    args.ros2_fields = None
    resolve_options(args, RunConfig(twin="rb-1", observations="ros2:/target"))
    assert args.topic is None
    # Nothing given anywhere: the defaults.
    args = parser.parse_args([])
    resolve_options(args, RunConfig(twin="rb-1"))
    assert (args.ros2_frame, args.ros2_child_frame, args.ros2_depth, args.ros2_best_effort) == \
        ("map", "base_link", 100, False)
    # What dtpf launch passes on to its bridge: what was given, not the defaults.
    given = parser.parse_args(["--ros2-params", str(path), "--ros2-child-frame", "body", "--ros2-best-effort"])
    assert bridge_words(given) == ["--ros2-child-frame", "body", "--ros2-params", str(path), "--ros2-best-effort"]


@pytest.mark.parametrize("text, expected", [
    ("dtpf_rb_1:\n  ros__parameters:\n    frme: odom\n",
     r"unknown parameter 'frme' \(known: topic, type, fields, pose, namespace, frame, child_frame, depth, "
     r"covariance, best_effort\)"),
    ("dtpf_rb_1:\n  ros__parameters:\n    depth: ten\n", r"depth must be an integer \(as --ros2-depth\), not 'ten'"),
    ("dtpf_rb_1:\n  ros__parameters:\n    depth: 0\n", r"depth must be at least 1, not 0"),
    ("dtpf_rb_1:\n  ros__parameters:\n    best_effort: 1\n", r"best_effort must be true or false"),
    ("dtpf_rb_1:\n  ros__parameters:\n    covariance: half\n", r"covariance must be one of full, diagonal"),
    ("dtpf_rb_1:\n  ros__parameters:\n    frame: ''\n", r"frame must be a non-empty string"),
    ("amcl:\n  ros__parameters:\n    x: 1\n", r"no entry for the bridge's node dtpf_rb_1 \(the file has: amcl\); "
                                            r"name it 'dtpf_rb_1:' or '/\*\*:'"),
    ("dtpf_rb_1:\n  frame: map\n", r"'dtpf_rb_1' has no 'ros__parameters:' mapping"),
    ("dtpf_rb_1: [\n", r"not YAML at line \d+"),
    ("- frame\n", r"expected node names at the top"),
])
def test_what_the_bridge_does_not_know_is_one_line(tmp_path, text, expected):
    path = tmp_path / "bridge.yaml"
    path.write_text(text)
    with pytest.raises(Ros2Error, match=expected) as caught:
        params.load(path, "dtpf_rb_1")
    assert str(caught.value).startswith(f"--ros2-params {path}: ") and "\n" not in str(caught.value)


def test_a_missing_file_is_one_line(tmp_path):
    with pytest.raises(Ros2Error, match=r"--ros2-params .*nope.yaml: cannot read it \(No such file or directory\)"):
        params.load(tmp_path / "nope.yaml", "dtpf_rb_1")
