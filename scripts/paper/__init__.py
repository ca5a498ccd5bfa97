"""The paper's reproduction: research that uses the product, not part of it.

:mod:`~scripts.paper.experiments` (section 4: Table 2, Figs. 4-8, Table 3),
:mod:`~scripts.paper.tracking` (section 5: the video tracking application),
:mod:`~scripts.paper.evaluate_policies` and
:mod:`~scripts.paper.compare_weight_rules` (the PS policies and weight rules
against each other), :mod:`~scripts.paper.common` (what they share). They may
import the layers, ``scripts.inprocess`` and ``scripts.console``; nothing in
the product imports them. Reports are written to docs/.
"""
