"""The messages the three layers exchange, as validated pydantic models.

Every message carries the same header (:class:`Message`): who sent it (run,
twin, layer), for which filter step, and when. Construction validates every
field, so a bad message fails where it is made, not where it is read::

    from dtpf.messages.models import ParticleSet
    ps = ParticleSet(run_id="r1", twin_id="ungm-1", step=3, kind="propagated",
                     particles=x, weights=w, observation=[z])

``stamp`` defaults to :meth:`Time.now` and ``layer`` to the only layer that
produces the message, but only when a message is built in Python: a decoded
message must carry both.

Conventions
-----------
- Floats are finite everywhere (NaN and inf are rejected at construction:
  JSON has no spelling for them).
- Closed sets are string enums (:class:`Layer`, :class:`ParticleSetKind`,
  :class:`ServiceState`); plain strings with the same value are accepted.
- Messages are frozen. The arrays of a :class:`ParticleSet` are read-only
  views; ``ps.particles.copy()`` gives a writable array.
"""
from __future__ import annotations

import base64
import binascii
import enum
import re
import time
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PlainSerializer,
    PlainValidator,
    ValidationInfo,
    WithJsonSchema,
    model_validator,
)

from dtpf.messages import family, names
from dtpf.messages.arrays import check_particles, check_probability, check_weights, is_plain_float64

UINT32_MAX = 2**32 - 1

_object_setattr = object.__setattr__

#: Characters allowed in run and twin ids (they become key-expression chunks).
ID_PATTERN = r"^[A-Za-z0-9_.-]+$"
_ID_RE = re.compile(ID_PATTERN)


class Layer(enum.StrEnum):
    """The processes that publish messages (a closed set)."""

    ENTITY = "entity"
    INFORMATION = "information"
    SYSTEM = "system"
    RECORDER = "recorder"
    #: The physical system's sensor (or its stand-in ``dtpf sensor``): not a layer of the twin, but it publishes.
    SENSOR = "sensor"


class ParticleSetKind(enum.StrEnum):
    """Which point of the filter step a :class:`ParticleSet` comes from."""

    PROPAGATED = "propagated"      #: entity, after propagate + weight + normalise
    PREPROCESSED = "preprocessed"  #: information, after the rules of Eq. 28-30


class ServiceState(enum.StrEnum):
    """Life cycle of a layer process, as reported by :class:`Status`."""

    STARTING = "starting"
    RUNNING = "running"
    #: Running, but waiting for input that does not come (a live entity with no observation for a while).
    WAITING = "waiting"
    FINISHED = "finished"
    FAILED = "failed"


def check_id(value: str, name: str = "id") -> str:
    """Return ``value`` if it is a valid run or twin id, else raise ValueError.

    Ids are non-empty and use only letters, digits, '_', '.' and '-', so they
    are safe as one chunk of a Zenoh key expression (no '/', '*', '$', '?', '#').
    """
    if not isinstance(value, str):
        raise ValueError(f"{name} must be a string, got {value!r}")
    if not _ID_RE.match(value):
        raise ValueError(f"{name} must be non-empty and use only letters, digits, '_', '.', '-'; got {value!r}")
    return value


def _run_id(value: str) -> str:
    return check_id(value, "run_id")


def _twin_id(value: str) -> str:
    return check_id(value, "twin_id")


def _probability(name: str):
    def check(value: float | None) -> float | None:
        return None if value is None else check_probability(value, name)
    return AfterValidator(check)


def _read_only(array: np.ndarray) -> np.ndarray:
    """A read-only, C-contiguous view (never a write to the caller's flags)."""
    view = np.ascontiguousarray(array).view()
    view.flags.writeable = False
    return view


#: Validation context for arrays that passed :func:`~dtpf.messages.arrays.check_particles` and
#: :func:`~dtpf.messages.arrays.check_weights` already, where a layer publishes its own output:
#: ``ParticleSet.model_validate(fields, context=ARRAYS_CHECKED)``. Float64 arrays of the right
#: rank become read-only views without a second scan; every other field, and the lengths,
#: are validated as always. Receivers never use it: decoding checks every array.
ARRAYS_CHECKED = {"arrays_checked": True}


def _checked(value: Any, info: ValidationInfo, ndim: int) -> bool:
    return bool(info.context) and info.context.get("arrays_checked") is True and is_plain_float64(value, ndim)


def _particles(value: Any, info: ValidationInfo) -> np.ndarray:
    return _read_only(value if _checked(value, info, 2) else check_particles(value))


def _weights(value: Any, info: ValidationInfo) -> np.ndarray:
    return _read_only(value if _checked(value, info, 1) else check_weights(value))


