"""System layer: degradation prediction and control of the degree factor PS
(paper section 3, Fig. 3).

Modules: :mod:`dtpf.system.predict` (the degradation predictor: weight-state
history and the twin's one-step simulation), :mod:`dtpf.system.policy` (the PS
policy interface and its policies: fixed, rule, predictive),
:mod:`dtpf.system.layer` (the transport-free layer object) and
:mod:`dtpf.system.service` (its Zenoh shell). Measurements: docs/results/system-layer.md.
It may import the floors below it: the wire contract, the entity and the
information layer (its simulation runs their rules).
"""
