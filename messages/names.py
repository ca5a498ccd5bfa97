"""The names a run configuration may use: part of the wire contract.

A :class:`~dtpf.messages.config.RunConfig` travels in every Status message and
every log, so the names it may hold are part of the contract, here, where
the contract's readers can check them without loading a layer. Each layer
implements the names of its own room and a test holds the two equal
(``tests/test_layout.py``): the entity its built-in scenarios, the
information layer the choosing policy's arms. Resamplers, moves after
resampling, threshold rules and PS policies are families
(:mod:`dtpf.messages.family`), and the information layer's weight rules and
move rules are families of built-ins only (:class:`BuiltinOnly`): their
names are read from their registries, never listed here.
"""
from __future__ import annotations

import functools
import importlib.metadata
import sys

from dtpf.messages.family import Family

__all__ = ["SCENARIOS", "MODEL_ENTRY_POINTS", "CANNOT_SAMPLE", "BuiltinOnly", "WEIGHT_RULE_REGISTRY",
           "MOVE_RULE_REGISTRY", "ARMS", "OWN_ARM", "REHEARSE", "COMMAND_LINE_POLICY", "CHOOSE_BASES", "REHEARSAL_WAIT", "scenario_names"]

#: Built-in scenarios (dtpf.entity.models): Eq. 35 with 25, Eq. 35 as printed (0.25), the tracking video, and a
#: slowly drifting constant with precise observations (where particles impoverish; not in the paper), and the
#: same constant seen by a sensor whose noise drops mid-run (the best cure changes).
SCENARIOS = ("ungm", "ungm-printed", "video", "drift", "switching", "moving")
#: The entry-point group where an installed package registers scenario names of its own.
MODEL_ENTRY_POINTS = "dtpf.models"
#: Built-in scenarios whose model cannot draw observations (no simulating policy with them).
CANNOT_SAMPLE = frozenset({"video"})


class BuiltinOnly(Family):
    """A family of dtpf's own members only: no entry points, no reference to a user's code (the contract in
    its package's ``base.py`` says why). Its names, ``--help`` and the run configuration's validation are read
    from its registry, as a :class:`~dtpf.messages.family.Family`'s are."""

    def __init__(self, kind: str, package: str):
        super().__init__(kind, package, group="")

    def entry_points(self) -> dict:
        """None: an installed package cannot add a member."""
        return {}

    def check_name(self, value) -> str:
        """``value`` if it names a built-in, else a ValueError in one line that lists the names."""
        known = self.names()
        if not isinstance(value, str) or value not in known:
            raise ValueError(f"unknown {self.kind} {value!r}; expected one of {', '.join(known)} (built-in only)")
        return value

    def help(self, own: str | None = None, default=None) -> str:
        """Every name with its summary, and the default (``own`` is not used: there is no user's member)."""
        listed = "; ".join(f"'{name}' ({text})" if text else f"'{name}'" for name, text in self.summaries().items())
        return f"{listed} (default: {default})"


#: Weights of processed particles (dtpf.information.weight_rules): built-in only.
WEIGHT_RULE_REGISTRY = BuiltinOnly("weight rule", "dtpf.information.weight_rules")
#: How small particles are moved (dtpf.information.move_rules): the paper's Eq. 29-30, or the translation-invariant
#: rule; built-in only.
MOVE_RULE_REGISTRY = BuiltinOnly("move rule", "dtpf.information.move_rules")
#: The moves the choosing policy picks from (dtpf.information.layer.ARMS): plain resampling, DT preprocessing
#: with the relative or the paper's rule, roughening, the regularised kernel; and "own", the run's own move after
#: resampling (--move file.py:NAME, or an installed package's), an arm of runs that have one.
ARMS = ("plain", "dt-relative", "dt-paper", "roughening", "regularised", "own")
#: The arm (and the name of the move on the wire) that stands for the run's own move after resampling.
OWN_ARM = "own"
#: The choosing policy's base arm when none is given: over 1,000 seeds per cell roughening was never
#: significantly worse than plain systematic resampling in any cell of its evaluation (docs/results/chooser.md).
DEFAULT_CHOOSE_BASE = "roughening"
#: The choosing policy's base "rehearse": before the run the system layer filters simulated runs of the model
#: with every arm and takes the arm that estimated best (dtpf.system.rehearse).
REHEARSE = "rehearse"
#: The PS policy ``dtpf launch`` and ``dtpf run`` take when none is named: the choosing policy on a rehearsed base
#: (docs/results/chooser.md). A run that sets PS, the weight or move rule or its own move, or turns the twin off,
#: takes the fixed policy, as :class:`~dtpf.messages.config.RunConfig` does.
COMMAND_LINE_POLICY = ("choose", REHEARSE)
#: What the choosing policy's base may be: an arm, or "rehearse".
CHOOSE_BASES = (*ARMS, REHEARSE)
#: Seconds an entity waits, beyond its startup timeout, for a system layer that rehearses (a rehearsal takes
#: seconds to a minute or two; the system layer is alive once it has its base).
REHEARSAL_WAIT = 600.0


def scenario_names() -> list[str]:
    """The names ``--scenario`` takes: the built-in ones and the entry points of :data:`MODEL_ENTRY_POINTS`.

    Looked up once per ``sys.path``: reading the installed distributions' metadata takes milliseconds, and
    a shared service validates a run configuration for every status of every twin it serves (a large fleet's
    information service spent a visible share of its time in this scan).
    """
    return list(_scenario_names(tuple(sys.path)))


@functools.lru_cache(maxsize=4)
def _scenario_names(path: tuple[str, ...]) -> tuple[str, ...]:
    try:
        points = {point.name for point in importlib.metadata.entry_points(group=MODEL_ENTRY_POINTS)}
    except Exception:  # a broken installed distribution must not stop dtpf
        points = set()
    return tuple(sorted(set(SCENARIOS) | points))