def _to_list(array: np.ndarray) -> list:
    return array.tolist()


#: (N, d) float64 states; a 1-D input of length N becomes (N, 1).
ParticlesArray = Annotated[
    np.ndarray,
    PlainValidator(_particles),
    PlainSerializer(_to_list, when_used="json"),
    WithJsonSchema({"type": "array", "items": {"type": "array", "items": {"type": "number"}}}),
]
#: (N,) float64 normalised weights.
WeightsArray = Annotated[
    np.ndarray,
    PlainValidator(_weights),
    PlainSerializer(_to_list, when_used="json"),
    WithJsonSchema({"type": "array", "items": {"type": "number"}}),
]
RunId = Annotated[str, AfterValidator(_run_id), Field(json_schema_extra={"pattern": ID_PATTERN})]
TwinId = Annotated[str, AfterValidator(_twin_id), Field(json_schema_extra={"pattern": ID_PATTERN})]
Count = Annotated[int, Field(ge=0, le=UINT32_MAX)]
#: A sensor's name (a model's ``sensors``): a letter, then letters, digits, '_' or '-'.
SENSOR_PATTERN = r"^[A-Za-z][A-Za-z0-9_-]{0,63}$"
SensorName = Annotated[str, Field(max_length=64, pattern=SENSOR_PATTERN)]
#: Most control components a message carries, and most pieces a step's drive has.
MAX_CONTROLS = 64
MAX_DRIVE_PIECES = 4096

#: Every model: unknown fields rejected, frozen, finite floats only.
STRICT_CONFIG = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Time(BaseModel):
    """Wall-clock time as Foxglove's ``{sec, nsec}`` (both uint32)."""

    model_config = STRICT_CONFIG

    sec: int = Field(ge=0, le=UINT32_MAX, description="Whole seconds since the Unix epoch.")
    nsec: int = Field(ge=0, le=999_999_999, description="Nanoseconds within the second.")

    @classmethod
    def from_ns(cls, ns: int) -> "Time":
        """The time ``ns`` nanoseconds after the Unix epoch."""
        sec, nsec = divmod(int(ns), 1_000_000_000)
        return cls(sec=sec, nsec=nsec)

    @classmethod
    def now(cls) -> "Time":
        """The current wall-clock time."""
        return cls.from_ns(time.time_ns())

    def to_ns(self) -> int:
        """Nanoseconds since the Unix epoch (what MCAP's ``log_time`` takes)."""
        return self.sec * 1_000_000_000 + self.nsec


class Message(BaseModel):
    """The header every message carries.

    Subclasses with a single producing layer set :attr:`producer`; ``layer``
    then defaults to it and any other value is rejected.
    """

    model_config = STRICT_CONFIG

    #: The layer that publishes this message class (None: any layer).
    producer: ClassVar[Layer | None] = None

    run_id: RunId = Field(description="Id of the run (one execution of a scenario).")
    twin_id: TwinId = Field(description="Id of the digital twin (one filter).")
    step: Count = Field(description="Filter step k, 1..T; 0 for run-level messages.")
    stamp: Time = Field(description="When the message was made (wall-clock publish time); an estimate of a run "
                                  "driven by a recorded log (a rosbag2 file) carries its step's recorded time.")
    layer: Layer = Field(description="The layer that produced the message.")

    @classmethod
    def _expected_layer(cls, data: Any) -> Layer | None:
        """The only layer allowed to produce this message, given its field values."""
        return cls.producer

    @model_validator(mode="before")
    @classmethod
    def _fill_defaults(cls, data: Any, info: ValidationInfo) -> Any:
        # Defaults only for messages built in Python: a decoded message that
        # lacks its stamp or layer is malformed, not "now" or "guessed".
        if info.mode != "python" or not isinstance(data, dict):
            return data
        if "stamp" in data and "layer" in data:
            return data
        data = dict(data)
        if "stamp" not in data:
            data["stamp"] = Time.now()
        if "layer" not in data:
            layer = cls._expected_layer(data)
            if layer is not None:
                data["layer"] = layer
        return data

    @model_validator(mode="after")
    def _check_layer(self) -> "Message":
        expected = self._expected_layer(self.__dict__)
        if expected is not None and self.layer != expected:
            raise ValueError(
                f"{type(self).__name__} is produced by the {expected.value} layer, got layer={self.layer.value!r}")
        return self


#: What the rules of Eq. 28-30 did at one step; optional on every message that carries them.
_COUNT_DOCS = {
    "n_large": "M: particles with weight above the threshold W, kept as they are (Eq. 28).",
    "n_processed": "N - M: small-weight particles moved by Eq. 29 (n_mixed + n_plain).",
    "n_mixed": "Processed particles that took the first branch of Eq. 30 (u <= PS).",
    "n_plain": "Processed particles that took the second branch of Eq. 30 (u > PS).",
}


