"""The paper's reproduction: research that uses the product, not part of it.

:mod:`~dtpf.scripts.paper.experiments` (section 4: Table 2, Figs. 4-8, Table 3),
:mod:`~dtpf.scripts.paper.tracking` (section 5: the video tracking application),
:mod:`~dtpf.scripts.paper.evaluate_policies` and
:mod:`~dtpf.scripts.paper.compare_weight_rules` (the PS policies and weight rules
against each other), :mod:`~dtpf.scripts.paper.common` (what they share). They may
import the layers, ``dtpf.scripts.inprocess`` and ``dtpf.scripts.console``; nothing in
the product imports them. Reports are written to docs/.
"""
