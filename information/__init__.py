"""Information layer: the mirror of the entity's weight state and the
preprocessing rules of Eq. 28-30 (paper section 3, Fig. 3).

Modules: :mod:`dtpf.information.rules` (Eq. 28-30), :mod:`dtpf.information.report`
(what one preprocessing did), :mod:`dtpf.information.select` (the threshold's order
statistic), :mod:`dtpf.information.mirror` (the weight-state summary sent to the
system layer), :mod:`dtpf.information.layer` (the transport-free layer object),
:mod:`dtpf.information.service` (its Zenoh shell). Families:
:mod:`dtpf.information.thresholds` (W of Eq. 28, open to a user's rule),
:mod:`dtpf.information.weight_rules` and :mod:`dtpf.information.move_rules`
(built-in only). It may import the wire contract and the entity layer (the
models), never the system layer.
"""
