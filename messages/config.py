"""Run configuration shared by the in-process pipeline and the services.

Every field is declared with its meaning and validated at construction, so a
bad resampler or model name fails at startup, not at step 500::

    from dtpf.messages.config import RunConfig
    config = RunConfig(particles=1000, steps=100, seed=7)
"""
from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from dtpf.messages import family, names
from dtpf.messages.errors import RunInputError

__all__ = ["RunConfig", "RunInputError", "ID_PATTERN", "BLOCK_PARTICLES", "add_run_arguments", "config_from_args",
           "recorded_config"]


#: Run and twin ids: safe inside a Zenoh key expression and a file name.
ID_PATTERN = r"^[A-Za-z0-9_.-]+$"

#: B, the particles of one block of the kernels (dtpf.entity.cores): the block_particles of a new run.
BLOCK_PARTICLES = 1 << 16


def _problems(error: ValidationError, flags: bool = False) -> str:
    """A validation error in one line: each field (as its command-line flag when ``flags``) and what is wrong."""
    def where(loc) -> str:
        if not loc:
            return ""
        name = "-".join(str(part) for part in loc) if flags else ".".join(str(part) for part in loc)
        return (f"--{name.replace('_', '-')}" if flags else name) + ": "

    return "; ".join(where(e["loc"]) + e["msg"].removeprefix("Value error, ") for e in error.errors())


def twin_of_model(reference: str) -> str:
    """The default twin id of a user's model: its file's or module's name and ``-1``
    (``models/rover.py:Rover`` -> ``rover-1``, ``lab.models:Rover`` -> ``models-1``)."""
    module = reference.rpartition(":")[0] or reference
    if module.endswith(".py") or "/" in module or "\\" in module:
        name = Path(module.replace("\\", "/")).name.removesuffix(".py")
    else:
        name = module.rpartition(".")[2]
    name = re.sub(r"[^A-Za-z0-9_.-]+", "-", name).strip(".-")[:60]
    return f"{name or 'model'}-1"