def _count(name: str):
    return Field(default=None, description=_COUNT_DOCS[name])


def _check_counts(message: BaseModel, n: int | None) -> None:
    """n_mixed + n_plain == n_processed and n_large + n_processed <= n, where given."""
    large, processed, mixed, plain = message.n_large, message.n_processed, message.n_mixed, message.n_plain
    if None not in (processed, mixed, plain) and mixed + plain != processed:
        raise ValueError(
            f"n_mixed + n_plain must equal n_processed, got {mixed} + {plain} != {processed}")
    if n is not None and None not in (large, processed) and large + processed > n:
        raise ValueError(f"n_large + n_processed must be at most N={n}, got {large} + {processed}")


def _check_lengths(header: BaseModel, particles: np.ndarray, weights: np.ndarray) -> None:
    """As many particles as weights, and the header's counts and ``parents`` within that N."""
    n_particles, n_weights = particles.shape[0], weights.shape[0]
    if n_particles != n_weights:
        raise ValueError(
            f"particles and weights differ in length: {n_particles} particles, {n_weights} weights")
    _check_counts(header, n_weights)
    if header.parents is not None and header.parents > n_weights:
        raise ValueError(f"parents must be at most N={n_weights}, got {header.parents}")


class ParticleSetHeader(Message):
    """Everything of a :class:`ParticleSet` but its arrays.

    This is the ``fields`` object of the binary envelope's JSON header (see
    :mod:`dtpf.messages.codec`).
    """

    kind: ParticleSetKind = Field(
        description="'propagated' (entity, before resampling) or 'preprocessed' (information, after Eq. 28-30).")
    observation: list[float] = Field(default_factory=list, description="z_k, the observation of this step; may be empty.")
    ps: Annotated[float | None, _probability("ps")] = Field(
        default=None, description="PS used to preprocess this set, in [0, 1]; required for preprocessed sets, "
                                  "absent for propagated ones.")
    threshold: float | None = Field(
        default=None, ge=0.0, le=1.0, description="The weight threshold W of Eq. 28 used for preprocessed sets.")
    n_large: Count | None = _count("n_large")
    n_processed: Count | None = _count("n_processed")
    n_mixed: Count | None = _count("n_mixed")
    n_plain: Count | None = _count("n_plain")
    parents: int | None = Field(
        default=None, ge=1, le=UINT32_MAX, description="Number of distinct particles this set descends from "
                                                        "(distinct ancestors of the last resampling); absent "
                                                        "before the first resampling.")
    sensor: SensorName | None = Field(default=None, description="The sensor z_k is from (a model with several "
                                                                "sensors); absent: the model's one sensor.")
    dt: list[Annotated[float, Field(ge=0.0)]] | None = Field(
        default=None, max_length=MAX_DRIVE_PIECES, description="A driven step: the seconds of each piece of the "
        "interval from step k - 1 (pieces split at control changes; docs/guides/driven.md).")
    control: list[float] | None = Field(
        default=None, max_length=MAX_DRIVE_PIECES * MAX_CONTROLS, description="A driven step: the control held "
        "over each piece of dt, row by row (len(dt) rows of the model's control components).")
    jitter: Literal[(*family.MOVES.builtins(), names.OWN_ARM)] | None = Field(
        default=None, description="Preprocessed sets: the move the entity applies after resampling this set, "
                                  "the arm the system layer chose ('own': the run's own move of "
                                  "a user's code; absent: the run's own --jitter).")

    @classmethod
    def _expected_layer(cls, data: Any) -> Layer | None:
        kind = data.get("kind") if isinstance(data, dict) else None
        if not isinstance(kind, str):
            return None
        return {ParticleSetKind.PROPAGATED: Layer.ENTITY,
                ParticleSetKind.PREPROCESSED: Layer.INFORMATION}.get(kind)

    @model_validator(mode="after")
    def _check_preprocessing(self) -> "ParticleSetHeader":
        extras = [name for name in ("ps", "threshold", "n_large", "n_processed", "n_mixed", "n_plain", "jitter")
                  if getattr(self, name) is not None]
        if self.kind == ParticleSetKind.PROPAGATED and extras:
            raise ValueError(f"a propagated particle set carries no preprocessing fields, got {', '.join(extras)}")
        if self.kind == ParticleSetKind.PREPROCESSED and self.ps is None:
            raise ValueError("a preprocessed particle set must say which ps was used, got ps=None")
        if self.control is not None and (not self.dt or len(self.control) % len(self.dt)
                                         or len(self.control) // len(self.dt) > MAX_CONTROLS):
            raise ValueError(f"control must hold up to {MAX_CONTROLS} values per piece of dt, got "
                             f"{len(self.control)} values for {len(self.dt or [])} pieces")
        _check_counts(self, None)
        return self


class ParticleSet(ParticleSetHeader):
    """The particle set of one step: entity -> information (propagated) and back (preprocessed).

    Travels in the binary envelope of :mod:`dtpf.messages.codec`, not as JSON.
    ``particles`` is (N, d) float64, ``weights`` (N,) float64, normalised.
    Both are read-only, C-contiguous views; if the input already was float64
    and C-contiguous, they share its memory, so do not modify the input after
    construction.
    """

    particles: ParticlesArray = Field(description="(N, d) float64 particle states x_k^i.")
    weights: WeightsArray = Field(description="(N,) float64 normalised weights w_k^i, non-negative, summing to 1.")

    @model_validator(mode="after")
    def _check_lengths(self) -> "ParticleSet":
        _check_lengths(self, self.particles, self.weights)
        return self

    @classmethod
    def from_header(cls, header: ParticleSetHeader, particles: Any, weights: Any) -> "ParticleSet":
        """The set of an already validated ``header`` and two arrays, validating only what the header's
        validation did not: the arrays (the checks the constructor applies) and their lengths, against each
        other and the header's counts. What a decoder uses: the scalar fields are validated once.

        Raises ValueError naming the array (``particles: ...``) or the mismatch, as the constructor does.
        """
        if type(header) is not ParticleSetHeader:
            raise TypeError(f"header must be a ParticleSetHeader, got {type(header).__name__}")
        arrays = {}
        for name, check, value in (("particles", check_particles, particles), ("weights", check_weights, weights)):
            try:
                arrays[name] = _read_only(check(value))
            except ValueError as error:
                raise ValueError(f"{name}: Value error, {error}") from None
        try:
            _check_lengths(header, arrays["particles"], arrays["weights"])
        except ValueError as error:
            raise ValueError(f"Value error, {error}") from None
        # What ``model_construct`` makes of every field given (the header's, all set, and the arrays),
        # without its per-field loop: the header's fields are the set's fields but its arrays.
        message = cls.__new__(cls)
        _object_setattr(message, "__dict__", {**header.__dict__, **arrays})
        _object_setattr(message, "__pydantic_fields_set__", set(cls.__pydantic_fields__))
        _object_setattr(message, "__pydantic_extra__", None)
        _object_setattr(message, "__pydantic_private__", None)
        return message

    @property
    def n(self) -> int:
        """Number of particles N."""
        return self.weights.shape[0]

    @property
    def dim(self) -> int:
        """State dimension d."""
        return self.particles.shape[1]

    def __eq__(self, other: object) -> bool:
        # pydantic compares __dict__, which is ambiguous for arrays.
        if type(other) is not type(self):
            return NotImplemented
        for name in type(self).model_fields:
            mine, theirs = getattr(self, name), getattr(other, name)
            if isinstance(mine, np.ndarray):
                if mine.shape != theirs.shape or not np.array_equal(mine, theirs):
                    return False
            elif mine != theirs:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


class WeightState(Message):
    """Summary of the mirrored weights at one step: information -> system."""

    producer: ClassVar[Layer] = Layer.INFORMATION

    n: int = Field(ge=1, le=UINT32_MAX, description="Number of particles N.")
    ess: float = Field(ge=0.0, description="Effective sample size 1 / sum(w^2) (Eq. 25).")
    ess_ratio: float = Field(ge=0.0, description="ess / N.")
    entropy: float = Field(ge=0.0, description="Weight entropy -sum(w log w), in nats.")
    entropy_ratio: float = Field(ge=0.0, description="entropy / log N (1 when N = 1).")
    max_weight: float = Field(ge=0.0, le=1.0, description="Largest normalised weight.")
    threshold: float = Field(ge=0.0, le=1.0, description="Weight threshold W of Eq. 28.")
    n_above_threshold: Count = Field(description="Particles with weight > W.")
    distinct: int = Field(ge=1, le=UINT32_MAX, description="Number of distinct particles the set descends from "
                                                           "(distinct ancestors of the last resampling; "
                                                           "distinct states when that is unknown).")
    q10: float = Field(ge=0.0, le=1.0, description="10% quantile of the normalised weights.")
    q50: float = Field(ge=0.0, le=1.0, description="Median of the normalised weights.")
    q90: float = Field(ge=0.0, le=1.0, description="90% quantile of the normalised weights.")
    q99: float = Field(ge=0.0, le=1.0, description="99% quantile of the normalised weights.")
    ps: Annotated[float, _probability("ps")] = Field(description="PS in force at this step, in [0, 1].")
    n_large: Count | None = _count("n_large")
    n_processed: Count | None = _count("n_processed")
    n_mixed: Count | None = _count("n_mixed")
    n_plain: Count | None = _count("n_plain")

    @model_validator(mode="after")
    def _check_summary(self) -> "WeightState":
        for name in ("n_above_threshold", "distinct"):
            if getattr(self, name) > self.n:
                raise ValueError(f"{name} must be at most n={self.n}, got {getattr(self, name)}")
        quantiles = [("q10", self.q10), ("q50", self.q50), ("q90", self.q90), ("q99", self.q99),
                     ("max_weight", self.max_weight)]
        for (low_name, low), (high_name, high) in zip(quantiles, quantiles[1:]):
            if low > high:
                raise ValueError(f"weight quantiles must not decrease, got {low_name}={low!r} > {high_name}={high!r}")
        _check_counts(self, self.n)
        return self


class PSCommand(Message):
    """The PS to use from a given step on, and why: system -> information."""

    producer: ClassVar[Layer] = Layer.SYSTEM

    ps: Annotated[float, _probability("ps")] = Field(description="Preprocessing degree PS, in [0, 1].")
    applies_from_step: Count = Field(description="First filter step that uses this PS (>= step).")
    policy: str = Field(min_length=1, description="Name of the policy that chose the PS.")
    reason: str = Field(description="Why the PS was chosen or changed, in words.")
    preprocess: bool = Field(default=True, description="Whether the information layer preprocesses at all "
                             "from applies_from_step on; false: the entity's set is resampled as it is "
                             "(the system layer's decision 'off').")
    predicted_ess_ratio: float | None = Field(
        default=None, ge=0.0, description="ESS / N the policy predicts for the next step.")
    predicted_distinct_ratio: float | None = Field(
        default=None, ge=0.0, le=1.0, description="Distinct particles / N the policy predicts after resampling.")
    predicted_spread: float | None = Field(
        default=None, ge=0.0, description="Posterior standard deviation the policy predicts for the next step.")
    predicted_error: float | None = Field(
        default=None, ge=0.0, description="Squared estimation error the policy predicts with the chosen PS "
                                          "(over its simulated next steps).")
    surprise: float | None = Field(
        default=None, description="How much less likely this step's observation was than a typical one under "
                                  "the system layer's forecast, in nats (about 0 when typical).")
    evidence: float | None = Field(
        default=None, description="By how much preprocessing predicted the real observations of the last steps "
                                  "better than no preprocessing: the summed difference of predictive "
                                  "log-likelihoods, in nats (guard-observed policy); the choose policy: the "
                                  "chosen arm's evidence against plain resampling.")
    arm: Literal[names.ARMS] | None = Field(
        default=None, description="The move in force from applies_from_step on, chosen by the choose policy: "
                                  "plain, dt-relative, dt-paper (preprocessing by the information layer), "
                                  "roughening or regularised (by the entity after resampling).")

    @model_validator(mode="after")
    def _check_step(self) -> "PSCommand":
        if self.applies_from_step < self.step:
            raise ValueError(
                f"applies_from_step must be >= step, got applies_from_step={self.applies_from_step} < step={self.step}")
        return self


#: Largest state dimension whose estimate carries the covariances between its components (28 values).
MAX_COVARIANCE_DIM = 8


class Estimate(Message):
    """The state estimate of one step, after resampling: entity -> everyone."""

    producer: ClassVar[Layer] = Layer.ENTITY

    mean: list[float] = Field(min_length=1, description="(d,) weighted mean of the particles.")
    var: list[Annotated[float, Field(ge=0.0)]] = Field(min_length=1, description="(d,) weighted variance.")
    lower: list[float] = Field(min_length=1, description="(d,) lower end of the 95% interval.")
    upper: list[float] = Field(min_length=1, description="(d,) upper end of the 95% interval.")
    ess: float = Field(ge=0.0, description="Effective sample size before resampling.")
    ess_ratio: float = Field(ge=0.0, description="ess / N.")
    resampled: bool = Field(description="True if the particles were resampled at this step.")
    degraded: bool = Field(
        description="True if lockstep fell back to plain resampling (no preprocessed set in time).")
    truth: list[float] | None = Field(default=None, description="(d,) true state, when simulated.")
    observation: list[float] | None = Field(default=None, description="z_k used at this step.")
    ps: Annotated[float | None, _probability("ps")] = Field(
        default=None, description="PS of the preprocessed set that was resampled, if any.")
    log_predictive: float | None = Field(
        default=None, description="log p(z_k | z_1:k-1) of this step's observation under the filter, "
                                  "from the weights before normalisation: how well the filter predicts its "
                                  "data, the measure of a run without truth.")
    innovation: float | None = Field(
        default=None, ge=0.0, description="Normalised innovation squared of z_k (about the number of "
                                          "observed values when the filter is consistent), where the model "
                                          "gives the observation's moments.")
    sensor: SensorName | None = Field(default=None, description="The sensor z_k is from (a model with several "
                                                                "sensors).")
    covariance: list[float] | None = Field(
        default=None, description="(d(d-1)/2,) weighted covariances between the components, the pairs i < j "
                                  "row by row: (0, 1), (0, 2), ..., (1, 2), ...; given when 2 <= d <= "
                                  f"{MAX_COVARIANCE_DIM}.")

    @model_validator(mode="after")
    def _check_shapes(self) -> "Estimate":
        d = len(self.mean)
        for name in ("var", "lower", "upper", "truth"):
            values = getattr(self, name)
            if values is not None and len(values) != d:
                raise ValueError(f"{name} must have length d={len(self.mean)} like mean, got {len(values)}")
        if self.covariance is not None and len(self.covariance) != d * (d - 1) // 2:
            raise ValueError(f"covariance must hold d(d-1)/2 = {d * (d - 1) // 2} values (d={d}), "
                             f"got {len(self.covariance)}")
        for i, (low, high) in enumerate(zip(self.lower, self.upper)):
            if low > high:
                raise ValueError(f"lower must not exceed upper, got lower[{i}]={low!r} > upper[{i}]={high!r}")
        return self


#: Most steps ahead one published forecast carries.
MAX_FORECAST_HORIZON = 1000


class ForecastPoint(BaseModel):
    """One step of a forecast: the weighted moments and 95% band of the propagated set."""

    model_config = STRICT_CONFIG

    step: Count = Field(description="The step k + h this point forecasts.")
    mean: list[float] = Field(min_length=1, description="(d,) weighted mean of the propagated particles.")
    var: list[Annotated[float, Field(ge=0.0)]] = Field(min_length=1, description="(d,) weighted variance.")
    lower: list[float] = Field(min_length=1, description="(d,) 2.5% weighted quantile of each component.")
    upper: list[float] = Field(min_length=1, description="(d,) 97.5% weighted quantile of each component.")

    @model_validator(mode="after")
    def _check_shapes(self) -> "ForecastPoint":
        d = len(self.mean)
        for name in ("var", "lower", "upper"):
            if len(getattr(self, name)) != d:
                raise ValueError(f"{name} must have length d={d} like mean, got {len(getattr(self, name))}")
        for i, (low, high) in enumerate(zip(self.lower, self.upper)):
            if low > high:
                raise ValueError(f"lower must not exceed upper, got lower[{i}]={low!r} > upper[{i}]={high!r}")
        return self


class ForecastBand(Message):
    """The twin's forecast from the weighted set of ``step``, published each step (the entity's
    ``--forecast H``): entity -> everyone. The same numbers as a ``forecast`` question at that step
    (:mod:`dtpf.entity.forecast`)."""

    producer: ClassVar[Layer] = Layer.ENTITY

    ahead: list[ForecastPoint] = Field(min_length=1, max_length=MAX_FORECAST_HORIZON,
                                       description="Steps k + 1 .. k + H, in order, each of the same d.")

    @model_validator(mode="after")
    def _check_ahead(self) -> "ForecastBand":
        d = len(self.ahead[0].mean)
        for point in self.ahead:
            if len(point.mean) != d:
                raise ValueError(f"every point ahead must have d={d} components, got {len(point.mean)} at step "
                                 f"{point.step}")
        return self


class ObservationCounts(BaseModel):
    """What a live entity did with the observations that arrived (:class:`Status`)."""

    model_config = STRICT_CONFIG

    accepted: Count = Field(description="Observations that became filter steps.")
    duplicate: Count = Field(description="Rejected: the sequence number of the last accepted one again.")
    out_of_order: Count = Field(description="Rejected: a sequence number below the last accepted one "
                                            "(late, or from a sensor that started again from 1).")
    wrong_length: Count = Field(description="Rejected: not the model's number of observed values.")
    malformed: Count = Field(description="Rejected: not a valid Observation message (NaN values included).")
    missed: Count = Field(description="Sequence numbers skipped between accepted observations.")
    last_sequence: Count = Field(description="Sequence number of the last accepted observation (0: none yet).")
    late: Count = Field(default=0, description="Rejected: stamped before an observation already filtered, beyond "
                                               "the reorder window (a driven twin).")
    unknown_sensor: Count = Field(default=0, description="Rejected: from a sensor the model does not have.")
    controls: Count = Field(default=0, description="Controls taken (a driven twin).")
    controls_rejected: Count = Field(default=0, description="Controls rejected: the wrong number of values, a "
                                                            "sequence number or a stamp older than the last.")


#: Most kinds of rejection and keys a status lists (the rest are summed under "other").
MAX_STATUS_COUNTS = 101


class NamedCount(BaseModel):
    """One line of a tally: a name (a kind of rejection, a key expression) and how often."""

    model_config = STRICT_CONFIG

    name: str = Field(max_length=300, description="What was counted: a kind of rejection or a key expression.")
    count: Count = Field(description="How many times.")


class Component(BaseModel):
    """A user's code a run names (its model, resampler, move, threshold rule or policy), as a log keeps it so that
    a re-run can tell whether the code changed (:func:`dtpf.messages.family.component_records`)."""

    model_config = STRICT_CONFIG

    field: str = Field(max_length=32, pattern=r"^[a-z_]+$", description="The run configuration field that names "
                                                                       "it: model, resampler, jitter, threshold, policy.")
    reference: str = Field(max_length=4096, description="The reference as the run gives it (path/to/file.py:NAME, "
                                                        "package.module:NAME or an entry-point name).")
    sha256: str | None = Field(default=None, pattern=r"^[0-9a-f]{64}$",
                               description="SHA-256 of the file its code was loaded from, when one was found.")


#: Most components a status lists (one per field of the run configuration that may name code).
MAX_COMPONENTS = 8


class Status(Message):
    """Health of one layer process, published periodically and on change."""

    state: ServiceState = Field(description="'starting', 'running', 'finished' or 'failed'.")
    pid: Count = Field(description="Operating-system process id.")
    received: Count = Field(description="Messages received so far.")
    rejected: Count = Field(description="Messages rejected so far (failed to decode or out of order).")
    last_error: str | None = Field(default=None, description="Text of the last error, if any.")
    peers_alive: list[Layer] = Field(default_factory=list, description="Layers this process currently sees alive.")
    config_json: str | None = Field(
        default=None, max_length=65536,
        description="The run configuration this process runs (dtpf.messages.config.RunConfig as JSON), "
                    "so a log says how to re-run its layers.")
    detail: str | None = Field(default=None, max_length=1000,
                               description="What the process is doing or waiting for, in words.")
    components: list[Component] = Field(
        default_factory=list, max_length=MAX_COMPONENTS,
        description="The user's code the run names, with the SHA-256 of each file as this process found it.")
    observations: ObservationCounts | None = Field(
        default=None, description="A live entity's observation intake: accepted, rejected by reason, the "
                                  "last sequence number (a restarted sensor continues after it).")
    queued: Count = Field(default=0, description="Messages received but not yet handled (waiting in the "
                                                 "process's inboxes): a process that falls behind shows it here.")
    rejections: list[NamedCount] = Field(
        default_factory=list, max_length=MAX_STATUS_COUNTS,
        description="Rejected messages by kind of reason (the reason without its numbers), most first.")
    rejected_on: list[NamedCount] = Field(
        default_factory=list, max_length=MAX_STATUS_COUNTS,
        description="Rejected messages by the key expression they arrived on, most first.")


#: Validation context for base64 text a layer has just made with ``base64.b64encode`` (its own point
#: cloud or frame): ``PointCloud.model_validate(fields, context=BASE64_CHECKED)`` skips decoding it again
#: (the check costs several times the building of a cloud). Receivers never use it.
BASE64_CHECKED = {"base64_checked": True}


def base64_text(value: str, info: ValidationInfo) -> str:
    """``value`` if it is standard base64 (or was made so under :data:`BASE64_CHECKED`), else ValueError."""
    if info.context and info.context.get("base64_checked") is True and isinstance(value, str):
        return value
    if not is_base64(value):
        raise ValueError(f"data must be standard base64, got {value[:40]!r}...")
    return value


_BASE64_ALPHABET = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/"


def is_base64(value: str) -> bool:
    """Whether ``base64.b64decode(value, validate=True)`` takes ``value``, without decoding it.

    The alphabet is checked in one ``bytes.translate`` pass (7 times faster than decoding 43 KB); whether
    the padding fits depends only on how many characters come before it (mod 4, and whether there are
    any) and how many ``=`` end it (binascii's strict mode), so a short text with the same counts is decoded in its place.
    """
    try:
        text = value.encode("ascii")
    except (UnicodeEncodeError, AttributeError):
        return False
    data = text.rstrip(b"=")
    padding = len(text) - len(data)
    if data.translate(None, _BASE64_ALPHABET):
        return False
    n = len(data)
    try:  # three '=' or more are taken or refused alike
        base64.b64decode(b"A" * (n % 4 + (4 if n >= 4 else 0)) + b"=" * min(padding, 3), validate=True)
    except (binascii.Error, ValueError):
        return False
    return True


#: Longest observation vector a message may carry.
MAX_OBSERVATION_VALUES = 4096


class Observation(Message):
    """One measurement of the physical system: sensor -> entity.

    ``step`` is the sensor's sequence number (1, 2, ...: one more for every
    measurement), ``stamp`` the time of the measurement. ``end`` closes the
    stream: the entity finishes its run (``values`` may then be empty).
    ``sensor`` names the sensor of a model with several (each numbers its own
    measurements); a driven twin filters them in ``stamp`` order.
    """

    producer: ClassVar[Layer] = Layer.SENSOR

    values: list[float] = Field(max_length=MAX_OBSERVATION_VALUES,
                                description="z_k, the measured values (m of them, the model's obs_dim).")
    truth: list[float] | None = Field(default=None, max_length=MAX_OBSERVATION_VALUES,
                                      description="The true state, when the sensor is a simulation.")
    end: bool = Field(default=False, description="True on the last message of the stream: no more observations.")
    sensor: SensorName | None = Field(default=None, description="The sensor (a model's sensors); absent: the "
                                                                "model's one sensor.")

    @model_validator(mode="after")
    def _check_values(self) -> "Observation":
        if not self.end and not self.values:
            raise ValueError("an observation must carry at least one value (or end=true)")
        return self


class Control(Message):
    """The control input of a driven machine (wheel odometry, a commanded velocity): control source -> entity.

    ``step`` is the source's sequence number, ``stamp`` the time from which ``control`` is in force
    (zero-order hold until the next control; docs/guides/driven.md). ``end`` closes the control stream: a
    twin whose observations have ended takes what is held in stamp order once its controls have ended too
    (messages on two keys can overtake each other).
    """

    producer: ClassVar[Layer] = Layer.SENSOR

    control: list[float] = Field(default_factory=list, max_length=MAX_CONTROLS,
                                 description="u, the model's control components in the order of its controls.")
    end: bool = Field(default=False, description="True on the last message of the control stream.")

    @model_validator(mode="after")
    def _check_control(self) -> "Control":
        if not self.end and not self.control:
            raise ValueError("a control must carry at least one value (or end=true)")
        return self


#: Longest part of a rejected payload the recorder keeps (as base64 in :class:`Rejected`).
MAX_REJECTED_SAMPLE = 1024


class Rejected(Message):
    """A payload the recorder did not write to its channel because a service would reject it.

    The log records what the run is; this keeps a bounded sample of what else
    arrived, for forensics: where, why, how big, and its first bytes.
    """

    producer: ClassVar[Layer] = Layer.RECORDER

    key: str = Field(max_length=300, description="Key expression the payload arrived on (cut to 300 characters).")
    reason: str = Field(max_length=500, description="Why a service would reject it.")
    size: Count = Field(description="Size of the payload in bytes.")
    sample: Annotated[str, AfterValidator(base64_text)] = Field(
        max_length=4 * MAX_REJECTED_SAMPLE // 3 + 4, json_schema_extra={"contentEncoding": "base64"},
        description=f"The payload's first {MAX_REJECTED_SAMPLE} bytes, base64.")


class Missed(Message):
    """Messages the recorder missed and could not recover: a gap in one publisher's sequence that its cache
    (Zenoh's advanced publisher) no longer held when the recorder asked.

    Twin and run are those of the publisher's messages; ``step`` is the first step the gap may hold
    (``after_step + 1``, 0 when no message of the publisher was recorded before it). The steps lost are
    those after ``after_step`` and before ``before_step`` on ``key`` (a per-step topic loses them all; a
    status topic loses ``count`` statuses in that span).
    """

    producer: ClassVar[Layer] = Layer.RECORDER

    key: str = Field(max_length=300, description="Key expression of the missed messages (empty when unknown).")
    source: str = Field(max_length=300, description="The Zenoh publisher that sent them (its entity id).")
    count: Count = Field(description="How many messages of that publisher were missed.")
    after_step: Count | None = Field(default=None, description="Step of the last message of the publisher "
                                                               "recorded before the gap (None: none was).")
    before_step: Count | None = Field(default=None, description="Step of the first message of the publisher "
                                                                "recorded after the gap (None: none came).")
