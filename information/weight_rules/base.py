"""The contract of a weight rule: the weights of the particles the preprocessing moved.

Every weight rule has the form
``new_weights = rule(weights, threshold, particles, moved, log_likelihood)``:

Parameters
----------
weights : (N,) float64 ndarray
    The normalised weights of the set before the preprocessing (possibly read-only: a decoded message's).
threshold : float
    W of Eq. 28: the small particles, the ones the rules moved, are those of weight <= W.
particles, moved : (N, d) float64 ndarray
    The set before and after the moves (the large particles' rows are equal).
log_likelihood : callable or None
    ``(M, d) -> (M,)`` log p(z_k | x) of the step's observation; given to a rule whose ``needs_likelihood``
    is True, None otherwise.

Returns
-------
new_weights : (N,) float64 ndarray
    Normalised; a read-only view of ``weights`` when they are kept. The rule never changes its inputs.

Built-in only, because the rules are replayed outside this layer by name: the system layer's predictive
policies apply them to every simulated scenario at once, vectorised over the scenarios
(:mod:`dtpf.system.predict`), and the choosing policy's arms and its evidence name them
(:data:`dtpf.information.layer.ARMS`); a user's rule would run here and not there, and the system layer
would predict a filter other than the one that runs. :func:`adapt` refuses every reference.

A built-in is a module of this package that registers its function with
``@WEIGHT_RULE_REGISTRY.builtin("name")`` (:data:`dtpf.messages.names.WEIGHT_RULE_REGISTRY`).
"""
from __future__ import annotations

from dtpf.messages.names import WEIGHT_RULE_REGISTRY
from dtpf.messages.references import ReferenceLoadError

__all__ = ["WEIGHT_RULE_REGISTRY", "adapt"]


def adapt(obj, where: str):
    """Never: a weight rule is built-in only (module docstring)."""
    raise ReferenceLoadError(f"{where}: weight rules are built-in only: "
                             f"{', '.join(WEIGHT_RULE_REGISTRY.names())}")
