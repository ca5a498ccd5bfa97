"""``dtpf verify LOG``: re-run the information and system layers offline.

For every particle set the entity recorded, the information layer's rules and
mirror and the system layer's predictor and policy run again, in process,
with the run configuration the information layer recorded in its status;
every recorded output (preprocessed set with the move it names for the
entity, weight state, PS command with its reason, predicted figures and chosen
arm) must be reproduced exactly. The system layer's
simulation draws from its own random stream, so it is reproduced too. The report goes step by step; the first mismatch names the step,
the topic and the field, and the exit code is 1. A log whose twin has more than one estimate (or entity
particle set) at a step fails too, naming the steps: one twin, one entity, and such a log holds another
entity's or a forger's messages beside the twin's. A log whose recorder declared steps of the twin lost (it
missed them and its publishers' caches no longer held them) fails, naming them: the steps before the first
are re-run, what follows a lost step cannot be.
"""
from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field


from dtpf.entity.timeline import Drive
from dtpf.information.layer import InformationLayer, arms_for
from dtpf.messages.config import RunConfig, recorded_config
from dtpf.messages.models import Missed, ParticleSet, Status
from dtpf.recording.logfile import Log, LogError, in_step_order, read_logs
from dtpf.recording.missed import lost_steps
from dtpf.messages.family import component_records
from dtpf.scripts.logs.rerun_entity import EntityRerun, first_difference, rerun_entity
from dtpf.scripts.logs.summary import format_ranges
from dtpf.system.layer import SystemLayer
from dtpf.system.predict import Snapshot

__all__ = ["verify", "Verification", "Mismatch", "register"]

#: The topics the re-run reads or checks: steps of them that the recorder lost fail the log.
_CHECKED_TOPICS = ("/entity/particles", "/entity/estimate", "/information/preprocessed",
                   "/information/weight_state", "/system/ps")


@dataclass(frozen=True)
class Mismatch:
    """The first recorded output that the re-run does not reproduce."""

    step: int
    topic: str
    field: str
    recorded: object
    rerun: object

    def __str__(self) -> str:
        return f"step {self.step}: {self.topic} {self.field} differs: recorded {self.recorded}, re-run {self.rerun}"


@dataclass
class Verification:
    """Outcome of :func:`verify`: steps checked, steps without recorded output, the first mismatch."""

    twin: str
    config: RunConfig
    checked: list[int] = field(default_factory=list)
    unanswered: list[int] = field(default_factory=list)
    mismatch: Mismatch | None = None
    problem: str | None = None
    #: Steps that had more than one recorded message, by topic (a forger's, or a copy).
    competing: dict[str, list[int]] = field(default_factory=dict)
    #: Of a competing step's messages, the one the re-run reproduced (its index in file order), by (topic, step).
    used: dict[tuple[str, int], int] = field(default_factory=dict)
    #: The entity's re-run (None: not reached, the layers' re-run found a mismatch first).
    entity: EntityRerun | None = None
    #: The user's code the run names whose file differs from the one the run used (or cannot be found now).
    changed_code: list[str] = field(default_factory=list)
    #: Steps the recorder declared lost, by topic (it missed them, and its publishers' caches no longer held them).
    lost: dict[str, list[int]] = field(default_factory=dict)

    @property
    def lost_checked(self) -> dict[str, list[int]]:
        """The lost steps of the topics the re-run reads or checks (not, say, the entity's point cloud)."""
        return {topic: steps for topic, steps in self.lost.items() if topic.endswith(_CHECKED_TOPICS)}

    @property
    def entity_competing(self) -> dict[str, list[int]]:
        """The entity's topics that had more than one message at a step, with those steps: another entity (or a
        forger) published for the twin, so the log does not show one twin's run."""
        return {topic: steps for topic, steps in self.competing.items()
                if topic.endswith(("/entity/estimate", "/entity/particles"))}

    @property
    def ok(self) -> bool:
        """Every recorded output reproduced, one entity's messages only (no competing estimates or sets), and
        no step declared lost by the recorder."""
        return self.mismatch is None and not self.entity_competing and not self.lost_checked


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def _config_of(statuses: list[Status], twin: str) -> RunConfig:
    for layer in ("information", "system", "entity"):
        for status in reversed(statuses):
            if status.layer.value == layer and status.config_json:
                return recorded_config(status.config_json)  # a log from before blocks: one block
    raise LogError(f"the log holds no run configuration for twin {twin!r} (no status message with config_json)")


