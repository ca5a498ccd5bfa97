"""PS policies, one family: the contract in :mod:`~dtpf.system.policies.base`, one module per built-in.

``dtpf.system.policy`` is the recommended import; this package is where a new built-in goes (a module that
registers its class with ``@POLICIES.builtin(name)``). It may import the wire contract and the system
layer's predictor.
"""
