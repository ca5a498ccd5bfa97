"""Families of components a run names, each with one contract and one registry.

dtpf's filter is built from members of these families; a run configuration
names one member of each by a plain name or by a reference to the user's own
code (:mod:`dtpf.messages.references`)::

    ===============  ========================  ===========================  ==================
    family           option                    contract and built-ins       entry-point group
    ===============  ========================  ===========================  ==================
    resampler        --resampler               dtpf.entity.resamplers       dtpf.resamplers
    move             --jitter / --move         dtpf.entity.moves            dtpf.moves
    threshold rule   --threshold               dtpf.information.thresholds  dtpf.thresholds
    PS policy        --policy                  dtpf.system.policies         dtpf.policies
    reader           --reader                  dtpf.entity.readers          dtpf.readers
    ===============  ========================  ===========================  ==================

A family's package holds its contract in ``base.py`` and one module per
built-in member, which registers itself with the family's decorator::

    from dtpf.messages.family import RESAMPLERS

    @RESAMPLERS.builtin("systematic")
    def systematic(weights, rng, *, out=None, checked=False): ...

Adding a built-in is adding a module to the package: its name, the CLI's
help, the run configuration's validation and the names a log may carry are
read from the registry. A user's member (``path/to/file.py:NAME``,
``package.module:NAME``, or a name an installed package registers in the
family's entry-point group) goes through the contract's ``adapt(obj, where)``
in ``base.py``, which checks it on a small case and puts it in the family's
calling form; a mistake is one line (:class:`~dtpf.messages.references.ReferenceLoadError`).

The registry loads its members the way it loads a user's, by module name: the
wire contract names the families, never imports a layer statically.
Resolved members are cached per name or reference in each process.
"""
from __future__ import annotations

import importlib
import importlib.util
import pkgutil
import threading
from dataclasses import dataclass
from pathlib import Path

from dtpf.messages import references
from dtpf.messages.references import ReferenceLoadError

__all__ = ["Family", "Member", "component_records", "code_file", "CODE_FIELDS", "RESAMPLERS", "MOVES", "POLICIES",
           "THRESHOLDS", "READERS", "FAMILIES", "MAX_REFERENCE"]

#: The longest name or reference a run configuration or a message may carry.
MAX_REFERENCE = 4096
_FORMS = "path/to/file.py:NAME or package.module:NAME"


@dataclass(frozen=True)
class Member:
    """One resolved member of a family.

    ``name``: what the run names it by (a built-in name, an entry-point name or a reference); ``obj``: the
    member in its family's calling form; ``builtin``: one of dtpf's own; ``file`` and ``sha256``: the file
    its code was loaded from and the digest of that file's bytes (None for built-ins).
    """

    name: str
    obj: object
    builtin: bool
    file: str | None = None
    sha256: str | None = None

    def record(self) -> dict[str, str]:
        """What a log keeps of a user's member: its reference, file and digest (empty for a built-in)."""
        if self.builtin:
            return {}
        return {"reference": self.name, **({"file": self.file} if self.file else {}),
                **({"sha256": self.sha256} if self.sha256 else {})}


