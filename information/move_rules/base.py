"""The contract of a move rule: how the small particles of Eq. 28 are moved towards the large ones.

Every move rule has the form
``moved, W, n_large, n_small, n_mixed = rule(particles, weights, threshold_rule, ps, rng)``:

Parameters
----------
particles : (N, d) float64 ndarray
    The entity's set, read-only for the rule.
weights : (N,) float64 ndarray
    Its normalised weights (checked).
threshold_rule : str or float
    How W of Eq. 28 is found (:func:`dtpf.information.rules.threshold`).
ps : float
    The degree factor PS in [0, 1] (Eq. 30).
rng : numpy.random.Generator
    Seeds the rules' stream (:func:`dtpf.information.rules.draws`): for each small particle in index order
    its partner in the large set, r, then u.

Returns
-------
moved : (N, d) float64 ndarray or None
    A new array: the large particles as they were, the small ones moved; None when nothing moves (no large or
    no small particle).
W : float
    The threshold.
n_large, n_small, n_mixed : int
    M, N - M (0 when nothing moves) and the small particles on the first branch of Eq. 30 (u <= PS).

Built-in only, because a rule is fused with the compiled kernels of the split and the random stream (the
paper's rule draws its numbers inside the compiled loop, never as arrays, and the order of the draws is part
of what makes a run reproducible from its log), and because the rules are replayed outside this layer by
name: the system layer's predictive policies apply them to every simulated scenario at once
(:mod:`dtpf.system.predict`) and the choosing policy's arms name them (:data:`dtpf.information.layer.ARMS`).
:func:`adapt` refuses every reference.

A built-in is a module of this package that registers its function with ``@MOVE_RULE_REGISTRY.builtin("name")``
(:data:`dtpf.messages.names.MOVE_RULE_REGISTRY`).
"""
from __future__ import annotations

from dtpf.messages.names import MOVE_RULE_REGISTRY
from dtpf.messages.references import ReferenceLoadError

__all__ = ["MOVE_RULE_REGISTRY", "adapt"]


def adapt(obj, where: str):
    """Never: a move rule is built-in only (module docstring)."""
    raise ReferenceLoadError(f"{where}: move rules are built-in only: {', '.join(MOVE_RULE_REGISTRY.names())}")
