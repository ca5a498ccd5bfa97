"""The log tools: read, summarise, recover, plot, replay and verify an MCAP log of dtpf.

:mod:`~scripts.logs.summary` (``dtpf info``, ``summary``, ``recover``),
:mod:`~scripts.logs.plot` (``dtpf plot``), :mod:`~scripts.logs.play`
(``dtpf play``), :mod:`~scripts.logs.verify` (``dtpf verify``). They may import
the wire contract, the layers (verify re-runs them) and ``scripts.console``;
not the paper's reports or the benchmarks.
"""