class Family:
    """A family of members: the built-ins of ``package`` (registered by :meth:`builtin`), the entry points of
    ``group``, and references to a user's code.

    Parameters
    ----------
    kind : str
        What a member is called in messages ("resampler", "PS policy").
    package : str
        The package that holds ``base.py`` (the contract, with ``adapt(obj, where)``) and the built-ins.
    group : str
        The entry-point group installed packages register members in.
    """

    def __init__(self, kind: str, package: str, group: str):
        self.kind, self.package, self.group = kind, package, group
        self._builtins: dict[str, object] = {}
        self._loaded = False
        self._resolved: dict[str, Member] = {}
        self._lock = threading.RLock()

    def __repr__(self) -> str:
        return f"Family({self.kind!r}, {self.package!r})"

    # --- built-ins ------------------------------------------------------------------------------------------

    def builtin(self, name: str):
        """Decorator: register the decorated function or class as the built-in member ``name`` (a class
        without a ``name`` of its own gets this one)."""
        def register(obj):
            if isinstance(obj, type) and "name" not in vars(obj):
                obj.name = name
            if name in self._builtins and self._builtins[name] is not obj:
                raise RuntimeError(f"two built-in {self.kind}s named {name!r}")
            self._builtins[name] = obj
            return obj
        return register

    def builtins(self) -> dict[str, object]:
        """The built-in members by name: every module of the package imported once (``base`` and ``_private``
        modules hold no member)."""
        with self._lock:
            if not self._loaded:
                package = importlib.import_module(self.package)
                for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name):
                    if not info.name.startswith("_") and info.name != "base":
                        importlib.import_module(f"{self.package}.{info.name}")
                self._loaded = True
            return dict(sorted(self._builtins.items()))

    def entry_points(self) -> dict:
        """Installed packages' members by name (a built-in's name cannot be taken)."""
        builtins = self.builtins()
        return {name: point for name, point in references.entry_points(self.group).items() if name not in builtins}

    def names(self) -> list[str]:
        """Every plain name a run may give: the built-ins, then the installed packages' (each sorted)."""
        return [*self.builtins(), *sorted(self.entry_points())]

    def summaries(self) -> dict[str, str]:
        """Each plain name with the first line of its member's docstring (an installed package's: its value)."""
        out = {name: _summary(obj) for name, obj in self.builtins().items()}
        out.update({name: f"from {point.value}" for name, point in sorted(self.entry_points().items())})
        return out

    def help(self, own: str, default) -> str:
        """The text of the option that names a member: every name with its summary, and how to give your own."""
        listed = "; ".join(f"'{name}' ({text})" if text else f"'{name}'" for name, text in self.summaries().items())
        return f"{listed}; or {own} as path/to/file.py:NAME or package.module:NAME (default: {default})"

    def trait(self, value: str, name: str, default=None, *, load: bool = True):
        """The attribute ``name`` of the member ``value`` names (a trait such as a policy's ``constant``);
        ``default`` if it has none, or, with ``load`` False, if the member is not a built-in."""
        builtins = self.builtins()
        if value in builtins:
            return getattr(builtins[value], name, default)
        if not load:
            return default
        return getattr(self.get(value), name, default)

    def contract(self):
        """The module holding the family's contract (``<package>.base``)."""
        return importlib.import_module(f"{self.package}.base")

    # --- checking a configuration ---------------------------------------------------------------------------

    def check_name(self, value) -> str:
        """``value`` if a run may name a member by it (a known name, or a well-formed reference), else a
        ValueError in one line that lists the names. The reference's code is not loaded here."""
        if not isinstance(value, str) or not value:
            raise ValueError(f"a {self.kind} is named by a string, got {value!r}")
        if len(value) > MAX_REFERENCE:
            raise ValueError(f"a {self.kind} reference is at most {MAX_REFERENCE} characters, got {len(value)}")
        if references.is_reference(value):
            source, _, attr = value.rpartition(":")
            if not source.strip() or not attr.strip():
                raise ValueError(f"{self.kind} reference {value!r} must be {_FORMS}")
            return value
        known = self.names()
        if value not in known:
            raise ValueError(f"unknown {self.kind} {value!r}; expected one of {', '.join(known)}, or your own: "
                             f"{_FORMS}")
        return value

    # --- resolving ------------------------------------------------------------------------------------------

    def resolve(self, value: str) -> Member:
        """The member ``value`` names, checked against the contract; the same object on every call.

        Raises :class:`~dtpf.messages.references.ReferenceLoadError` (one line) for an unknown name, code
        that cannot be loaded, or a member that breaks the contract.
        """
        with self._lock:
            member = self._resolved.get(value)
            if member is None:
                member = self._resolved[value] = self._resolve(value)
            return member

    def get(self, value: str):
        """The member ``value`` names, in the family's calling form (:meth:`resolve`'s ``obj``)."""
        return self.resolve(value).obj

    def _resolve(self, value: str) -> Member:
        try:
            self.check_name(value)
        except ValueError as error:
            raise ReferenceLoadError(str(error)) from None
        builtins = self.builtins()
        if value in builtins:
            return Member(value, builtins[value], builtin=True)
        contract = self.contract()
        if references.is_reference(value):
            where = f"{self.kind} {value!r}"
            obj, module = references.load(value, where, listing=getattr(contract, "listing", None))
        else:
            point = self.entry_points()[value]
            where = references.entry_point_where(value, point, self.group, self.kind)
            obj, module = references.load_entry_point(value, point, where,
                                                       listing=getattr(contract, "listing", None))
        adapted = contract.adapt(obj, where)
        if isinstance(adapted, type) and not isinstance(vars(adapted).get("name"), str):
            adapted.name = value  # a class's name on the wire and in the log: how the run named it
        path = references.origin_of(module)
        return Member(value, adapted, builtin=False, file=str(path) if path else None,
                      sha256=references.file_sha256(path) if path else None)

    def origin(self, value: str) -> Path | None:
        """The file a resolved member's code came from (None for a built-in)."""
        member = self.resolve(value)
        return Path(member.file) if member.file else None


