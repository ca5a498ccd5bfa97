"""Weight rules of processed particles, a family of built-ins only: the contract in
:mod:`~dtpf.information.weight_rules.base`, one module per rule.

:func:`dtpf.information.rules.preprocess` applies the rule a run names (``--weight-rule``); this package is
where a new one goes (a module that registers its function with ``@WEIGHT_RULE_REGISTRY.builtin(name)``,
:data:`dtpf.messages.names.WEIGHT_RULE_REGISTRY`). It may import the wire contract only.
"""