class RunConfig(BaseModel):
    """One digital-twin run: scenario, filter, preprocessing and PS policy.

    A field that does not fit raises :class:`RunInputError` (a :class:`~dtpf.messages.errors.DtpfError`)
    naming every bad field in one line.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    def __init__(self, **values):
        observations = values.get("observations")
        if "steps" not in values and isinstance(observations, str) and observations != "live" \
                and not observations.startswith(("live:", "ros2:")):
            values["steps"] = None  # an observation file: every row, as dtpf run reads it
        if "steps" not in values and values.get("sensor_files"):
            values["steps"] = None  # every row of every sensor's file
        # A new run records B; a config read back from a log written before blocks has none, and
        # recorded_config gives it one block, the numbers of that log.
        values.setdefault("block_particles", BLOCK_PARTICLES)
        try:
            super().__init__(**values)
        except ValidationError as error:
            raise RunInputError(_problems(error), validation=error) from None

    scenario: str = Field("ungm", description="State-space model by name: 'ungm' (Eq. 35 with 25, the "
                                                "standard benchmark), 'ungm-printed' (Eq. 35 as printed, "
                                                "0.25), 'video', 'drift' (a slowly drifting constant), or a "
                                                "name an installed package registers "
                                                "in the entry-point group 'dtpf.models'.")
    model: str | None = Field(None, max_length=4096, description="The user's own model instead of a scenario: "
                              "'package.module:NAME' or 'path/to/file.py:NAME' (a StateSpaceModel instance, "
                              "subclass or zero-argument factory). Every layer loads it.")
    observations: str | None = Field(None, max_length=4096, description="Where the observations come from: "
                                     "None simulates the model (truth known); a file (.csv, .npy, .npz, one "
                                     "row per step); 'live' (the key dtpf/<twin>/sensor/observation) or "
                                     "'live:KEY', a sensor publishing over Zenoh; 'ros2:TOPIC', a ROS 2 topic "
                                     "(a bridge process feeds it to the live key); a rosbag2 log (folder or "
                                     ".mcap) with 'topic'.")
    reader: str | None = Field(None, max_length=family.MAX_REFERENCE, description="How the observations are "
                               "read: a built-in reader (dtpf run --help lists them), a name registered in the "
                               "entry-point group 'dtpf.readers', or your own read(source) -> observations as "
                               "'path/to/file.py:NAME' (None: by the file's kind).")
    topic: str | None = Field(None, max_length=1024, description="The topic of a rosbag2 log given as "
                              "observations (one message, one step).")
    ros2_fields: str | None = Field(None, max_length=4096, description="How a ROS 2 message becomes an "
                                    "observation: field paths, e.g. 'range', 'point.x,point.y', 'ranges[0:8]' "
                                    "(None: the model's observation_from_ros2(message)).")
    partial: bool = Field(False, description="Read what is intact of a damaged observation file (a rosbag2 log "
                          "whose messages are fewer than it declares, or whose chunks do not decode) and say "
                          "what was skipped; False refuses such a file.")
    sensor_files: dict[str, str] | None = Field(None, max_length=64, description="A driven twin's observation "
                                                "files, one per sensor: sensor name (the model's sensors) -> "
                                                "file with a time column (--observations NAME=FILE).")
    controls: str | None = Field(None, max_length=4096, description="A file of the control input: a time column "
                                 "and the model's control columns (zero-order hold between rows); a rosbag2 "
                                 "topic 'BAG:/TOPIC'; 'ros2:TOPIC', a live ROS 2 topic; live, the controls come "
                                 "on dtpf/<twin>/sensor/control.")
    sensor_fields: dict[str, str] | None = Field(None, max_length=64, description="A driven twin's sensors from "
                                                 "ROS 2 topics (a bag's or live): sensor name -> the field paths of "
                                                 "its messages (--ros2-fields NAME=PATHS; none: the model's "
                                                 "observation_from_ros2).")
    control_fields: str | None = Field(None, max_length=4096, description="The field paths of the control "
                                       "topic's messages (--ros2-control-fields; default by its type: Twist, "
                                       "TwistStamped, Odometry -> forward speed and yaw rate, Imu -> forward "
                                       "acceleration and yaw rate).")
    reorder_window: float = Field(0.1, ge=0.0, le=3600.0, description="Seconds of stamp time within which "
                                  "observations (and controls) that arrive out of order are put in stamp order; "
                                  "older ones are counted and skipped.")
    particles: int = Field(1000, ge=1, description="Number of particles N.")
    steps: int | None = Field(100, ge=1, description="Number of time points T (k = 1 .. T). With observations "
                              "from a file: at most this many of its rows (None, the default for a file: every "
                              "row); live: stop after this many steps (None: when the stream ends).")
    resampler: str = Field("systematic", max_length=family.MAX_REFERENCE, description="Traditional resampling "
                           "scheme run after preprocessing: a built-in (dtpf.entity.resampling.RESAMPLERS; "
                           "dtpf run --help lists them), a name an installed package registers in the entry-point group "
                           "'dtpf.resamplers', or your own f(weights, rng) -> ancestors as 'path/to/file.py:NAME' "
                           "or 'package.module:NAME'.")
    resample_below: float | None = Field(None, gt=0.0, le=1.0, description="Resample when ESS < this "
                                         "fraction of N; None resamples at every step (the paper).")
    preprocess: bool = Field(True, description="Run the digital-twin preprocessing (Eq. 28-30) before "
                                               "resampling; False gives the plain traditional filter.")
    threshold: str | float = Field("neff", description="Threshold W of Eq. 28: a built-in rule ('neff', the "
                                   "round(ESS)+1-th largest weight; 'inverse-n', 1/N), a name an installed package "
                                   "registers in the entry-point group 'dtpf.thresholds', your own "
                                   "W = rule(weights) as 'path/to/file.py:NAME' or 'package.module:NAME', or a "
                                   "number (W itself).")
    weight_rule: str = Field("inherit", max_length=64, description="Weights of processed particles, a built-in "
                             "rule (dtpf.information.weight_rules): 'inherit' keeps them, 'likelihood' "
                             "re-evaluates the likelihood.")
    move_rule: str = Field("paper", max_length=64, description="How small particles are moved, a built-in rule "
                           "(dtpf.information.move_rules): 'paper' (Eq. 29-30 as printed) or 'relative' (a "
                           "fraction of x_l - x_m, at most the set's weighted spread: translation invariant; not "
                           "the paper's).")
    jitter: str = Field("none", max_length=family.MAX_REFERENCE, description="After resampling, the entity "
                        "moves each particle by a built-in move ('none', the paper's; dtpf.entity.jitter.JITTERS, which "
                        "dtpf run --help lists), a name registered in the entry-point group 'dtpf.moves', or your own "
                        "move(resampled, particles, weights, rng) as 'path/to/file.py:NAME'.")
    policy: str = Field("fixed", max_length=family.MAX_REFERENCE, description="PS policy of the system layer: a "
                        "built-in (dtpf.system.policy.POLICIES; dtpf run --help lists them), a name registered in the "
                        "entry-point group 'dtpf.policies', or your own PSPolicy subclass as "
                        "'path/to/file.py:NAME'.")
    choose_base: Literal[names.CHOOSE_BASES] | None = Field(
        None, description="The choosing policy's base arm: the move in force when no other has the evidence, and "
        "the one every other arm's evidence is against (only with policy 'choose'; default "
        f"{names.DEFAULT_CHOOSE_BASE}); '{names.REHEARSE}': the arm that estimated best on simulated runs of the "
        "model before the run (dtpf.system.rehearse).")
    ps: float = Field(0.81, ge=0.0, le=1.0, description="PS of the fixed policy, and the initial PS.")
    ps_rate: float = Field(0.25, gt=0.0, le=1.0, description="Largest change of PS per step that the "
                                                              "adaptive policies make.")
    seed: int = Field(0, ge=0, description="Root seed of every random stream of the run.")
    twin: str = Field("ungm-1", pattern=ID_PATTERN, description="Twin id (key expressions dtpf/<twin>/...).")
    run_id: str = Field("run", pattern=ID_PATTERN, description="Run id carried by every message.")
    block_particles: int | None = Field(None, ge=1, description="B: the kernels split a set of N > B "
                                        "particles into blocks of B, sum each block's share of a sum and draw "
                                        "each block's random numbers from its own stream, so that the numbers do "
                                        "not depend on the threads that run them (dtpf.entity.cores). A new run "
                                        f"takes {BLOCK_PARTICLES}; None (a log recorded before blocks): one "
                                        "block, whatever N.")

    @field_validator("scenario")
    @classmethod
    def _known_scenario(cls, value: str) -> str:
        known = names.scenario_names()
        if value not in known:
            raise ValueError(f"unknown scenario {value!r}; expected one of {', '.join(known)} "
                             f"(or give your own model with --model)")
        return value

    @field_validator("model")
    @classmethod
    def _model_reference(cls, value: str | None) -> str | None:
        if value is not None and (":" not in value or not value.rpartition(":")[2] or not value.rpartition(":")[0]):
            raise ValueError(f"model reference {value!r} must be 'package.module:NAME' or 'path/to/file.py:NAME'")
        return value

    @field_validator("observations")
    @classmethod
    def _observation_source(cls, value: str | None) -> str | None:
        if value is None:
            return value
        if not value:
            raise ValueError("observations must name a file, 'live' or 'live:KEY'")
        if value.startswith("ros2:"):
            if not value[len("ros2:"):].strip("/"):
                raise ValueError("observations 'ros2:TOPIC' must name a topic, e.g. ros2:/range")
            return value
        if value.startswith("live:"):
            from dtpf.messages import keys
            key = value[len("live:"):]
            try:
                topic = keys.topic_of(key)
            except ValueError as error:
                raise ValueError(f"live observations: {error}") from None
            if topic.name != "observation":
                raise ValueError(f"live observations come on a key dtpf/<twin>/sensor/observation, got {key!r}")
        return value

    @property
    def model_ref(self) -> str:
        """The model every layer loads: the ``model`` reference, else the ``scenario`` name."""
        return self.model or self.scenario

    @property
    def rehearses(self) -> bool:
        """Whether the system layer rehearses the model before the first step (``choose_base`` "rehearse")."""
        return self.choose_base == names.REHEARSE

    @property
    def live(self) -> bool:
        """Whether observations arrive over Zenoh, one at a time."""
        if self.ros2_sensors:
            return True
        return self.observations is not None and (self.observations == "live" or self.observations.startswith("live:")
                                                  or self.ros2_topic is not None)

    @property
    def ros2_sensors(self) -> dict[str, str]:
        """A driven twin's sensors on live ROS 2 topics (``--observations NAME=ros2:TOPIC``): name -> topic."""
        return {name: _ros2_topic(source) for name, source in (self.sensor_files or {}).items()
                if source.startswith("ros2:")}

    @property
    def ros2_control(self) -> str | None:
        """The live ROS 2 topic of the controls (``--controls ros2:TOPIC``), else None."""
        return _ros2_topic(self.controls) if self.controls and self.controls.startswith("ros2:") else None

    @property
    def ros2_inputs(self) -> bool:
        """Whether a ROS 2 bridge feeds the twin (``ros2:TOPIC`` observations, sensors or controls)."""
        return self.ros2_topic is not None or bool(self.ros2_sensors) or self.ros2_control is not None

    @property
    def ros2_topic(self) -> str | None:
        """The ROS 2 topic of ``--observations ros2:TOPIC`` (absolute, with its leading '/'), else None."""
        if self.observations is None or not self.observations.startswith("ros2:"):
            return None
        topic = self.observations[len("ros2:"):]
        return topic if topic.startswith("/") else "/" + topic

    @property
    def observation_file(self) -> str | None:
        """The file the observations are read from, if any."""
        return None if self.observations is None or self.live else self.observations

    @property
    def simulated(self) -> bool:
        """Whether the observations (and the truth) come from simulating the model."""
        return self.observations is None and not self.sensor_files

    @field_validator("sensor_files")
    @classmethod
    def _sensor_files(cls, value: dict[str, str] | None) -> dict[str, str] | None:
        import re

        for name, path in (value or {}).items():
            if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]{0,63}", name):
                raise ValueError(f"sensor name {name!r} must be a letter then letters, digits, '_' or '-'")
            if not path or len(path) > 4096:
                raise ValueError(f"sensor {name!r} needs a file")
        return value or None

    def observation_key(self) -> str | None:
        """The Zenoh key of live observations: ``dtpf/<twin>/sensor/observation`` or the one given."""
        if not self.live:
            return None
        if self.observations is not None and self.observations.startswith("live:"):
            return self.observations[len("live:"):]  # a ros2: topic comes through the twin's own key
        return f"dtpf/{self.twin}/sensor/observation"

    @field_validator("resampler")
    @classmethod
    def _known_resampler(cls, value: str) -> str:
        return family.RESAMPLERS.check_name(value)

    @field_validator("jitter")
    @classmethod
    def _known_move(cls, value: str) -> str:
        return family.MOVES.check_name(value)

    @field_validator("reader")
    @classmethod
    def _known_reader(cls, value: str | None) -> str | None:
        return None if value is None else family.READERS.check_name(value)

    @field_validator("policy")
    @classmethod
    def _known_policy(cls, value: str) -> str:
        return family.POLICIES.check_name(value)

    @field_validator("threshold")
    @classmethod
    def _known_threshold(cls, value: str | float) -> str | float:
        if isinstance(value, str):
            try:
                value = float(value)
            except ValueError:
                try:
                    return family.THRESHOLDS.check_name(value)
                except ValueError as error:
                    raise ValueError(f"{error}; or a number, W itself") from None
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"threshold W must be a finite non-negative number, got {value!r}")
        return float(value)

    @field_validator("weight_rule")
    @classmethod
    def _known_weight_rule(cls, value: str) -> str:
        return names.WEIGHT_RULE_REGISTRY.check_name(value)

    @field_validator("move_rule")
    @classmethod
    def _known_move_rule(cls, value: str) -> str:
        return names.MOVE_RULE_REGISTRY.check_name(value)

    @model_validator(mode="before")
    @classmethod
    def _twin_of_the_model(cls, values):
        """A user's model names its twin (:func:`twin_of_model`) unless a twin is given."""
        if isinstance(values, dict) and values.get("twin") is None and isinstance(values.get("model"), str):
            values = {**values, "twin": twin_of_model(values["model"])}
        return values

    @model_validator(mode="after")
    def _policy_fits_scenario(self) -> "RunConfig":
        if self.steps is None and self.simulated:
            raise ValueError("steps: a simulated scenario needs a number of steps")
        if self.sensor_files and self.observations is not None:
            raise ValueError("observations: give every sensor as NAME=FILE, or one source without names")
        _check_ros2_sources(self)
        if self.reader is not None and (self.observations is None or self.live):
            raise ValueError(f"reader: a reader ({self.reader}) reads the observations a run is given "
                             f"(--observations SOURCE), not a simulation or a live stream")
        if self.choose_base is not None and not family.POLICIES.trait(self.policy, "chooses_arms", True, load=False):
            raise ValueError(f"choose_base: a base arm ({self.choose_base}) is for policy 'choose', not "
                             f"{self.policy!r}")
        if self.model is not None:
            return self  # a user model is checked when it is loaded (dtpf.entity.model_check)
        # A simulating policy draws observations from the model; a video scenario cannot.
        simulates = family.POLICIES.trait(self.policy, "samples_observations", False, load=False)
        if simulates and self.scenario in names.CANNOT_SAMPLE:
            raise ValueError(f"policy {self.policy!r} simulates observations, which scenario "
                             f"{self.scenario!r} cannot draw (the video scenario does not support the "
                             f"simulating system-layer policies rule, predictive); use policy 'fixed'")
        return self