def _summary(obj) -> str:
    """The first line of an object's docstring, without its trailing period."""
    doc = (getattr(obj, "__doc__", None) or "").strip()
    return doc.splitlines()[0].strip().rstrip(".").replace("``", "") if doc else ""


def code_file(reference: str, group: str | None = None) -> Path | None:
    """The file a reference's code lives in, found without importing it: ``path.py`` of ``path.py:NAME``
    (relative to the current directory), the module's file of ``package.module:NAME``, the module of an
    entry point of ``group`` for a plain name; None when none is found (a built-in, a missing file)."""
    if references.is_reference(reference):
        source = reference.rpartition(":")[0]
        if references.is_path(source):
            path = references.resolved_path(source)
            return path if path.is_file() else None
        module = source
    elif group is not None:
        point = references.entry_points(group).get(reference)
        if point is None:
            return None
        module = point.value.split(":")[0].strip()
        if references.is_path(module):
            path = references.resolved_path(module)
            return path if path.is_file() else None
    else:
        return None
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        return None
    origin = getattr(spec, "origin", None)
    return Path(origin) if origin and Path(origin).is_file() else None


#: The run configuration fields that may name a user's code, with the entry-point group of their plain names.
CODE_FIELDS = {"model": "dtpf.models", "resampler": "dtpf.resamplers", "jitter": "dtpf.moves",
               "threshold": "dtpf.thresholds", "policy": "dtpf.policies", "reader": "dtpf.readers"}


def component_records(config) -> list[dict]:
    """Each field of ``config`` that names code other than dtpf's own: ``{field, reference, sha256}``, the
    digest of the file as found now (None when no file is found). Built-in names give no record."""
    records = []
    for field, group in CODE_FIELDS.items():
        value = getattr(config, field, None)
        if not isinstance(value, str) or not value:
            continue
        if not references.is_reference(value):
            if value not in references.entry_points(group):
                continue  # a built-in (or a number, for the threshold)
            family = next((f for f in FAMILIES.values() if f.group == group), None)
            if family is not None and value in family.builtins():
                continue  # an installed package never replaces a built-in
        path = code_file(value, group)
        records.append({"field": field, "reference": value,
                        "sha256": references.file_sha256(path) if path is not None else None})
    return records


#: Traditional resampling schemes: ``ancestors = resample(weights, rng)`` (dtpf.entity.resamplers).
RESAMPLERS = Family("resampler", "dtpf.entity.resamplers", "dtpf.resamplers")
#: Moves after resampling: ``moved = move(resampled, particles, weights, rng)`` (dtpf.entity.moves).
MOVES = Family("move", "dtpf.entity.moves", "dtpf.moves")
#: Threshold rules for W of Eq. 28: ``W = rule(weights)`` (dtpf.information.thresholds).
THRESHOLDS = Family("threshold rule", "dtpf.information.thresholds", "dtpf.thresholds")
#: Observation readers: ``table = read(source)`` (dtpf.entity.readers).
READERS = Family("reader", "dtpf.entity.readers", "dtpf.readers")
#: PS policies of the system layer: classes deriving from PSPolicy (dtpf.system.policies).
POLICIES = Family("PS policy", "dtpf.system.policies", "dtpf.policies")

#: Every family by the RunConfig field that names its member.
FAMILIES = {"resampler": RESAMPLERS, "jitter": MOVES, "threshold": THRESHOLDS, "policy": POLICIES,
            "reader": READERS}
