"""The translation-invariant rule: x_tilde = x_m + f c (x_l - x_m), at most one weighted spread (not the paper's)."""
from __future__ import annotations

from dtpf.information import rules
from dtpf.messages.names import MOVE_RULE_REGISTRY

__all__ = ["relative"]


@MOVE_RULE_REGISTRY.builtin("relative")
def relative(particles, weights, threshold_rule, ps, rng):
    """A fraction of x_l - x_m, at most the set's weighted spread: translation invariant, not the paper's."""
    return rules.move_relative(particles, weights, threshold_rule, ps, rng)