def load_model_of(config: RunConfig, override: str | None = None):
    """The model the log's run used (``override``: a reference to load instead); LogError says what
    to install or pass when it cannot be loaded."""
    from dtpf.entity import model_ref

    if override is not None:
        config = config.model_copy(update={"model": override})
    try:
        return model_ref.resolve(config.model_ref)
    except model_ref.ModelError as error:
        hint = ("pass --model REF to point at it (for example where the file lies now)" if config.model
                else "install the package that registers it in the entry-point group 'dtpf.models'")
        raise LogError(f"the run's model {config.model_ref!r} cannot be loaded: {error}; {hint}") from None


def verify(log: Log, twin: str | None = None, model_override: str | None = None) -> Verification:
    """Re-run the information and system layers on ``log``'s entity particle sets.

    ``model_override``: a model reference to load instead of the one the log's
    run configuration names (the same model, found elsewhere).
    """
    by_topic = decoded_by_topic(log)
    twins = filtered_twins(by_topic)
    if twin is None:
        if len(twins) != 1:
            raise LogError(f"the log holds twins {twins}: choose one with --twin")
        twin = twins[0]
    elif twin not in {m.twin_id for ms in by_topic.values() for m in ms}:
        raise LogError(f"twin {twin!r} is not in the log; it holds {twins}")
    # The layers sum with one BLAS thread (dtpf.shell.service); a threaded np.dot of more than 10,000 weights
    # sums in another order, and a log of N > 10,000 recorded before blocks would not verify.
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return verify_twin(by_topic, twin, log.problem, model_override)


def decoded_by_topic(log: Log) -> dict[str, list]:
    """Every message of ``log`` that decodes, by topic."""
    by_topic: dict[str, list] = {}
    for item, message in log.decoded():
        if not isinstance(message, Exception):
            by_topic.setdefault(item.topic, []).append(message)
    return by_topic


def filtered_twins(by_topic: dict[str, list]) -> list[str]:
    """The twins whose entity recorded particle sets (a fleet's recorder reports under a twin of its own)."""
    return sorted({m.twin_id for topic, ms in by_topic.items() if topic.endswith("/entity/particles") for m in ms})


def verify_twin(by_topic: dict[str, list], twin: str, problem: str | None = None,
                model_override: str | None = None) -> Verification:
    """:func:`verify` of one twin of an already decoded log."""

    def recorded(topic: str) -> dict[int, list]:
        """The topic's messages by step, each step's in file order."""
        by_step: dict[int, list] = {}
        for message in by_topic.get(f"dtpf/{twin}/{topic}", []):
            by_step.setdefault(message.step, []).append(message)
        for step, found in by_step.items():
            if len(found) > 1:
                result.competing.setdefault(f"dtpf/{twin}/{topic}", []).append(step)
        return by_step

    def matching(step: int, topic: str, candidates: list, compare) -> Mismatch | None:
        """None when one of the step's recorded messages is reproduced; else the first one's mismatch.
        A step with several says which one matched."""
        mismatches = [compare(candidate) for candidate in candidates]
        if None in mismatches:
            if len(candidates) > 1:
                result.used[topic, step] = mismatches.index(None)
            return None
        return mismatches[0]

    statuses = [m for topic, ms in by_topic.items() if topic.startswith(f"dtpf/{twin}/") for m in ms
                if isinstance(m, Status)]
    config = _config_of(statuses, twin)
    if config.rehearses:  # the re-run system layer rehearses too: say why the next seconds pass in silence
        print(f"dtpf verify: twin {twin}: the system layer rehearses the model first (--choose-base rehearse), "
              "seconds to a minute or two", file=sys.stderr, flush=True)
    result = Verification(twin, config, problem=problem, changed_code=changed_code(statuses, config))
    result.lost = lost_steps([m for m in by_topic.get(f"dtpf/{twin}/recorder/missed", []) if isinstance(m, Missed)])
    first_lost = min((steps[0] for steps in result.lost_checked.values()), default=None)
    # The entity's sets are the re-run's input: where a step has several, the one in step order (as the
    # entity publishes them) is used; a lost step ends it (what follows depends on what was lost).
    particle_sets, _ = in_step_order(by_topic.get(f"dtpf/{twin}/entity/particles", []))
    if first_lost is not None:
        particle_sets = {step: found for step, found in particle_sets.items() if step < first_lost}
    recorded("entity/particles")
    # Whether the entity took a step's answer is what its estimate says: the one in step order, as for its sets.
    estimates, competing_estimates = in_step_order(by_topic.get(f"dtpf/{twin}/entity/estimate", []))
    if competing_estimates:  # one twin, one entity: such a log fails (Verification.ok), the steps named
        result.competing[f"dtpf/{twin}/entity/estimate"] = sorted(competing_estimates)
    preprocessed = recorded("information/preprocessed")
    weight_states = recorded("information/weight_state")
    commands = recorded("system/ps")

    model = load_model_of(config, model_override)
    system = SystemLayer.from_config(config, twin, model=model)
    information = InformationLayer(model, ps=system.policy.initial_ps, threshold_rule=config.threshold,
                                   weight_rule=config.weight_rule, seed=config.seed, twin=twin,
                                   move_rule=config.move_rule, preprocess=system.policy.initial_preprocess,
                                   arm=getattr(system.policy, "initial_arm", None),
                                   arms=arms_for(config.jitter), block=config.block_particles)
    for step in sorted(particle_sets):
        source: ParticleSet = particle_sets[step]
        out = information.process(step, source.particles, source.weights, source.observation, source.parents,
                                  sensor=source.sensor)  # a driven twin's step: weighed by its own sensor
        if step not in preprocessed:
            result.unanswered.append(step)
        else:
            mismatch = matching(step, f"dtpf/{twin}/information/preprocessed", preprocessed[step],
                                lambda recorded_set: _compare_preprocessed(step, twin, recorded_set, out))
            if mismatch is not None:
                result.mismatch = mismatch
                return result
        if step in weight_states:
            topic = f"dtpf/{twin}/information/weight_state"
            expected = {**out.summary.as_dict(), "ps": out.preprocessed.report.ps}
            mismatch = matching(step, topic, weight_states[step],
                                lambda state: _compare_fields(step, topic, state, expected))
            if mismatch is not None:
                result.mismatch = mismatch
                return result
        # The system layer simulates from the preprocessed set, as its service receives it.
        snapshot = Snapshot.of(out.preprocessed.particles, out.preprocessed.weights, source.observation) \
            if system.needs_particles else None
        decision = system.observe(step, out.summary, snapshot, sensor=source.sensor,
                                  drive=Drive.from_fields(source.dt, source.control))
        information.set_ps(decision.ps, decision.applies_from_step, decision.preprocess, decision.arm)
        if step in commands:
            topic = f"dtpf/{twin}/system/ps"
            mismatch = matching(step, topic, commands[step],
                                lambda command: _compare_fields(step, topic, command, decision.command_fields()))
            if mismatch is not None:
                result.mismatch = mismatch
                return result
        result.checked.append(step)
    answers = {step: sets[result.used.get((f"dtpf/{twin}/information/preprocessed", step), 0)]
               for step, sets in preprocessed.items()}
    result.entity = rerun_entity(config, model, twin, particle_sets, answers, estimates)
    if result.entity.mismatch is not None:
        step, name, value, other = result.entity.mismatch
        result.mismatch = Mismatch(step, f"dtpf/{twin}/entity/particles", name, value, other)
    return result


