"""Move rules of the small particles, a family of built-ins only: the contract in
:mod:`~dtpf.information.move_rules.base`, one module per rule.

:func:`dtpf.information.rules.preprocess` applies the rule a run names (``--move-rule``); this package is
where a new one goes (a module that registers its function with ``@MOVE_RULE_REGISTRY.builtin(name)``,
:data:`dtpf.messages.names.MOVE_RULE_REGISTRY`). It may import the wire contract and
:mod:`dtpf.information.rules` (the split, the random stream and the compiled moves the rules share).
"""
