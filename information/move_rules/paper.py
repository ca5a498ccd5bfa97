"""Eq. 29-30 as printed: x_tilde = x_m + f x_l (the paper)."""
from __future__ import annotations

from dtpf.information import rules
from dtpf.messages.names import MOVE_RULE_REGISTRY

__all__ = ["paper"]


@MOVE_RULE_REGISTRY.builtin("paper")
def paper(particles, weights, threshold_rule, ps, rng):
    """Eq. 29-30 as printed, x_tilde = x_m + f x_l: the paper's, not translation invariant."""
    return rules.move_paper(particles, weights, threshold_rule, ps, rng)