def _ros2_topic(source: str) -> str:
    """The absolute topic of 'ros2:TOPIC'."""
    topic = source[len("ros2:"):]
    return topic if topic.startswith("/") else "/" + topic


def _check_ros2_sources(config: RunConfig) -> None:
    """A driven twin's ROS 2 sources fit together: live topics for every sensor or none (and the controls with
    them), field paths only for sensors given."""
    files = config.sensor_files or {}
    live = [name for name, source in files.items() if source.startswith("ros2:")]
    if any(not source[len("ros2:"):].strip("/") for source in [*files.values(), config.controls or ""]
           if source.startswith("ros2:")):
        raise ValueError("observations: 'ros2:TOPIC' must name a topic, e.g. gps=ros2:/gps")
    if live and len(live) != len(files):
        other = next(name for name in files if name not in live)
        raise ValueError(f"observations: sensor {live[0]} is a live ROS 2 topic and {other} is not: give every "
                         f"sensor as NAME=ros2:TOPIC, or none")
    if config.ros2_control is not None and files and not live:
        raise ValueError("controls: a live ROS 2 topic (ros2:TOPIC) drives a twin whose sensors are live ROS 2 "
                         "topics too (NAME=ros2:TOPIC)")
    if live and config.controls is not None and config.ros2_control is None:
        raise ValueError("controls: the sensors are live ROS 2 topics: give the controls as ros2:TOPIC too")
    unknown = [name for name in config.sensor_fields or {} if name not in files]
    if unknown:
        raise ValueError(f"--ros2-fields {unknown[0]}=...: no sensor {unknown[0]} is given as "
                         f"--observations {unknown[0]}=BAG:/TOPIC or {unknown[0]}=ros2:TOPIC")


