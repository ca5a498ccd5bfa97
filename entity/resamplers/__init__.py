"""Resamplers, one family: the contract in :mod:`~dtpf.entity.resamplers.base`, one module per built-in.

``dtpf.entity.resampling`` is the recommended import; this package is where a new built-in goes (a module
that registers its function with ``@RESAMPLERS.builtin(name)``). It may import the wire contract and
:mod:`dtpf.entity._merge`.
"""
