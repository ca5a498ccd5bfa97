"""Benchmarks and soak runs: tables of medians and ratios, never timed tests.

:mod:`~dtpf.scripts.bench.resampling` (resamplers and the DT preprocessing against
particles and filterpy), :mod:`~dtpf.scripts.bench.pipeline` (the lockstep step
over Zenoh), :mod:`~dtpf.scripts.bench.live` (live-sensor latency),
:mod:`~dtpf.scripts.bench.encoding` and :mod:`~dtpf.scripts.bench.recording` (the wire
and the log), :mod:`~dtpf.scripts.bench.soak_launches` and
:mod:`~dtpf.scripts.bench.soak_memory` (many launches; RSS over a long one). They may
import the layers and ``dtpf.scripts.launch`` / ``dtpf.scripts.inprocess``; nothing in
the product imports them.
"""