class _FieldsAction(argparse.Action):
    """``--ros2-fields PATHS`` once, or ``--ros2-fields NAME=PATHS`` once per sensor (into ``sensor_fields``):
    a field path has no '='."""

    def __call__(self, parser, namespace, value, option_string=None):
        if not _put_named(parser, namespace, "sensor_fields", "--ros2-fields", value):
            setattr(namespace, self.dest, value)


def _put_named(parser, namespace, dest: str, option: str, value: str) -> bool:
    """Put ``value`` written NAME=VALUE into the dict ``dest`` of ``namespace`` (False: not NAME=VALUE); a name
    given twice is a parser error."""
    import re

    match = re.fullmatch(r"([A-Za-z][A-Za-z0-9_-]{0,63})=(.+)", value)
    if not match:
        return False
    named = dict(getattr(namespace, dest, None) or {})
    if match.group(1) in named:
        parser.error(f"{option} {match.group(1)}= is given twice")
    named[match.group(1)] = match.group(2)
    setattr(namespace, dest, named)
    return True


class _ObservationsAction(argparse.Action):
    """``--observations SOURCE`` once, or ``--observations NAME=FILE`` once per sensor (into ``sensor_files``)."""

    def __call__(self, parser, namespace, value, option_string=None):
        import os

        if not os.path.exists(value) and _put_named(parser, namespace, "sensor_files", "--observations", value):
            return
        if getattr(namespace, self.dest, None) is not None:
            parser.error("--observations takes one source, or NAME=FILE once per sensor")
        setattr(namespace, self.dest, value)


