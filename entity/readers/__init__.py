"""Observation readers, one family: the contract in :mod:`~dtpf.entity.readers.base`, one module per built-in.

``dtpf.entity.sources.read_table`` is the recommended way in: it picks the reader the run names
(``--reader``), or the one a file's kind calls for. A new built-in is a module here that registers its
reader with ``@READERS.builtin(name)``. It may import the wire contract and the entity's observation files.
"""
