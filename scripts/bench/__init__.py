"""Benchmarks and soak runs: tables of medians and ratios, never timed tests.

:mod:`~scripts.bench.resampling` (resamplers and the DT preprocessing against
particles and filterpy), :mod:`~scripts.bench.pipeline` (the lockstep step
over Zenoh), :mod:`~scripts.bench.live` (live-sensor latency),
:mod:`~scripts.bench.encoding` and :mod:`~scripts.bench.recording` (the wire
and the log), :mod:`~scripts.bench.soak_launches` and
:mod:`~scripts.bench.soak_memory` (many launches; RSS over a long one). They may
import the layers and ``scripts.launch`` / ``scripts.inprocess``; nothing in
the product imports them.
"""
