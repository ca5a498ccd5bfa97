"""Run configuration shared by the in-process pipeline and the services.

Every field is declared with its meaning and validated at construction, so a
bad resampler or model name fails at startup, not at step 500::

    from messages.config import RunConfig
    config = RunConfig(particles=1000, steps=100, seed=7)
"""
from __future__ import annotations

import argparse
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

__all__ = ["RunConfig", "ID_PATTERN", "add_run_arguments", "config_from_args"]

#: Run and twin ids: safe inside a Zenoh key expression and a file name.
ID_PATTERN = r"^[A-Za-z0-9_.-]+$"


class RunConfig(BaseModel):
    """One digital-twin run: scenario, filter, preprocessing and PS policy."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    scenario: str = Field("ungm", description="State-space model: 'ungm' (Eq. 35 with 25, the standard "
                                                "benchmark) or 'ungm-printed' (Eq. 35 as printed, 0.25).")
    particles: int = Field(1000, ge=1, description="Number of particles N.")
    steps: int = Field(100, ge=1, description="Number of time points T (k = 1 .. T).")
    resampler: str = Field("systematic", description="Traditional resampling scheme run after preprocessing: "
                                                      "multinomial, stratified, systematic or residual.")
    resample_below: float | None = Field(None, gt=0.0, le=1.0, description="Resample when ESS < this "
                                         "fraction of N; None resamples at every step (the paper).")
    preprocess: bool = Field(True, description="Run the digital-twin preprocessing (Eq. 28-30) before "
                                               "resampling; False gives the plain traditional filter.")
    threshold: str | float = Field("neff", description="Threshold W of Eq. 28: 'neff' (the round(ESS)+1-th "
                                   "largest weight), 'inverse-n' (1/N) or a number.")
    weight_rule: Literal["inherit", "likelihood"] = Field("inherit", description="Weights of processed "
                                                          "particles: keep them, or re-evaluate the likelihood.")
    policy: str = Field("fixed", description="PS policy of the system layer.")
    ps: float = Field(0.81, ge=0.0, le=1.0, description="PS of the fixed policy, and the initial PS.")
    ps_rate: float = Field(0.25, gt=0.0, le=1.0, description="Largest change of PS per step that the "
                                                              "adaptive policies make.")
    seed: int = Field(0, ge=0, description="Root seed of every random stream of the run.")
    twin: str = Field("ungm-1", pattern=ID_PATTERN, description="Twin id (key expressions dtpf/<twin>/...).")
    run_id: str = Field("run", pattern=ID_PATTERN, description="Run id carried by every message.")

    @field_validator("scenario")
    @classmethod
    def _known_scenario(cls, value: str) -> str:
        from entity import models
        models.get(value)
        return value

    @field_validator("resampler")
    @classmethod
    def _known_resampler(cls, value: str) -> str:
        from entity import resampling
        resampling.get(value)
        return value

    @field_validator("policy")
    @classmethod
    def _known_policy(cls, value: str) -> str:
        from system import policy
        if value not in policy.POLICIES:
            raise ValueError(f"unknown PS policy {value!r}; expected one of {', '.join(policy.POLICIES)}")
        return value

    @field_validator("threshold")
    @classmethod
    def _known_threshold(cls, value: str | float) -> str | float:
        from information.rules import THRESHOLD_RULES
        if isinstance(value, str) and value not in THRESHOLD_RULES:
            try:
                value = float(value)
            except ValueError:
                raise ValueError(f"unknown threshold rule {value!r}; expected one of "
                                 f"{', '.join(THRESHOLD_RULES)} or a number") from None
        if not isinstance(value, str) and not value >= 0:
            raise ValueError(f"threshold W must be non-negative, got {value!r}")
        return value

    @model_validator(mode="after")
    def _policy_fits_scenario(self) -> "RunConfig":
        # A simulating policy draws observations from the model; a video scenario cannot.
        from entity import models
        from system import policy
        if policy.POLICIES[self.policy].simulates and not models.get(self.scenario).samples_observations:
            raise ValueError(f"policy {self.policy!r} simulates observations, which scenario "
                             f"{self.scenario!r} cannot draw (the video scenario does not support the "
                             f"simulating system-layer policies rule, predictive); use policy 'fixed'")
        return self


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of one run, shared by every command that starts a run."""
    from entity import models, resampling
    from information.rules import WEIGHT_RULES
    from system import policy

    defaults = RunConfig()
    group = parser.add_argument_group("scenario and filter")
    group.add_argument("--scenario", default=defaults.scenario, choices=sorted(models.MODELS),
                       help="state-space model: 'ungm' is Eq. 35 with 25 (the standard benchmark), "
                            "'ungm-printed' Eq. 35 as printed with 0.25 (default: %(default)s)")
    group.add_argument("--particles", "-n", type=int, default=defaults.particles,
                       help="number of particles N (default: %(default)s)")
    group.add_argument("--steps", "-T", type=int, default=defaults.steps,
                       help="number of time points (default: %(default)s)")
    group.add_argument("--resampler", default=defaults.resampler, choices=sorted(resampling.RESAMPLERS),
                       help="traditional resampling run after preprocessing (default: %(default)s)")
    group.add_argument("--resample-below", type=float, default=None, metavar="FRACTION",
                       help="resample only when ESS < FRACTION * N (default: every step, as the paper)")
    group.add_argument("--seed", type=int, default=defaults.seed, help="root seed (default: %(default)s)")
    group.add_argument("--twin", default=defaults.twin, help="twin id (default: %(default)s)")
    group.add_argument("--run-id", default=defaults.run_id, help="run id (default: %(default)s)")
    group = parser.add_argument_group("digital twin")
    group.add_argument("--no-preprocess", dest="preprocess", action="store_false",
                       help="turn the DT preprocessing off: the plain traditional filter")
    group.add_argument("--threshold", default=defaults.threshold,
                       help="W of Eq. 28: 'neff', 'inverse-n' or a number (default: %(default)s)")
    group.add_argument("--weight-rule", default=defaults.weight_rule, choices=WEIGHT_RULES,
                       help="weights of processed particles (default: %(default)s)")
    group.add_argument("--policy", default=defaults.policy, choices=sorted(policy.POLICIES),
                       help="PS policy of the system layer (default: %(default)s)")
    group.add_argument("--ps", type=float, default=defaults.ps,
                       help="PS of the fixed policy, initial PS of the others (default: %(default)s)")
    group.add_argument("--ps-rate", type=float, default=defaults.ps_rate, metavar="CHANGE",
                       help="largest change of PS per step of the adaptive policies (default: %(default)s)")


def config_from_args(args: argparse.Namespace) -> RunConfig:
    """The RunConfig of parsed arguments; raises ValueError naming a bad option."""
    try:
        return RunConfig(scenario=args.scenario, particles=args.particles, steps=args.steps,
                         resampler=args.resampler, resample_below=args.resample_below,
                         preprocess=args.preprocess, threshold=args.threshold, weight_rule=args.weight_rule,
                         policy=args.policy, ps=args.ps, ps_rate=args.ps_rate, seed=args.seed, twin=args.twin, run_id=args.run_id)
    except ValidationError as error:
        problems = "; ".join((f"--{'-'.join(str(p) for p in e['loc'])}: " if e["loc"] else "") + e["msg"]
                             for e in error.errors())
        raise ValueError(problems.replace("_", "-")) from None