def add_run_arguments(parser: argparse.ArgumentParser, threads: bool = False, choose_by_default: bool = False) -> None:
    """Options of one run, shared by every command that starts a run; ``threads``: and ``--threads``, for
    a command that computes a run's filter (``dtpf run``, ``dtpf launch``, the layers' services);
    ``choose_by_default``: its --help gives the command line's policy (:func:`command_line_policy`) as the default
    (``dtpf run``, ``dtpf launch``)."""
    defaults = RunConfig()
    policy_default = (f"{names.COMMAND_LINE_POLICY[0]} on a {names.COMMAND_LINE_POLICY[1]}d base; {defaults.policy} "
                      f"(PS {defaults.ps}, the paper's) with --ps, --weight-rule, --move-rule, --move or "
                      "--no-preprocess"
                      if choose_by_default else defaults.policy)
    # Every run flag defaults to None, "not given", so that a --config file can set what no flag does.
    parser.add_argument("--config", type=Path, default=None, metavar="FILE",
                        help="run configuration file (TOML, the RunConfig fields, e.g. particles = 5000); "
                             "flags given override it")
    group = parser.add_argument_group("scenario and filter")
    group.add_argument("--scenario", default=None, choices=names.scenario_names(),
                       help="state-space model by name: 'ungm' is Eq. 35 with 25 (the standard benchmark), "
                            "'ungm-printed' Eq. 35 as printed with 0.25, 'video' the tracking scenario, 'drift' a slowly drifting "
                            "constant seen precisely (where particles impoverish), 'switching' that constant seen by a "
                            "sensor whose noise drops at step 51, 'moving' that constant moving away from the origin "
                            "at 0.3 a step "
                            "(the best cure changes during the run); "
                            "installed packages add names through the entry-point group 'dtpf.models' "
                            f"(default: {defaults.scenario})")
    group.add_argument("--model", default=None, metavar="REF",
                       help="your own model instead of a scenario: 'package.module:NAME' or "
                            "'path/to/file.py:NAME', a StateSpaceModel instance, subclass or zero-argument "
                            "factory; checked on a few particles at startup")
    group.add_argument("--observations", default=None, metavar="SOURCE", action=_ObservationsAction,
                       help="observations to filter instead of a simulation: a file (.csv with a header, "
                            ".npy or .npz; one row per step; truth columns optional), or 'live' to take them "
                            "from a sensor on dtpf/<twin>/sensor/observation ('live:KEY' for another key), "
                            "'ros2:TOPIC' for a ROS 2 topic, or a rosbag2 log (folder or .mcap) with --topic; "
                            "a driven model's sensors: NAME=FILE, NAME=BAG:/TOPIC (a rosbag2 log's topic) or "
                            "NAME=ros2:TOPIC, once per sensor")
    group.add_argument("--controls", default=None, metavar="FILE",
                       help="a driven model's control input: a file with a time column and the model's control "
                            "columns (docs/guides/driven.md), a rosbag2 log's topic BAG:/TOPIC or a live "
                            "ros2:TOPIC (Twist, TwistStamped, Odometry or Imu; docs/guides/ros2.md)")
    group.add_argument("--reorder-window", type=float, default=None, metavar="SECONDS",
                       help="put observations that arrive out of order within this much stamp time in order; "
                            f"older ones are counted and skipped (default: {defaults.reorder_window})")
    group.add_argument("--reader", default=None, metavar="NAME",
                       help="how --observations is read: " + family.READERS.help(
                           "your own read(source) -> observations", "by the file's kind"))
    group.add_argument("--topic", default=None, metavar="TOPIC",
                       help="the topic of a rosbag2 log given to --observations (one message, one step)")
    group.add_argument("--ros2-fields", default=None, metavar="PATHS", action=_FieldsAction,
                       help="how a ROS 2 message becomes an observation: field paths, e.g. 'range', "
                            "'point.x,point.y', 'ranges[0:8]' (default: the model's observation_from_ros2); a "
                            "driven model's sensor on a topic: NAME=PATHS, once per sensor")
    group.add_argument("--ros2-control-fields", dest="control_fields", default=None, metavar="PATHS",
                       help="the field paths of the control topic's messages (default by type: Twist "
                            "'linear.x,angular.z', TwistStamped 'twist.linear.x,twist.angular.z', Odometry "
                            "'twist.twist.linear.x,twist.twist.angular.z', Imu "
                            "'linear_acceleration.x,angular_velocity.z')")
    group.add_argument("--partial", action="store_true", default=None,
                       help="read what is intact of a damaged observation file (a rosbag2 log with fewer "
                            "messages than it declares, or chunks that do not decode) and say what was skipped "
                            "(default: refuse it)")
    group.add_argument("--particles", "-n", type=int, default=None,
                       help=f"number of particles N (default: {defaults.particles})")
    group.add_argument("--steps", "-T", type=int, default=None,
                       help=f"number of time points (default: {defaults.steps} for a simulation; every row "
                            f"of an observation file; live: until the sensor ends its stream)")
    group.add_argument("--resampler", default=None, metavar="NAME",
                       help="traditional resampling run after preprocessing: " + family.RESAMPLERS.help(
                           "your own f(weights, rng) -> ancestors", defaults.resampler))
    group.add_argument("--jitter", "--move", dest="jitter", default=None, metavar="NAME",
                       help="after resampling, move each particle (cures of particle impoverishment): "
                            + family.MOVES.help("your own move(resampled, particles, weights, rng) -> moved",
                                                f"{defaults.jitter}, the paper"))
    group.add_argument("--resample-below", type=float, default=None, metavar="FRACTION",
                       help="resample only when ESS < FRACTION * N (default: every step, as the paper)")
    group.add_argument("--seed", type=int, default=None, help=f"root seed (default: {defaults.seed})")
    group.add_argument("--twin", default=None, help=f"twin id (default: {defaults.twin}; with --model, the model's "
                                                    f"file or module name and -1: models/rover.py:Rover -> rover-1)")
    group.add_argument("--run-id", default=None, help=f"run id (default: {defaults.run_id})")
    group = parser.add_argument_group("digital twin")
    group.add_argument("--no-preprocess", dest="preprocess", action="store_false", default=None,
                       help="turn the DT preprocessing off: the plain traditional filter")
    group.add_argument("--threshold", default=None, metavar="RULE",
                       help="W of Eq. 28, a number (W itself) or a rule: " + family.THRESHOLDS.help(
                           "your own W = rule(weights)", defaults.threshold))
    group.add_argument("--weight-rule", default=None, metavar="NAME",
                       help="weights of processed particles: " + names.WEIGHT_RULE_REGISTRY.help(
                           default=defaults.weight_rule))
    group.add_argument("--move-rule", default=None, metavar="NAME",
                       help="how small particles are moved (docs/guides/policies.md): " + names.MOVE_RULE_REGISTRY.help(
                           default=defaults.move_rule))
    group.add_argument("--policy", default=None, metavar="NAME",
                       help="PS policy of the system layer (docs/guides/policies.md): " + family.POLICIES.help(
                           "your own PSPolicy subclass", policy_default))
    group.add_argument("--choose-base", default=None, choices=names.CHOOSE_BASES, metavar="ARM",
                       help="with --policy choose: the arm in force when no other has the evidence, and the one the "
                            f"others are scored against ({', '.join(names.ARMS)}; default: {names.DEFAULT_CHOOSE_BASE}); "
                            f"'{names.REHEARSE}': before the run, filter 200 to 1,600 simulated runs of the model with "
                            "every arm and take the one that estimated best (roughening unless one is significantly "
                            "better)")
    group.add_argument("--ps", type=float, default=None,
                       help=f"PS of the fixed policy, initial PS of the others (default: {defaults.ps})")
    group.add_argument("--ps-rate", type=float, default=None, metavar="CHANGE",
                       help=f"largest change of PS per step of the adaptive policies (default: {defaults.ps_rate})")
    group.add_argument("--block-particles", type=_block_particles, default=None, metavar="B",
                       help="the kernels work on more than B particles in blocks of B, each block's sums and "
                            "random numbers its own, so that the numbers do not depend on --threads; 'none': one "
                            "block, the numbers of a log recorded before blocks (default: "
                            f"{BLOCK_PARTICLES})")
    if not threads:
        return
    group = parser.add_argument_group("process")
    group.add_argument("--threads", type=_threads, default=None, metavar="COUNT",
                       help="threads this process computes on: sets of more than block_particles particles are "
                            "worked on in blocks shared among them, with the same numbers for any COUNT (not a "
                            "setting of the run: it is not recorded) (default: every core this process may use)")


