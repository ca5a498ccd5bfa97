"""``python -m dtpf.scripts.ros2``: the same as ``dtpf ros2`` (the bridge)."""
import sys

from dtpf.scripts.ros2.bridge import command_line

sys.exit(command_line())
