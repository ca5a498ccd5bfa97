"""What a twin can be asked over Zenoh queries: the keys, the selectors, the bounds.

Three questions, each a Zenoh queryable on the twin's key space::

    dtpf/<twin>/entity/state?particles=true            the latest estimate (and its particle set)
    dtpf/<twin>/entity/forecast?horizon=20             the particle set propagated 20 steps ahead
    dtpf/<twin>/entity/forecast?horizon_s=2;dt=0.1     a driven twin's, 2 seconds ahead in steps of 0.1 s
    dtpf/<twin>/recorder/history?steps=10:20;topics=entity/estimate   the record of steps 10 .. 20

A selector's parameters are ``name=value`` pairs separated by ``;`` (Zenoh's
form) or ``&``. :func:`parse` reads them for one kind of question and gives a
frozen selector, or raises :class:`SelectorError` with one line naming what
is wrong; anything may arrive (any text, any size), so the text, the number
of parameters and every value are bounded before use. The service names the
bound an answer would break instead of answering more than it carries::

    from dtpf.messages import queries
    queries.parse("history", "steps=3:5;topics=entity/estimate")
    # HistorySelector(steps=(3, 5), time=None, topics=('entity/estimate',), limit=1000, max_bytes=4194304)
    queries.parameters_text(steps="3:5")   # 'steps=3:5', what a client sends

The answers are JSON (:mod:`dtpf.scripts.logs.history`, :mod:`dtpf.entity.answers`).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

from dtpf.messages.errors import DtpfError
from dtpf.messages.models import check_id

__all__ = ["KINDS", "SelectorError", "StateSelector", "ForecastSelector", "HistorySelector", "parse", "key",
           "parameters_text", "check_size", "check_values", "DEFAULT_LIMIT", "MAX_LIMIT", "DEFAULT_MAX_BYTES", "MAX_BYTES", "MAX_HORIZON",
           "MAX_FORECAST_WORK", "MAX_SELECTOR_TEXT"]

#: The questions, and the layer whose key space answers each.
KINDS = {"state": "entity", "forecast": "entity", "history": "recorder"}
#: Longest parameter text read (characters); more is refused unread.
MAX_SELECTOR_TEXT = 2048
#: Most parameters one selector may carry.
MAX_PARAMETERS = 16
#: Messages one history answer carries unless the selector says ``limit=`` (and at most ``MAX_LIMIT``).
DEFAULT_LIMIT = 1000
MAX_LIMIT = 100_000
#: Bytes of JSON one answer carries unless the selector says ``max_bytes=`` (and at most ``MAX_BYTES``).
DEFAULT_MAX_BYTES = 4 << 20
MAX_BYTES = 64 << 20
#: Most steps a forecast looks ahead, and most particle-steps (N x horizon) one forecast propagates.
MAX_HORIZON = 1000
MAX_FORECAST_WORK = 5_000_000
#: Most topics a history selector names, and most control components a forecast's plan holds.
MAX_TOPICS = 16
MAX_CONTROLS = 64
DEFAULT_TOPICS = ("entity/estimate",)
_TOPIC = re.compile(r"^[A-Za-z0-9_.*/-]{1,200}$")
_TRUE, _FALSE = ("true", "1", "yes", ""), ("false", "0", "no")


class SelectorError(DtpfError, ValueError):
    """A selector that cannot be answered; the text names the parameter and what is wrong, in one line."""


@dataclass(frozen=True)
class StateSelector:
    """``state``: the latest estimate; ``particles``: with the particle set it was made from; at most
    ``max_bytes`` bytes of JSON."""

    particles: bool = False
    max_bytes: int = DEFAULT_MAX_BYTES


@dataclass(frozen=True)
class ForecastSelector:
    """``forecast``: the latest particle set propagated ``horizon`` steps without observations.

    ``dt`` (seconds a step) and ``control`` (the control held over the horizon, a what-if) are for a
    driven model; ``horizon_s``: a horizon in seconds instead of steps (steps of ``dt``, which it needs, the
    last one shorter); ``particles``: the propagated set of the last step too; at most ``max_bytes`` bytes
    of JSON.
    """

    horizon: int = 10
    dt: float | None = None
    horizon_s: float | None = None
    control: tuple[float, ...] | None = None
    particles: bool = False
    max_bytes: int = DEFAULT_MAX_BYTES


@dataclass(frozen=True)
class HistorySelector:
    """``history``: the recorded messages of ``steps`` (first, last; None: open) and ``time`` (first, last
    log time in ns; None: open) on ``topics`` (globs or suffixes, as ``dtpf cat --topics``), at most
    ``limit`` messages and ``max_bytes`` bytes of JSON."""

    steps: tuple[int, int | None] | None = None
    time: tuple[int | None, int | None] | None = None
    topics: tuple[str, ...] = DEFAULT_TOPICS
    limit: int = DEFAULT_LIMIT
    max_bytes: int = DEFAULT_MAX_BYTES

    def holds_step(self, step: int) -> bool:
        if self.steps is None:
            return True
        first, last = self.steps
        return first <= step and (last is None or step <= last)

    def holds_time(self, log_time: int) -> bool:
        if self.time is None:
            return True
        first, last = self.time
        return (first is None or first <= log_time) and (last is None or log_time <= last)


#: The parameters each kind takes.
_NAMES = {
    "state": ("particles", "max_bytes"),
    "forecast": ("horizon", "horizon_s", "dt", "control", "particles", "max_bytes"),
    "history": ("steps", "time", "topics", "particles", "limit", "max_bytes"),
}


def key(twin: str, kind: str) -> str:
    """The key expression of a question about one twin: ``dtpf/<twin>/<layer>/<kind>``."""
    if kind not in KINDS:
        raise SelectorError(f"unknown question {kind!r}; expected one of {', '.join(KINDS)}")
    return f"dtpf/{check_id(twin, 'twin id')}/{KINDS[kind]}/{kind}"


def parameters_text(**values) -> str:
    """The parameter text of a selector (``name=value;...``) from keyword values; None values left out,
    booleans as true/false, sequences joined by commas."""
    parts = []
    for name, value in values.items():
        if value is None or value is False:
            continue
        if value is True:
            value = "true"
        elif isinstance(value, (list, tuple)):
            value = ",".join(str(v) for v in value)
        parts.append(f"{name}={value}")
    return ";".join(parts)


def split(text) -> dict[str, str]:
    """The ``name=value`` pairs of a parameter text; SelectorError on a text too long, too many pairs, a
    repeated or empty name."""
    if text is None:
        return {}
    if not isinstance(text, str):
        raise SelectorError(f"selector parameters must be text, got {type(text).__name__}")
    if len(text) > MAX_SELECTOR_TEXT:
        raise SelectorError(f"selector parameters of {len(text)} characters; at most {MAX_SELECTOR_TEXT}")
    pairs: dict[str, str] = {}
    for part in re.split(r"[;&]", text):
        if not part:
            continue
        name, _, value = part.partition("=")
        name = name.strip()
        if not name:
            raise SelectorError(f"selector parameter without a name: {_shown(part)}")
        if name in pairs:
            raise SelectorError(f"selector parameter {_shown(name)} given twice")
        pairs[name] = value.strip()
        if len(pairs) > MAX_PARAMETERS:
            raise SelectorError(f"more than {MAX_PARAMETERS} selector parameters")
    return pairs


def parse(kind: str, text) -> StateSelector | ForecastSelector | HistorySelector:
    """The selector of a ``kind`` question from its parameter text; SelectorError names what is wrong."""
    if kind not in _NAMES:
        raise SelectorError(f"unknown question {kind!r}; expected one of {', '.join(KINDS)}")
    pairs = split(text)
    unknown = [name for name in pairs if name not in _NAMES[kind]]
    if unknown:
        raise SelectorError(f"unknown {kind} parameter {_shown(unknown[0])}; expected "
                            f"{', '.join(_NAMES[kind])}")
    if kind == "state":
        return StateSelector(particles=_flag(pairs, "particles"), max_bytes=_max_bytes(pairs))
    if kind == "forecast":
        horizon = _integer(pairs, "horizon", ForecastSelector.horizon, 1, MAX_HORIZON)
        dt = _number(pairs["dt"], "dt") if "dt" in pairs else None
        if dt is not None and dt < 0:
            raise SelectorError(f"dt must be seconds >= 0, got {_shown(pairs['dt'])}")
        control = _numbers(pairs["control"], "control", MAX_CONTROLS) if "control" in pairs else None
        horizon_s = None
        if "horizon_s" in pairs:
            if "horizon" in pairs:
                raise SelectorError("give horizon= (steps) or horizon_s= (seconds), not both")
            horizon_s = _number(pairs["horizon_s"], "horizon_s")
            if horizon_s <= 0:
                raise SelectorError(f"horizon_s must be seconds > 0, got {_shown(pairs['horizon_s'])}")
            if not dt:
                raise SelectorError("horizon_s= needs dt= (seconds a forecast step, > 0)")
            horizon = math.ceil(horizon_s / dt - 1e-9)
            if horizon > MAX_HORIZON:
                raise SelectorError(f"horizon_s={horizon_s:g} in steps of dt={dt:g} is {horizon} steps; at most "
                                    f"{MAX_HORIZON}: raise dt= or shorten horizon_s=")
        return ForecastSelector(horizon=horizon, dt=dt, horizon_s=horizon_s, control=control,
                                particles=_flag(pairs, "particles"), max_bytes=_max_bytes(pairs))
    topics = _topics(pairs.get("topics"))
    if _flag(pairs, "particles") and "entity/particles" not in topics:
        topics = (*topics, "entity/particles")
    return HistorySelector(steps=_steps(pairs.get("steps")), time=_times(pairs.get("time")), topics=topics,
                           limit=_integer(pairs, "limit", DEFAULT_LIMIT, 1, MAX_LIMIT),
                           max_bytes=_max_bytes(pairs))


def check_size(body: bytes, max_bytes: int) -> bytes:
    """``body`` if it is at most ``max_bytes`` long; else SelectorError naming the bound."""
    if len(body) > max_bytes:
        raise SelectorError(f"the answer is {len(body)} bytes of JSON, more than max_bytes={max_bytes} (at most "
                            f"{MAX_BYTES}); ask without particles=true, or raise max_bytes=")
    return body


#: The fewest bytes one float takes in a JSON array ("0.0,"): what an answer's numbers weigh at the least.
MIN_JSON_FLOAT_BYTES = 4


def check_values(count: int, max_bytes: int) -> None:
    """SelectorError, before the answer is built, when ``count`` numbers in JSON cannot fit in ``max_bytes``
    (a particle set asked of a twin of a million particles is refused without turning it into a list first)."""
    least = count * MIN_JSON_FLOAT_BYTES
    if least > max_bytes:
        raise SelectorError(f"the answer holds {count} numbers, at least {least} bytes of JSON, more than "
                            f"max_bytes={max_bytes} (at most {MAX_BYTES}); ask without particles=true, or raise "
                            f"max_bytes=")


def _max_bytes(pairs: dict) -> int:
    return _integer(pairs, "max_bytes", DEFAULT_MAX_BYTES, 1, MAX_BYTES)


def _shown(text: str, most: int = 40) -> str:
    text = repr(text)
    return text if len(text) <= most else text[:most - 4] + "...'"


def _flag(pairs: dict, name: str) -> bool:
    if name not in pairs:
        return False
    value = pairs[name].lower()
    if value in _TRUE:
        return True
    if value in _FALSE:
        return False
    raise SelectorError(f"{name} must be true or false, got {_shown(pairs[name])}")


def _integer(pairs: dict, name: str, default: int, low: int, high: int) -> int:
    if name not in pairs:
        return default
    text = pairs[name]
    if not re.fullmatch(r"[0-9]{1,12}", text):
        raise SelectorError(f"{name} must be an integer in {low} .. {high}, got {_shown(text)}")
    value = int(text)
    if not low <= value <= high:
        raise SelectorError(f"{name}={value} is out of bounds: at most {high}" if value > high
                            else f"{name}={value} is out of bounds: at least {low}")
    return value


def _number(text: str, name: str) -> float:
    if len(text) > 40:
        raise SelectorError(f"{name} must be a number, got {_shown(text)}")
    try:
        value = float(text)
    except ValueError:
        raise SelectorError(f"{name} must be a number, got {_shown(text)}") from None
    if not math.isfinite(value):
        raise SelectorError(f"{name} must be a finite number, got {_shown(text)}")
    return value


def _numbers(text: str, name: str, most: int) -> tuple[float, ...]:
    parts = [part for part in text.split(",")]
    if len(parts) > most:
        raise SelectorError(f"{name} holds more than {most} values")
    return tuple(_number(part.strip(), name) for part in parts)


def _steps(text: str | None) -> tuple[int, int | None] | None:
    """``A:B``, ``A:``, ``:B`` or ``K``: steps A .. B, both included (as ``dtpf cat --steps``)."""
    if text is None:
        return None
    first, sep, last = text.partition(":")
    if not re.fullmatch(r"[0-9]{0,12}", first) or not re.fullmatch(r"[0-9]{0,12}", last) or \
            (not sep and not first):
        raise SelectorError(f"steps must be A:B, A:, :B or K (integers), got {_shown(text)}")
    low = int(first) if first else 0
    high = (int(last) if last else None) if sep else low
    if high is not None and high < low:
        raise SelectorError(f"steps {_shown(text)}: need A <= B")
    return low, high


def _times(text: str | None) -> tuple[int | None, int | None] | None:
    """``T0:T1`` in seconds since the Unix epoch (either end may be left out): log times in ns."""
    if text is None:
        return None
    first, sep, last = text.partition(":")
    if not sep or (not first and not last):
        raise SelectorError(f"time must be T0:T1, T0: or :T1 (seconds since the Unix epoch), got {_shown(text)}")
    low = round(_number(first, "time") * 1e9) if first else None
    high = round(_number(last, "time") * 1e9) if last else None
    if low is not None and high is not None and high < low:
        raise SelectorError(f"time {_shown(text)}: need T0 <= T1")
    return low, high


def _topics(text: str | None) -> tuple[str, ...]:
    if text is None or text == "":
        return DEFAULT_TOPICS
    topics = tuple(topic.strip() for topic in re.split(r"[,|]", text) if topic.strip())
    if len(topics) > MAX_TOPICS:
        raise SelectorError(f"topics names more than {MAX_TOPICS} topics")
    for topic in topics:
        if not _TOPIC.match(topic):
            raise SelectorError(f"topics: {_shown(topic)} is no topic (a glob or a suffix such as entity/estimate)")
    return topics or DEFAULT_TOPICS
