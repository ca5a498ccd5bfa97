"""System layer: degradation prediction and control of the degree factor PS
(paper section 3, Fig. 3).

Modules: :mod:`system.policy` (the PS policy interface and its policies).
"""
