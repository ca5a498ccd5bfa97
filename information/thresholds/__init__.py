"""Threshold rules for W of Eq. 28, one family: the contract in :mod:`~dtpf.information.thresholds.base`, one
module per built-in.

:func:`dtpf.information.rules.threshold` is where W is computed; this package is where a new built-in goes (a
module that registers its rule with ``@THRESHOLDS.builtin(name)``). It may import the wire contract and
:mod:`dtpf.information.select` (the order statistics of the weights).
"""