def changed_code(statuses: list[Status], config: RunConfig) -> list[str]:
    """The user's code the log's statuses record whose file now has another SHA-256 (or is not found)."""
    now = {(r["field"], r["reference"]): r["sha256"] for r in component_records(config)}
    seen, changed = set(), []
    for status in statuses:
        for component in status.components:
            key = (component.field, component.reference)
            if key in seen or component.sha256 is None:
                continue
            seen.add(key)
            found = now.get(key)
            if found != component.sha256:
                state = "is not found" if found is None else f"has changed (SHA-256 {found[:12]}, the run's {component.sha256[:12]})"
                word = {"jitter": "move", "policy": "PS policy", "threshold": "threshold rule"}.get(component.field,
                                                                                                 component.field)
                changed.append(f"the {word} {component.reference} {state}")
    return changed


def _compare_preprocessed(step: int, twin: str, recorded: ParticleSet, out) -> Mismatch | None:
    topic = f"dtpf/{twin}/information/preprocessed"
    rerun = out.preprocessed
    for name, mine in (("particles", rerun.particles), ("weights", rerun.weights)):
        where = first_difference(getattr(recorded, name), mine)
        if where is not None:
            index, value, other = where
            return Mismatch(step, topic, f"{name}{index}" if index != "shape" else f"{name} shape", value, other)
    report = rerun.report
    return _compare_fields(step, topic, recorded, {
        "ps": report.ps, "threshold": min(report.threshold, 1.0), "n_large": report.n_large,
        "n_processed": report.n_processed, "n_mixed": report.n_mixed, "n_plain": report.n_plain,
        "jitter": out.jitter})


def _compare_fields(step: int, topic: str, recorded, expected: dict) -> Mismatch | None:
    for name, value in expected.items():
        got = getattr(recorded, name)
        if not _same(got, value):
            return Mismatch(step, topic, name, got, value)
    return None


def _ordinals(found: list[int]) -> str:
    """[1, 1, 2] -> 'the 1st received at 2 steps, the 2nd received at 1 step'."""
    counts = {n: found.count(n) for n in sorted(set(found))}
    words = {1: "1st", 2: "2nd", 3: "3rd"}
    return ", ".join(f"the {words.get(n, f'{n}th')} received at {k} step{'s' * (k != 1)}" for n, k in counts.items())