#: --block-particles none: one block (RunConfig.block_particles None).
ONE_BLOCK = "none"


def _block_particles(text: str) -> int | str:
    """``--block-particles B``: a positive whole number, or 'none'."""
    if text.strip().lower() == ONE_BLOCK:
        return ONE_BLOCK
    value = int(text) if text.strip().isdigit() else 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"--block-particles takes a positive whole number or 'none', got {text!r}")
    return value


def _threads(text: str) -> int:
    """``--threads COUNT``: a positive whole number."""
    value = int(text) if text.strip().isdigit() else 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"--threads takes a positive whole number, got {text!r}")
    return value


#: The RunConfig fields the run flags set (argparse dest = field name).
_FLAG_FIELDS = ("scenario", "model", "observations", "sensor_files", "controls", "reorder_window", "reader", "topic", "ros2_fields", "sensor_fields", "control_fields", "partial", "particles", "steps", "resampler", "resample_below",
                "preprocess", "threshold", "weight_rule", "move_rule", "jitter", "policy", "choose_base", "ps", "ps_rate", "seed", "twin", "run_id")


def read_config_file(path) -> dict:
    """The RunConfig fields of a TOML file; ValueError names a missing file, bad TOML or an unknown key."""
    import tomllib

    try:
        with open(path, "rb") as file:
            values = tomllib.load(file)
    except OSError as error:
        raise ValueError(f"--config: cannot read {path}: {error.strerror or error}") from None
    except tomllib.TOMLDecodeError as error:
        raise ValueError(f"--config: {path} is not valid TOML: {error}") from None
    unknown = sorted(set(values) - set(RunConfig.model_fields))
    if unknown:
        raise ValueError(f"--config: {path} has keys that are not run settings: {', '.join(unknown)} "
                         f"(known: {', '.join(RunConfig.model_fields)})")
    if values.get("block_particles") == ONE_BLOCK:  # TOML has no None
        values["block_particles"] = None
    return values


