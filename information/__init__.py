"""Information layer: the mirror of the entity's weight state and the
preprocessing rules of Eq. 28-30 (paper section 3, Fig. 3).

Modules: :mod:`information.rules` (Eq. 28-30), :mod:`information.mirror`
(the weight-state summary sent to the system layer),
:mod:`information.layer` (the transport-free layer object).
"""
