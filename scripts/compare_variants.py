"""The variants of ``dtpf compare``: ``LABEL:FIELD=VALUE[,FIELD=VALUE...]`` read into run configurations.

A variant is a label and the :class:`~dtpf.messages.config.RunConfig` fields it changes in the base
run (the run options of the command)::

    variant = parse_variant("mine:model=path/to/file.py:Target,ros2_fields=point.x,point.y")
    variant.label, variant.fields      # "mine", {"model": "path/to/file.py:Target", "ros2_fields": "point.x,point.y"}
    variant.config(base, seed=3)       # the RunConfig of seed 3

The label ends at the first ':'; the rest is split on commas, and a piece is a new field only when it
reads ``NAME=...`` with NAME a field's name (so values may hold commas and colons); a field's value
begins after its first '='. ``none`` gives None. A mistake is a :class:`RunInputError` naming the variant.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass

from dtpf.messages.config import RunConfig, RunInputError

__all__ = ["Variant", "parse_variant", "settings_of"]

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_-]*$")
#: Fields a variant may not set: the seed is each run's own.
_PER_RUN = ("seed",)


@dataclass(frozen=True)
class Variant:
    """A label and the RunConfig fields (as text) it sets over the base run."""

    label: str
    fields: dict[str, str]

    @property
    def spec(self) -> str:
        """The fields as given, ``FIELD=VALUE,...`` (empty: the base run unchanged)."""
        return ",".join(f"{name}={value}" for name, value in self.fields.items())

    def config(self, base: RunConfig, seed: int) -> RunConfig:
        """The run of seed ``seed``: ``base`` with this variant's fields; RunInputError names the variant."""
        values = base.model_dump()
        values.update({name: _value(text) for name, text in self.fields.items()})
        values["seed"] = seed
        try:
            return RunConfig(**values)
        except RunInputError as error:
            raise RunInputError(f"variant {self.label!r}: {error}") from None


def parse_variant(text: str) -> Variant:
    """The variant of ``LABEL:FIELD=VALUE[,FIELD=VALUE...]`` (``LABEL`` or ``LABEL:`` alone: the base run)."""
    label, _, rest = text.partition(":")
    label = label.strip()
    if not label:
        raise RunInputError(f"variant {text!r}: no label (LABEL:FIELD=VALUE[,FIELD=VALUE...])")
    fields: dict[str, str] = {}
    current = None
    for piece in rest.split(",") if rest.strip() else []:
        name, equals, value = piece.partition("=")
        name = name.strip().replace("-", "_")
        if equals and _NAME.match(name):
            if name not in RunConfig.model_fields:
                raise RunInputError(f"variant {label!r}: unknown field {name!r} (fields: "
                                    f"{', '.join(f for f in RunConfig.model_fields if f not in _PER_RUN)})")
            if name in _PER_RUN:
                raise RunInputError(f"variant {label!r}: {name} is each run's own (--seeds or --seed-list)")
            if name in fields:
                raise RunInputError(f"variant {label!r}: {name} is given twice")
            fields[name] = value.strip()
            current = name
        elif current is not None:  # a comma inside the previous value
            fields[current] += "," + piece
        else:
            raise RunInputError(f"variant {label!r}: {piece.strip()!r} is not FIELD=VALUE "
                                f"(LABEL:FIELD=VALUE[,FIELD=VALUE...])")
    return Variant(label, fields)


def settings_of(config: RunConfig) -> str:
    """What a run is, but its seed: the fields that differ from RunConfig's defaults, as JSON."""
    defaults = RunConfig.model_fields
    values = {name: value for name, value in config.model_dump().items()
              if name not in _PER_RUN and value != defaults[name].default}
    return json.dumps(values, separators=(",", ":"))


def _value(text: str):
    """A field's value: None for ``none``, else the text (RunConfig converts numbers and booleans)."""
    return None if text.strip().lower() == "none" else text
