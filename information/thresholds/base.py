"""The contract of a threshold rule (W of Eq. 28), and the checks a user's rule passes before a run.

A threshold rule has the form ``W = rule(weights)``:

Parameters
----------
weights : (N,) float64 ndarray, read-only
    The normalised weights of one particle set (N >= 1): finite, non-negative, summing to 1 up to rounding.
    The rule may assume all of that and must not change them (a user's rule gets a read-only view: writing
    to it raises).

Returns
-------
W : float
    A finite number, W >= 0. A particle whose weight exceeds W is *large* and kept; the others are *small*
    and moved towards the large ones (Eq. 28-30). W at or above the largest weight leaves no large particle:
    nothing is moved that step.

W must depend on the weights alone, with no random numbers and no state carried from one call to the next:
the information layer, its mirror of the weight state and the system layer's predictions each compute W
of the same weights and must find the same number.

A user's rule is a plain function of the weights, ``path/to/file.py:NAME`` or ``package.module:NAME``
(``dtpf run --threshold my_rules.py:half_max`` with ``def half_max(weights): return 0.5 * weights.max()``),
or a name an installed package registers in the entry-point group ``dtpf.thresholds``. :func:`adapt` tries
it on a small set before a run and checks its result at every call (one number, finite, non-negative: a
mistake is one line naming the rule and what is wrong). A number given as the threshold is W itself, with
no rule.

In the family's calling form every member gives the split of Eq. 28 what it needs,
``(W, capacity) = member(weights)`` (a :class:`Split`): ``capacity`` is the most weights that can exceed
W, the size of the split kernel's array of large rows (k for ``neff``; N for ``inverse-n`` and a user's
rule). A built-in may also have ``order(weights) -> (rank, capacity)``: W is then the weight of ascending
rank ``rank`` (0 when rank < 0), which the compiled rules select themselves on a small set instead of
calling the member (one compiled call, not two).

A built-in is a module of this package that registers its function with ``@THRESHOLDS.builtin("name")``
(:mod:`dtpf.messages.family`).
"""
from __future__ import annotations

import math
import numbers
from typing import NamedTuple

import numpy as np

from dtpf.messages import references
from dtpf.messages.family import THRESHOLDS
from dtpf.messages.references import ReferenceLoadError, a, describe

__all__ = ["THRESHOLDS", "Split", "adapt", "CHECK_WEIGHTS"]

#: The weights a user's rule is tried on before a run: unequal, one of them 0.
CHECK_WEIGHTS = np.array([0.30, 0.02, 0.17, 0.0, 0.11, 0.25, 0.05, 0.10])


class Split(NamedTuple):
    """What a threshold rule gives the split of Eq. 28: W, and the most weights that can exceed it."""

    threshold: float
    capacity: int


def adapt(obj, where: str):
    """A user's ``W = rule(weights)`` in the family's calling form, tried on a small set (module docstring)."""
    references.function_of(obj, where, "a threshold rule", "rule(weights) -> W", ("weights",))
    rule = _Checked(obj, where)
    weights = CHECK_WEIGHTS / CHECK_WEIGHTS.sum()
    weights.flags.writeable = False
    rule(weights)
    return rule


class _Checked:
    """A user's ``W = rule(weights)`` in the family's form ``(W, N)``, its result checked at every call."""

    def __init__(self, function, where: str):
        self.function, self.where = function, where
        self.__name__ = getattr(function, "__name__", "rule")
        self.__doc__ = getattr(function, "__doc__", None)

    def __call__(self, weights: np.ndarray) -> Split:
        view = weights.view()
        view.flags.writeable = False
        try:
            result = self.function(view)
        except Exception as exc:
            hint = " (a threshold rule must not change the weights)" if "read-only" in str(exc) else ""
            raise ReferenceLoadError(f"{self.where} raised {describe(exc)}{hint}") from exc
        return Split(self.value(result), weights.size)

    def value(self, result) -> float:
        """``result`` as W, or a ReferenceLoadError naming the rule and what is wrong."""
        if isinstance(result, np.ndarray) and result.shape == () and result.dtype.kind in "iuf":
            result = result[()]
        if isinstance(result, (bool, np.bool_)) or not isinstance(result, numbers.Real):
            shape = f" of shape {result.shape}" if isinstance(result, np.ndarray) else ""
            raise ReferenceLoadError(f"{self.where} returned {a(result)}{shape}, expected W, one finite "
                                     f"non-negative number")
        value = float(result)
        if not math.isfinite(value):
            raise ReferenceLoadError(f"{self.where} returned {value}, expected W, a finite non-negative number")
        if value < 0:
            raise ReferenceLoadError(f"{self.where} returned {value!r}, a negative W (W >= 0)")
        return value