def write_config_file(config: dict, path) -> None:
    """``config`` (RunConfig fields, as a log recorded them) as a TOML file that ``--config`` reads back; None
    values are left out, but a missing or None block_particles is written "none" (one block, as recorded)."""
    lines = ["# dtpf run configuration: dtpf launch --config FILE (flags given override it)"]
    for name in RunConfig.model_fields:
        value = config.get(name)
        if name == "block_particles" and value is None:  # one block (a log recorded before blocks has none)
            value = ONE_BLOCK
        if value is None:
            continue
        if isinstance(value, bool):
            text = "true" if value else "false"
        elif isinstance(value, (int, float)):
            text = repr(value)
        elif isinstance(value, dict):  # a TOML inline table (the sensors' files)
            text = "{ " + ", ".join(f"{json.dumps(str(k))} = {json.dumps(str(v))}" for k, v in value.items()) + " }"
        else:
            text = json.dumps(str(value))  # a TOML basic string
        lines.append(f"{name} = {text}")
    Path(path).write_text("\n".join(lines) + "\n")


def recorded_config(config_json: str) -> RunConfig:
    """The RunConfig a log recorded (a status message's ``config_json``). A log recorded before
    ``block_particles`` existed has none: its config takes None, one block, the numbers it was recorded with."""
    config = RunConfig.model_validate_json(config_json)
    if "block_particles" not in json.loads(config_json):
        config = config.model_copy(update={"block_particles": None})
    return config


