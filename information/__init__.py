"""Information layer: the mirror of the entity's weight state and the
preprocessing rules of Eq. 28-30 (paper section 3, Fig. 3).

Modules: :mod:`dtpf.information.rules` (Eq. 28-30), :mod:`dtpf.information.select`
(the threshold's order statistic), :mod:`dtpf.information.mirror` (the weight-state
summary sent to the system layer), :mod:`dtpf.information.layer` (the
transport-free layer object), :mod:`dtpf.information.service` (its Zenoh shell).
It may import the wire contract and the entity layer (the models and the
filter's report type), never the system layer.
"""
