"""Information layer: the mirror of the entity's weight state and the
preprocessing rules of Eq. 28-30 (paper section 3, Fig. 3).

Modules: :mod:`information.rules` (Eq. 28-30), :mod:`information.select`
(the threshold's order statistic), :mod:`information.mirror` (the weight-state
summary sent to the system layer), :mod:`information.layer` (the
transport-free layer object), :mod:`information.service` (its Zenoh shell).
It may import the wire contract and the entity layer (the models and the
filter's report type), never the system layer.
"""
