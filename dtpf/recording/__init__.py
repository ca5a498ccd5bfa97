"""The MCAP log files: writing them as a run goes, reading them back whole or cut short.

Modules: :mod:`dtpf.recording.writer` (the recorder's writer: one channel per
key expression, every schema embedded, flushed on a timer),
:mod:`dtpf.recording.logfile` (reading a log, complete or damaged, and writing
it back as a valid file), :mod:`dtpf.recording.mcap_file` (the MCAP records
themselves: chunks, indexes, summary) and :mod:`dtpf.recording.crc` (the chunks' CRC-32).
It may import the wire contract (:mod:`dtpf.messages`) and nothing above.
"""
