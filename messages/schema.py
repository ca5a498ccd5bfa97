"""JSON Schema of the messages, in the subset Foxglove reads.

pydantic's schema uses ``$defs``/``$ref`` for nested models and enums and
``anyOf [X, null]`` for optional fields; Foxglove's JSON Schema reader accepts
neither (nor ``type: null``, nor arrays of arrays, nor a property without a
``type``). :func:`json_schema` rewrites the pydantic schema into that subset
and checks the result::

    from dtpf.messages.schema import json_schema
    schema = json_schema(WeightState)      # dict, ready for json.dumps

Rewrites: every ``$ref`` is replaced by a copy of its definition (sibling keys
such as ``description`` win) and ``$defs`` is dropped; ``anyOf [X, null]``
becomes X and the field leaves ``required``; ``default: null`` is dropped.
Anything else Foxglove cannot read raises ValueError naming the path.
"""
from __future__ import annotations

import copy
from typing import Any

from pydantic import BaseModel

#: Property types Foxglove's reader knows.
FOXGLOVE_TYPES = frozenset({"boolean", "string", "number", "integer", "object", "array"})
_REF_PREFIX = "#/$defs/"


def json_schema(cls: type[BaseModel]) -> dict:
    """The JSON Schema of ``cls``'s JSON form, post-processed for Foxglove.

    Raises
    ------
    ValueError
        If the model has a construct Foxglove cannot read (a union other than
        ``X | None``, arrays of arrays, bytes without standard base64, ...);
        the message names the path.
    """
    raw = cls.model_json_schema(mode="serialization")
    defs = raw.pop("$defs", {})
    schema = _rewrite(raw, defs, path=cls.__name__, seen=())
    problems = foxglove_problems(schema, path=cls.__name__)
    if problems:
        raise ValueError(f"JSON Schema of {cls.__name__} is not readable by Foxglove: " + "; ".join(problems))
    return schema


def _rewrite(node: Any, defs: dict, path: str, seen: tuple[str, ...]) -> Any:
    """Inline refs and collapse Optional, recursively; returns a new object."""
    if isinstance(node, list):
        return [_rewrite(item, defs, f"{path}[{i}]", seen) for i, item in enumerate(node)]
    if not isinstance(node, dict):
        return node
    node = dict(node)
    ref = node.pop("$ref", None)
    if ref is not None:
        name = ref[len(_REF_PREFIX):] if ref.startswith(_REF_PREFIX) else None
        if name not in defs:
            raise ValueError(f"{path}: cannot resolve $ref {ref!r}")
        if name in seen:
            raise ValueError(f"{path}: recursive model {name!r} cannot be inlined")
        target = _rewrite(copy.deepcopy(defs[name]), defs, path, seen + (name,))
        node = {**target, **node}
    any_of = node.pop("anyOf", None)
    if any_of is not None:
        alternatives = [alt for alt in any_of if alt != {"type": "null"}]
        if len(alternatives) != 1:
            raise ValueError(f"{path}: a union of {len(alternatives)} types (anyOf) is not readable by Foxglove")
        target = _rewrite(alternatives[0], defs, path, seen)
        node = {**target, **node}
    if isinstance(node.get("type"), list):
        types = [t for t in node["type"] if t != "null"]
        node["type"] = types[0] if len(types) == 1 else types
    if "default" in node and node["default"] is None:
        del node["default"]
    out = {}
    for key, value in node.items():
        if key == "properties":
            out[key] = {name: _rewrite(sub, defs, f"{path}.{name}", seen) for name, sub in value.items()}
        else:
            out[key] = _rewrite(value, defs, f"{path}.{key}", seen)
    if "required" in out and "properties" in node:
        out["required"] = [name for name in out["required"] if not _nullable(node["properties"].get(name, {}))]
        if not out["required"]:
            del out["required"]
    return out


def _nullable(prop: dict) -> bool:
    """True if a raw pydantic property admits null."""
    if any(alt == {"type": "null"} for alt in prop.get("anyOf", ())):
        return True
    types = prop.get("type")
    return isinstance(types, list) and "null" in types


def foxglove_problems(schema: Any, path: str = "$") -> list[str]:
    """Every construct in ``schema`` that Foxglove's JSON Schema reader rejects.

    Returns a list of "path: problem" strings; empty means readable.
    """
    problems: list[str] = []
    if not isinstance(schema, dict) or schema.get("type") != "object":
        return [f"{path}: the root must be an object schema"]
    _check_object(schema, path, problems)
    _check_banned(schema, path, problems)
    return problems


def _check_object(schema: dict, path: str, problems: list[str]) -> None:
    properties = schema.get("properties")
    if not isinstance(properties, dict):
        problems.append(f"{path}: an object needs 'properties'")
        return
    for name, prop in properties.items():
        _check_property(prop, f"{path}.{name}", problems, in_array=False)


def _check_property(prop: Any, path: str, problems: list[str], in_array: bool) -> None:
    if not isinstance(prop, dict):
        problems.append(f"{path}: schema must be an object")
        return
    kind = prop.get("type")
    if kind not in FOXGLOVE_TYPES:
        problems.append(f"{path}: type {kind!r} is not one of {sorted(FOXGLOVE_TYPES)}")
    elif kind == "object":
        _check_object(prop, path, problems)
    elif kind == "array":
        if in_array:
            problems.append(f"{path}: arrays of arrays are not readable by Foxglove")
        else:
            _check_property(prop.get("items"), f"{path}[]", problems, in_array=True)
    elif kind == "string" and prop.get("format") in ("binary", "base64url"):
        problems.append(f"{path}: bytes must be standard base64 with contentEncoding 'base64'")


def _check_banned(node: Any, path: str, problems: list[str]) -> None:
    """Keywords and values Foxglove rejects, wherever they appear."""
    if isinstance(node, list):
        for i, item in enumerate(node):
            _check_banned(item, f"{path}[{i}]", problems)
        return
    if not isinstance(node, dict):
        return
    for key in ("$ref", "$defs", "anyOf", "allOf", "oneOf"):
        if key in node:
            problems.append(f"{path}: '{key}' is not readable by Foxglove")
    if node.get("type") == "null" or (isinstance(node.get("type"), list) and "null" in node["type"]):
        problems.append(f"{path}: type null is not readable by Foxglove")
    for key, value in node.items():
        if key in ("properties",):
            for name, sub in value.items():
                _check_banned(sub, f"{path}.{name}", problems)
        elif isinstance(value, (dict, list)):
            _check_banned(value, f"{path}.{key}", problems)
