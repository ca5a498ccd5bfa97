"""The log tools: read, summarise, recover, plot, replay and verify an MCAP log of dtpf.

:mod:`~dtpf.scripts.logs.summary` (``dtpf info``, ``summary``, ``recover``),
:mod:`~dtpf.scripts.logs.plot` (``dtpf plot``), :mod:`~dtpf.scripts.logs.play`
(``dtpf play``), :mod:`~dtpf.scripts.logs.verify` (``dtpf verify``). They may import
the wire contract, the layers (verify re-runs them) and ``dtpf.scripts.console``;
not the paper's reports or the benchmarks.
"""