def cmd_verify(args: argparse.Namespace) -> int:
    try:
        log = read_logs(args.log)
        if args.twin is None:  # every twin of the log, one after the other (a fleet's log holds many)
            by_topic = decoded_by_topic(log)
            twins = filtered_twins(by_topic)
            if not twins:
                raise LogError("the log holds no entity particle set to verify")
            results = [verify_twin(by_topic, twin, log.problem, args.model) for twin in twins]
        else:
            results = [verify(log, args.twin, args.model)]
    except LogError as error:
        print(f"dtpf verify: error: {error}")
        return 2
    if log.problem:
        print(f"note: {log.problem}")
    codes = [_report(result, args.verbose) for result in results]
    if len(results) > 1:
        print(f"{codes.count(0)} of {len(results)} twins reproduced exactly")
    return max(codes)


def _report(result: Verification, verbose: bool) -> int:
    c = result.config
    print(f"twin {result.twin}: re-running information (threshold {c.threshold}, weight rule {c.weight_rule}) "
          f"and system (policy {c.policy}, PS {c.ps:g}) on the recorded entity particle sets, then the entity "
          f"(resampler {c.resampler}, move {c.jitter})")
    for change in result.changed_code:
        print(f"note: {change} since the run: a difference may come from it")
    if verbose:
        for step in result.checked:
            print(f"step {step}: ok")
    if result.unanswered:
        print(f"steps without a recorded preprocessed set (the information layer did not answer): "
              f"{format_ranges(result.unanswered)}")
    for topic, steps in sorted(result.competing.items()):
        if topic.endswith("/entity/estimate"):
            how = "the re-run used the one received in step order; the others are another entity's or a forger's"
        elif topic.endswith("/entity/particles"):
            how = "the re-run used the one received in step order, as the entity publishes them"
        else:
            found = [result.used[topic, step] + 1 for step in steps if (topic, step) in result.used]
            how = (f"the re-run reproduced one message of each ({_ordinals(found)}); the rest are not what the "
                   f"twin's layers computed" if found else "none was checked")
        print(f"competing: {topic} had more than one message at steps {format_ranges(steps)}: {how}")
    for topic, steps in sorted(result.entity_competing.items()):
        print(f"FAILED: {topic} had more than one message at steps {format_ranges(steps)}: one twin, one "
              f"entity; the log holds another entity's (or a forger's) messages beside the twin's, so it does "
              f"not show one twin's run")
    if result.mismatch is not None:
        print(f"MISMATCH {result.mismatch}")
        entity = result.entity
        if entity is not None and entity.mismatch is not None:
            print(f"the information and system layers reproduced steps {format_ranges(result.checked)}"
                  + (f"; the entity steps {format_ranges(entity.checked)} before it" if entity.checked else ""))
        elif result.checked:
            print(f"steps {format_ranges(result.checked)} were reproduced exactly before it")
        return 1
    for topic, steps in result.lost.items():
        checked = topic in result.lost_checked
        print(f"{'FAILED' if checked else 'note'}: the recorder declared steps {format_ranges(steps)} of {topic} lost "
              f"(it missed them and the publishers' caches no longer held them)"
              + ("; the re-run stops before the first" if checked else ""))
    if result.entity_competing or result.lost_checked:
        print(f"the layers' outputs of {len(result.checked)} steps were reproduced exactly; the log fails all the "
              f"same")
        return 1
    print(f"OK: {len(result.checked)} steps reproduced exactly "
          f"(preprocessed sets bit for bit, weight states, PS commands)")
    entity = result.entity
    if entity is not None:
        done = f"entity: {len(entity.checked)} propagated sets reproduced bit for bit (propagation, weights, " \
               f"the resampling and move of the step before)"
        print(done + (f"; stopped: {entity.skipped}" if entity.skipped else ""))
    return 0


def register(subparsers) -> None:
    """Add the ``verify`` command to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "verify", help="re-run the information and system layers on a log and check every recorded output",
        description=__doc__.split("\n\n", 1)[1].replace("\n", " "))
    parser.add_argument("log", nargs="+", metavar="LOG",
                        help="MCAP log written by dtpf launch or the recorder; several: the segments of one "
                             "run, in order")
    parser.add_argument("--twin", help="twin to verify (default: every twin of the log, one after the other)")
    parser.add_argument("--model", metavar="REF", default=None,
                        help="load the run's model from this reference instead of the one the log names "
                             "(for a model file that has moved)")
    parser.add_argument("--verbose", "-v", action="store_true", help="print a line for every step")
    parser.set_defaults(handler=cmd_verify)
