"""Re-run a recorded twin's entity: propagation, weights, resampling and the move after it.

The entity's filter runs again, in process, on the observations its particle sets carry, with the run's
model, resampler and move (a user's own included, loaded by the reference the log names), taking at each
step the answer it took in the run: the recorded preprocessed set when the step's estimate is not marked
degraded, none when it is. Every recorded propagated set must come out bit for bit: so the resampling and
the move of step k are checked through the set of step k + 1 they lead to. A driven twin's set carries its
sensor and its drive (each piece's dt and control), which the re-run steps with.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dtpf.entity.filter import ParticleFilter, Preprocessed
from dtpf.entity.timeline import Drive
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate, ParticleSet

__all__ = ["EntityRerun", "rerun_entity", "first_difference"]


@dataclass
class EntityRerun:
    """What the entity's re-run found: steps reproduced, the first difference, or why it could not run."""

    checked: list[int]
    #: (step, field, recorded, re-run) of the first propagated set that differs.
    mismatch: tuple[int, str, object, object] | None = None
    #: Why the re-run stopped before the last recorded step (a set or an observation missing), or None.
    skipped: str | None = None


def first_difference(recorded: np.ndarray, rerun: np.ndarray) -> tuple[str, object, object] | None:
    """Where two arrays differ bit for bit: ('[i, j]', recorded value, re-run value), or None."""
    if recorded.shape != rerun.shape:
        return "shape", recorded.shape, rerun.shape
    differ = recorded != rerun
    if not differ.any():
        return None
    index = tuple(int(i) for i in np.argwhere(differ)[0])
    return f"[{', '.join(map(str, index))}]", float(recorded[index]), float(rerun[index])


def drive_of(recorded: ParticleSet) -> Drive | None:
    """The drive a propagated set carries (its pieces' dt and control), or None."""
    return Drive.from_fields(recorded.dt, recorded.control)


def rerun_entity(config: RunConfig, model, twin: str, propagated: dict[int, ParticleSet],
                 preprocessed: dict[int, ParticleSet], estimates: dict[int, Estimate]) -> EntityRerun:
    """Re-run the entity of ``twin`` (module docstring); each dict holds one message per step (the one the
    twin used, in step order)."""
    result = EntityRerun(checked=[])
    steps = sorted(propagated)
    if not steps or steps[0] != 1:
        result.skipped = "the log does not start at step 1"
        return result
    answers: dict[int, Preprocessed | None] = {}

    def answer(step, particles, weights, observation, parents, **driven):
        return answers.get(step)

    pf = ParticleFilter(model, None, config.particles, resampler=config.resampler,
                        resample_below=config.resample_below, seed=config.seed, twin=twin,
                        preprocessor=answer, jitter=config.jitter, block=config.block_particles)
    for step in steps:
        if step != pf.k + 1:
            result.skipped = f"step {pf.k + 1} is not in the log"
            return result
        recorded = propagated[step]
        z = np.asarray(recorded.observation, dtype=np.float64)
        sensor, drive = recorded.sensor, drive_of(recorded)
        if z.size != (model.obs_dim if sensor is None else pf.calls.sensors.get(sensor, -1)):
            result.skipped = f"step {step}'s particle set does not carry its observation"
            return result
        estimate = estimates.get(step)
        if estimate is not None and estimate.resampled and not estimate.degraded:
            answer_set = preprocessed.get(step)
            if answer_set is None:
                result.skipped = f"step {step}: the preprocessed set the entity took is not in the log"
                return result
            answers[step] = Preprocessed(answer_set.particles, answer_set.weights, checked=True,
                                         jitter=answer_set.jitter)
        filtered = pf._step(z, sensor=sensor, drive=drive)
        answers.pop(step, None)
        for name in ("particles", "weights"):
            where = first_difference(getattr(recorded, name), getattr(filtered, name))
            if where is not None:
                index, value, other = where
                result.mismatch = (step, f"{name}{index}" if index != "shape" else f"{name} shape", value, other)
                return result
        result.checked.append(step)
        if estimate is None and step != steps[-1]:
            result.skipped = f"step {step}'s estimate is not in the log (whether it took an answer is unknown)"
            return result
    return result
