"""An observation reader of your own: ``read(source) -> observations`` for a format dtpf does not know.

    dtpf run --model docs/examples/range_bearing.py:RangeBearingTarget \
        --observations docs/examples/components/range_bearing.txt --reader docs/examples/components/reader.py:read_spaced

It may return the observations alone ((T, m) or (T,)), or a dict with ``observations`` and optionally
``truth``, ``times`` and ``stamps``; dtpf checks the values and the columns against the model.
"""
import numpy as np


def read_spaced(source):
    """Whitespace-separated rows 'range bearing' after a '#' comment line, one step per row."""
    return {"observations": np.loadtxt(source, comments="#", ndmin=2)}
