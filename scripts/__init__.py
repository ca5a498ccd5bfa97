"""The product's commands, on the top floor: they may import every layer and the wire contract.

This folder: ``cli`` (the ``dtpf`` command), ``launch`` (the three layers and
the recorder as processes), ``record`` (the recorder service), ``sensor`` (a
live sensor stand-in), ``inprocess`` (the three layers in one process) and
``console`` (progress on stderr, shared by everything below). Three rooms:

- :mod:`dtpf.scripts.logs`: the log tools (``dtpf info``, ``summary``, ``recover``,
  ``plot``, ``play``, ``verify``);
- :mod:`dtpf.scripts.paper`: the paper's reproduction (experiments, tracking,
  policy evaluation), research, not product;
- :mod:`dtpf.scripts.bench`: benchmarks and soak runs.

Imports run down the floors messages < entity < information < system <
scripts; inside scripts, the rooms import this folder's modules, never each
other's (tests/test_layout.py holds it), and nothing imports a service module.
"""
