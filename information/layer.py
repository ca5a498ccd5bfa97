"""The information layer, without transport.

It mirrors each particle set the entity sends, applies the preprocessing
rules (Eq. 28-30) with the PS in force and returns the preprocessed set and
the weight-state summary. The Zenoh service and the in-process pipeline both
drive this object, so both compute the same numbers::

    layer = InformationLayer(model, ps=0.81, seed=7, twin="ungm-1")
    out = layer.process(step, particles, weights, observation)
    layer.set_ps(decision.ps, decision.applies_from_step, decision.preprocess)

The system layer may turn the preprocessing off for a step (its decision's
``preprocess`` is False): the entity's set then goes back as it came, and the
entity resamples it plainly.

A choosing system layer names an *arm* instead (:data:`ARMS`): the move in
force from the step its decision names. The DT arms preprocess here, with the
arm's own rule, weights and PS; the others send the set back as it came and
name, in :attr:`InformationOutput.jitter` (on the wire: the preprocessed
set's ``jitter`` field), the move the entity applies after resampling it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dtpf.entity import cores
from dtpf.entity.calls import ModelCalls
from dtpf.entity.models import StateSpaceModel
from dtpf.information import rules
from dtpf.information.mirror import WeightSummary, summarise
from dtpf.messages.arrays import check_probability
from dtpf.messages.family import MOVES, THRESHOLDS
from dtpf.messages.names import MOVE_RULE_REGISTRY, OWN_ARM, WEIGHT_RULE_REGISTRY
from dtpf.messages.streams import stream

__all__ = ["InformationLayer", "InformationOutput", "Arm", "ARMS", "arms_for"]


@dataclass(frozen=True)
class Arm:
    """One move a choosing system layer can put in force, with its documented parameters.

    ``preprocess``: DT preprocessing (Eq. 28-30) with ``ps``, ``move_rule`` and
    ``weight_rule`` (:func:`dtpf.information.rules.preprocess`) before the
    entity resamples; ``jitter``: the entity's move after resampling
    (:mod:`dtpf.entity.jitter`).
    """

    name: str
    preprocess: bool = False
    ps: float = 0.0
    move_rule: str = "paper"
    weight_rule: str = "inherit"
    jitter: str = "none"


#: The arms of the choosing policy, by name (the names are :data:`dtpf.messages.names.ARMS`):
#: plain resampling; the relative move rule at PS 0 with likelihood weights (the guard's setting);
#: the paper's Eq. 29-30 at PS 0.81 with inherited weights; roughening (K = 0.2); the regularised
#: filter's kernel (h_opt).
ARMS: dict[str, Arm] = {
    "plain": Arm("plain"),
    "dt-relative": Arm("dt-relative", True, 0.0, "relative", "likelihood"),
    "dt-paper": Arm("dt-paper", True, 0.81, "paper", "inherit"),
    "roughening": Arm("roughening", jitter="roughening"),
    "regularised": Arm("regularised", jitter="regularised"),
}


def arms_for(move: str = "none") -> dict[str, Arm]:
    """The arms of a run whose own move after resampling is ``move``: :data:`ARMS`, and, when ``move`` is
    not a built-in (a user's ``file.py:NAME`` or an installed package's), the arm "own" that makes it
    (named "own" on the wire; the entity and the system layer's copies apply the run's move)."""
    if move in MOVES.builtins():
        return ARMS
    return {**ARMS, OWN_ARM: Arm(OWN_ARM, jitter=OWN_ARM)}


@dataclass(frozen=True)
class InformationOutput:
    """The preprocessed set (for the entity) and the summary (for the system layer)."""

    step: int
    preprocessed: rules.PreprocessResult
    summary: WeightSummary
    #: The entity's move after resampling this set, when a chosen arm names one (None: the run's own).
    jitter: str | None = None


#: Most PS commands waiting for their step (the system layer sends one per step, for the next).
MAX_PENDING = 64

#: The (threshold rule, size class) whose kernels :meth:`InformationLayer.warm_up` has loaded in this
#: process: numba compiles per type of argument, not per twin, so a fleet's service warms up once a class.
_WARMED: set[tuple[str, int]] = set()


class InformationLayer:
    """Mirror plus preprocessing rules for one twin.

    Parameters
    ----------
    model : StateSpaceModel
        Gives the observation likelihood for the ``"likelihood"`` weight rule.
    ps : float
        PS in force until the system layer says otherwise.
    threshold_rule, weight_rule, move_rule :
        Options of :func:`dtpf.information.rules.preprocess`. A threshold rule that names a user's
        code is loaded and tried here (:class:`~dtpf.messages.references.ReferenceLoadError`, one line).
    seed, twin :
        Key of the random streams: step k draws from
        ``stream(seed, twin, k, "information")``.
    preprocess : bool
        Whether the preprocessing runs before the system layer's first
        decision (False for a policy that starts off, the guard).
    arm : str, optional
        The arm (:data:`ARMS`) in force before the system layer's first
        decision (the choosing policy starts with "plain").
    arms : dict, optional
        The arms a system layer may name (:func:`arms_for` the run's move; default :data:`ARMS`).
    """

    def __init__(self, model: StateSpaceModel, *, ps: float, threshold_rule: str | float = "neff",
                 weight_rule: str = "inherit", seed: int = 0, twin: str = "twin", move_rule: str = "paper",
                 preprocess: bool = True, arm: str | None = None, arms: dict[str, Arm] | None = None,
                 block: int | None = None):
        self.model = model
        #: The model's calls with a sensor (dtpf.entity.calls), read once when a driven step first needs them.
        self._calls = None
        #: The arms a system layer may name.
        self.arms: dict[str, Arm] = ARMS if arms is None else arms
        self.ps = check_probability(ps, "PS")
        #: Whether the preprocessing runs (the system layer's latest decision in force).
        self.enabled = bool(preprocess)
        #: The chosen arm in force (None: the run's own preprocessing options).
        self.arm: Arm | None = None
        self.pending: list[tuple[int, float, bool, Arm | None]] = []
        if isinstance(threshold_rule, str):
            THRESHOLDS.get(threshold_rule)  # a user's rule is loaded and tried on a small set here, not at step 1
        self.threshold_rule = threshold_rule
        self.weight_rule = WEIGHT_RULE_REGISTRY.check_name(weight_rule)
        self.move_rule = MOVE_RULE_REGISTRY.check_name(move_rule)
        self.seed = seed
        self.twin = twin
        #: B of the run (its block_particles): a larger set is worked on in blocks (dtpf.entity.cores).
        self.block = block
        self._ahead: tuple[int, np.random.Generator] | None = None
        if arm is not None:
            self.set_ps(self.ps, 0, preprocess, arm)
            self.ps_for(0)

    def warm_up(self, particles: int = 8) -> None:
        """Run the rules and the mirror on a throwaway set of the size class of ``particles``, read-only
        as a decoded message's arrays are, so that the compiled kernels the service's first real step
        takes are loaded before it (a compilation takes seconds); once per process, threshold rule and
        size class. No state changes.

        numba compiles read-only arrays apart from writable ones, and the rules' path changes with N
        (one compiled call below SMALL_SET, three from it on, the radix select from RADIX_MIN on): a
        service that warmed up on writable arrays compiled for seconds on its first set, past the
        entity's lockstep timeout, and one that warmed up every class and kind compiled for longer
        than the entity's default startup timeout on a cold cache.
        """
        stream(self.seed, self.twin, 0, "information")  # the compiled SeedSequence (dtpf.messages._seedseq)
        size = rules.size_class(particles)
        key = (self.threshold_rule if isinstance(self.threshold_rule, str) else "a value", size,
               self.block is not None and particles > self.block, particles >= cores.PARALLEL_MIN)
        if key in _WARMED:
            return
        rng = np.random.default_rng(0)
        x = rng.standard_normal((size, self.model.dim))
        w = rng.random(size)
        w /= w.sum()
        x.flags.writeable = w.flags.writeable = False
        # A run in blocks: its blocked kernels too, on two blocks of half the set.
        for block in (None,) if self.block is None or particles <= self.block else (None, size // 2):
            rules.preprocess(x, w, self.ps, rng, threshold_rule=self.threshold_rule, weight_rule="inherit",
                             block=block)
            summarise(x, w, self.threshold_rule, size, block=block)
        if particles >= cores.PARALLEL_MIN:  # the kernels that share a large set among the threads
            rules.warm_up_threads(x, w)
        _WARMED.add(key)

    def set_ps(self, ps: float, applies_from_step: int, preprocess: bool = True, arm: str | None = None) -> None:
        """Schedule a new PS from the system layer, in force from ``applies_from_step``;
        ``preprocess=False`` turns the preprocessing off from that step (until a later command turns it on).
        ``arm`` (:data:`ARMS`): the chosen move from that step on; its own PS and rules replace ``ps``
        and the run's options (ValueError for an unknown arm).

        A later command for the same step replaces the earlier one; at most
        MAX_PENDING steps wait (the farthest is dropped), so a flood of commands
        cannot grow the schedule.
        """
        step, ps = int(applies_from_step), check_probability(ps, "PS")
        chosen = None
        if arm is not None:
            if arm not in self.arms:
                raise ValueError(f"unknown arm {arm!r}; expected one of {', '.join(self.arms)}")
            chosen = self.arms[arm]
            ps, preprocess = chosen.ps, chosen.preprocess
        self.pending = [item for item in self.pending if item[0] != step]
        self.pending.append((step, ps, bool(preprocess), chosen))
        self.pending.sort(key=lambda item: item[0])
        del self.pending[MAX_PENDING:]

    def ps_for(self, step: int) -> float:
        """The PS in force at ``step``: the latest scheduled one that applies by then."""
        while self.pending and self.pending[0][0] <= step:
            _, self.ps, self.enabled, self.arm = self.pending.pop(0)
        return self.ps

    @property
    def jitter(self) -> str | None:
        """The entity's move after resampling under the arm in force (None without a chosen arm)."""
        return None if self.arm is None else self.arm.jitter

    def prepare(self, step: int) -> None:
        """Make the random stream of ``step`` now, before its particle set arrives.

        For a caller with time to spare (the service, once the mirror of the
        step before is out); :meth:`preprocess` of ``step`` then uses it, so
        the numbers do not change.
        """
        self._ahead = (int(step), stream(self.seed, self.twin, step, "information"))

    def _stream(self, step: int) -> np.random.Generator:
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead[0] == step:
            return ahead[1]
        return stream(self.seed, self.twin, step, "information")

    def preprocess(self, step: int, particles, weights, observation, *, checked: bool = False,
                   sensor: str | None = None) -> rules.PreprocessResult:
        """Eq. 28-30 on the entity's particle set of ``step``, with the PS in force.

        The first half of :meth:`process`: what the entity waits for. W comes
        from the layer's threshold rule, as the mirror computes it.
        ``checked``: the arrays come from a decoded (validated) message; see
        :func:`dtpf.information.rules.preprocess`. ``sensor``: the sensor the observation is from (a model
        with several sensors weighs it by that sensor's likelihood).
        """
        ps = self.ps_for(step)
        if not self.enabled:
            self._ahead = None  # a stream made ahead for this step is not used
            return rules.unprocessed(particles, weights, ps, threshold_rule=self.threshold_rule, checked=checked)
        z = np.asarray(observation, dtype=np.float64)
        arm = self.arm
        weight_rule = self.weight_rule if arm is None else arm.weight_rule
        move_rule = self.move_rule if arm is None else arm.move_rule
        log_likelihood = None
        if weight_rule == "likelihood":
            if sensor is None:
                def log_likelihood(x):
                    return self.model.log_likelihood(x, z, step)
            else:
                calls = self._calls = self._calls if self._calls is not None else ModelCalls(self.model)

                def log_likelihood(x):
                    return calls.log_likelihood(x, z, step, sensor=sensor)
        return rules.preprocess(particles, weights, ps, self._stream(step),
                                threshold_rule=self.threshold_rule, weight_rule=weight_rule,
                                log_likelihood=log_likelihood, checked=checked, move_rule=move_rule,
                                block=self.block)

    def mirror(self, particles, weights, parents: int | None = None,
               threshold: float | None = None, *, checked: bool = False) -> WeightSummary:
        """The weight-state summary of the entity's set (see :func:`dtpf.information.mirror.summarise`).

        ``threshold``: W if :meth:`preprocess` already found it (the same number).
        """
        return summarise(particles, weights, self.threshold_rule if threshold is None else threshold, parents,
                         checked=checked, block=self.block)

    def process(self, step: int, particles, weights, observation, parents: int | None = None, *,
                sensor: str | None = None) -> InformationOutput:
        """Mirror and preprocess the entity's particle set of ``step`` (``parents``: see
        :func:`dtpf.information.mirror.summarise`; ``sensor``: see :meth:`preprocess`)."""
        result = self.preprocess(step, particles, weights, observation, sensor=sensor)
        summary = self.mirror(particles, weights, parents, result.report.threshold)
        return InformationOutput(step, result, summary, self.jitter)
