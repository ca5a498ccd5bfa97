"""CRC-32 of MCAP records at memory speed.

MCAP's chunk and summary CRCs are zlib's CRC-32. CPython's zlib takes about as
long to checksum a large particle set as writing the set to the file takes;
zlib-ng computes the same function with SIMD folding, an order of magnitude
faster (``python -m dtpf.scripts.bench.recording`` prints both)::

    from dtpf.recording.crc import crc32, use_fast_crc
    crc32(data)          # == zlib.crc32(data), faster where zlib-ng is installed
    use_fast_crc()       # the mcap package computes its CRCs with it too

The mcap package calls ``zlib.crc32`` through the ``zlib`` name of its own
modules; :func:`use_fast_crc` points that name at a copy of the zlib module
whose ``crc32`` is zlib-ng's. The numbers are the same, so files written
either way read back alike. Without zlib-ng (a platform with no wheel),
everything stays on zlib.
"""
from __future__ import annotations

import importlib
import types
import zlib

__all__ = ["crc32", "FAST", "use_fast_crc"]

try:
    from zlib_ng import zlib_ng as _zlib_ng
except ImportError:  # pragma: no cover - zlib-ng is a dependency; this is the fallback
    _zlib_ng = None

#: Whether :func:`crc32` is zlib-ng's.
FAST = _zlib_ng is not None

#: CRC-32 (zlib's polynomial): ``crc32(data, value=0)``.
crc32 = _zlib_ng.crc32 if FAST else zlib.crc32

#: The mcap modules that compute CRCs through their ``zlib`` name.
MCAP_MODULES = ("mcap.writer", "mcap.records", "mcap.data_stream", "mcap.stream_reader")


def _fast_zlib() -> types.SimpleNamespace:
    """A copy of the zlib module's names with zlib-ng's crc32."""
    shim = types.SimpleNamespace(**{name: getattr(zlib, name) for name in dir(zlib) if not name.startswith("__")})
    shim.crc32 = crc32
    return shim


def use_fast_crc(enabled: bool = True) -> bool:
    """Let the mcap package compute its CRCs with :func:`crc32`; True if that is zlib-ng's.

    ``enabled=False`` puts zlib back (for benchmarks). Safe to call more than
    once. A module of mcap without a ``zlib`` name is left alone (a later mcap
    may compute CRCs some other way).
    """
    fast = enabled and FAST
    target = _fast_zlib() if fast else zlib
    for name in MCAP_MODULES:
        module = importlib.import_module(name)
        if isinstance(getattr(module, "zlib", None), (types.ModuleType, types.SimpleNamespace)):
            module.zlib = target
    return fast
