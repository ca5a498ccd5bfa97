"""Moves after resampling, one family: the contract in :mod:`~dtpf.entity.moves.base`, one module per built-in.

``dtpf.entity.jitter`` is the recommended import; this package is where a new built-in goes (a module that
registers its move with ``@MOVES.builtin(name)``). It may import the wire contract.
"""