#: Settings a run names to have them run at every step: PS and the rules of the fixed policy, and the move after
#: resampling (``--move``). A run that sets one (or turns the twin off) without naming a policy takes the fixed one
#: (:func:`command_line_policy`); the choosing policy would run a named move only where its evidence favours it.
FIXED_SETTINGS = ("ps", "weight_rule", "move_rule", "jitter")


def command_line_policy(values: dict) -> dict:
    """``values`` (RunConfig fields given) with the command line's policy when they name none: the choosing policy
    on a rehearsed base (:data:`~dtpf.messages.names.COMMAND_LINE_POLICY`), unless they set PS, a rule or a move
    (:data:`FIXED_SETTINGS`) or turn the twin off, which keeps RunConfig's default, the paper's fixed PS."""
    if "policy" in values or values.get("preprocess") is False or any(name in values for name in FIXED_SETTINGS):
        return values
    policy, base = names.COMMAND_LINE_POLICY
    return {**values, "policy": policy, "choose_base": values.get("choose_base") or base}


def config_from_args(args: argparse.Namespace, *, choose_by_default: bool = False) -> RunConfig:
    """The RunConfig of parsed arguments: the defaults, then the --config file, then the flags given;
    raises ValueError naming a bad option. ``choose_by_default``: a run that names no policy takes the command
    line's (:func:`command_line_policy`: ``dtpf run``, ``dtpf launch``); False: RunConfig's (the services started
    by hand, ``dtpf compare``'s variants)."""
    values = read_config_file(args.config) if getattr(args, "config", None) else {}
    values.update({name: getattr(args, name) for name in _FLAG_FIELDS if getattr(args, name, None) is not None})
    if choose_by_default:
        values = command_line_policy(values)
    block = getattr(args, "block_particles", None)
    if block is not None:
        values["block_particles"] = None if block == ONE_BLOCK else block
    if "steps" not in values and values.get("observations") is None and not values.get("sensor_files"):
        values["steps"] = RunConfig.model_fields["steps"].default
    elif "steps" not in values:
        values["steps"] = None  # an observation file's rows, or a live stream's end
    try:
        return RunConfig(**values)
    except RunInputError as error:
        if error.validation is None:
            raise
        raise RunInputError(_problems(error.validation, flags=True)) from None
