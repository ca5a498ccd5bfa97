"""Model references: run the filter on a model of your own, without editing dtpf.

Wherever dtpf takes a model name, it takes a *reference* of one of four forms:

=================================  ===========================================
``ungm``                           a built-in model (:data:`dtpf.entity.models.MODELS`)
``cv-radar``                       a name an installed package registers in the
                                   entry-point group ``dtpf.models``
``mypkg.models:RADAR``             ``NAME`` in an importable module
``path/to/my_model.py:MyModel``    ``NAME`` in a Python file (relative paths are
                                   relative to the current directory)
=================================  ===========================================

``NAME`` (a dotted attribute path is allowed: ``models:Factory.build``) is a
:class:`~dtpf.entity.models.StateSpaceModel` instance, a subclass of it (built with
no arguments) or a zero-argument factory returning an instance. A reference
is a file path when the part before its last ``:`` ends with ``.py`` or
contains a ``/`` or ``\\``. A file is imported once per process, under a
module name derived from its resolved path, and its folder is appended to
``sys.path``: a file may import the helpers beside it (``from helpers import G``), while
dtpf's own packages and the installed ones keep their precedence.

The recommended import is::

    from dtpf.entity import model_ref
    model = model_ref.resolve("docs/examples/range_bearing.py:RangeBearingTarget")
    truth, observations = model.simulate(100, rng)

A package registers its models in ``pyproject.toml``::

    [project.entry-points."dtpf.models"]
    cv-radar = "mypkg.models:RADAR"

Every mistake is a :class:`ModelError` whose one-line message names the
reference and what is wrong with it. Resolved models are cached per reference
string: every call in one process returns the same object. A model without a
usable ``name`` is given the reference as its name.
"""
from __future__ import annotations

import importlib
import importlib.machinery
import importlib.metadata
import importlib.util
import inspect
import numbers
import re
import threading

from dtpf.entity import models
from dtpf.entity.models import StateSpaceModel
from dtpf.messages import references
from dtpf.messages.references import ReferenceLoadError

__all__ = ["ModelError", "resolve", "registered_names", "is_reference", "ENTRY_POINT_GROUP"]

#: The entry-point group installed packages register their models in.
ENTRY_POINT_GROUP = "dtpf.models"

#: Resolved models by reference string.
_CACHE: dict[str, StateSpaceModel] = {}
_LOCK = threading.RLock()

_FORMS = "a built-in name, a name registered under dtpf.models, package.module:NAME or path/to/file.py:NAME"
_MODULE_NAME = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")


class ModelError(ReferenceLoadError):
    """A model reference cannot be resolved, or the model it names is unusable (one-line message)."""



def is_reference(ref: str) -> bool:
    """Whether ``ref`` points to code (``module:NAME`` or ``file.py:NAME``) rather than naming a registered model."""
    return isinstance(ref, str) and ":" in ref


def registered_names() -> list[str]:
    """Names a plain reference can take: the built-in models and the entry points of ``dtpf.models``, sorted."""
    return sorted(set(models.MODELS) | set(_entry_points()))


def resolve(ref: str) -> StateSpaceModel:
    """The model a reference names; the same object on every call in this process.

    Parameters
    ----------
    ref : str
        A built-in name, an entry-point name, ``package.module:NAME`` or
        ``path/to/file.py:NAME`` (see the module docstring).

    Raises
    ------
    ModelError
        With a one-line message naming the reference and what is wrong.
    """
    if not isinstance(ref, str):
        raise ModelError(f"model reference must be a string, got {_a(ref)}")
    with _LOCK:
        model = _CACHE.get(ref)
        if model is None:
            model = _CACHE[ref] = _resolve(ref)
        return model


# --- the four forms ---------------------------------------------------------------------------------------

def _resolve(ref: str) -> StateSpaceModel:
    if not ref.strip():
        raise ModelError(f"model reference is empty; expected {_FORMS}")
    if not is_reference(ref):
        return _named(ref)
    source, _, attr = ref.rpartition(":")
    where = f"model reference {ref!r}"
    if _is_path(source):
        module, shown = _load_file(source, ref), source
    else:
        module, shown = _import(source, ref), f"module {source!r}"
    return _finish(_build(_attribute(module, attr, shown, where), attr, where, module), ref, where)


def _named(ref: str) -> StateSpaceModel:
    """A built-in name, else an entry point of dtpf.models."""
    if ref in models.MODELS:
        try:
            return _finish(models.get(ref), ref, f"built-in model {ref!r}")
        except ModelError:
            raise
        except Exception as exc:  # a lazy built-in (a factory) failing to build
            raise ModelError(f"built-in model {ref!r} could not be built: {_describe(exc)}") from exc
    points = _entry_points()
    if ref in points:
        return _from_entry_point(ref, points[ref])
    if ref.strip() != ref and ref.strip() in set(models.MODELS) | set(points):
        raise ModelError(f"unknown model {ref!r}: remove the spaces around {ref.strip()!r}")
    hint = ""
    if ref.endswith(".py") or "/" in ref or "\\" in ref:
        hint = f"; to load a model from a file, name it: {ref}:NAME"
    installed = ", ".join(sorted(points)) or "none installed"
    raise ModelError(f"unknown model {ref!r}; built-in: {', '.join(models.MODELS)}; "
                     f"registered under {ENTRY_POINT_GROUP}: {installed}; or write package.module:NAME "
                     f"or path/to/file.py:NAME{hint}")


def _from_entry_point(ref: str, point: importlib.metadata.EntryPoint) -> StateSpaceModel:
    where = references.entry_point_where(ref, point, ENTRY_POINT_GROUP, "model reference")
    obj, module = references.load_entry_point(ref, point, where, ModelError, listing=_listing)
    name = point.value.rpartition(":")[2].strip() if ":" in point.value else point.value.strip()
    return _finish(_build(obj, name, where, module), ref, where)


def _entry_points() -> dict[str, importlib.metadata.EntryPoint]:
    """Entry points of dtpf.models by name; an installed package can never replace a built-in."""
    return references.entry_points(ENTRY_POINT_GROUP)


# --- importing (dtpf.messages.references) -----------------------------------------------------------------

def _is_path(source: str) -> bool:
    return references.is_path(source)


def _import(module_name: str, ref: str, where: str | None = None):
    return references.import_module(module_name, where or f"model reference {ref!r}", ModelError)


def _load_file(source: str, ref: str, where: str | None = None):
    """Import a Python file once per process (its folder appended to sys.path: it may import modules beside it)."""
    return references.load_file(source, where or f"model reference {ref!r}", ModelError, noun="model file")


def _attribute(module, attr: str, shown: str, where: str):
    if not attr:
        raise ModelError(f"{where}: nothing after ':'; expected the NAME of a model in {shown}")
    return references.attribute(module, attr, shown, where, ModelError, listing=_listing)


def _listing(module) -> str:
    defined = _model_like(module)
    return f"it defines: {', '.join(defined)}" if defined else "it defines no StateSpaceModel instance or subclass"


def _model_like(module) -> list[str]:
    """Public names of a module that are StateSpaceModel instances or subclasses."""
    names = []
    for name, value in sorted(vars(module).items()):
        if name.startswith("_") or value is StateSpaceModel:
            continue
        if isinstance(value, StateSpaceModel) or (isinstance(value, type) and issubclass(value, StateSpaceModel)):
            names.append(name)
    return names


# --- building and checking the object ---------------------------------------------------------------------

_EXPECTED = "expected a StateSpaceModel instance, subclass or zero-argument factory"


def _build(obj, attr: str, where: str, module=None) -> StateSpaceModel:
    """An instance from an instance, a subclass or a zero-argument factory."""
    if isinstance(obj, StateSpaceModel):
        return obj
    if isinstance(obj, type):
        if not issubclass(obj, StateSpaceModel):
            raise ModelError(f"{where}: {attr} is a class that does not derive from StateSpaceModel, {_EXPECTED}")
        if inspect.isabstract(obj):
            missing = ", ".join(sorted(obj.__abstractmethods__))
            raise ModelError(f"{where}: {attr} cannot be instantiated: it does not implement the abstract "
                             f"method{'s' if len(obj.__abstractmethods__) > 1 else ''} {missing}")
        kind = "class"
    elif callable(obj) and not inspect.ismodule(obj):
        kind = "factory"
    else:
        raise ModelError(f"{where}: {attr} is {_a(obj)}, {_EXPECTED}")
    try:
        inspect.signature(obj).bind()
    except TypeError as exc:
        raise ModelError(f"{where}: {attr}() needs arguments ({exc}); give defaults or a zero-argument "
                         f"factory") from None
    except ValueError:  # no signature (some builtins): just call it
        pass
    path = getattr(module, "__file__", None)
    try:
        result = obj()
    except (Exception, SystemExit) as exc:
        raise ModelError(f"{where}: {attr}() raised {_describe(exc, path)}") from exc
    if kind == "factory" and not isinstance(result, StateSpaceModel):
        raise ModelError(f"{where}: {attr}() returned {_a(result)}, expected a StateSpaceModel instance")
    return result


def _finish(model: StateSpaceModel, ref: str, where: str) -> StateSpaceModel:
    """Give a nameless model the reference as its name; check dim and obs_dim."""
    try:
        name = getattr(model, "name", None)
    except Exception:
        name = None
    if not isinstance(name, str) or not name:
        try:
            object.__setattr__(model, "name", ref)
        except Exception:  # a read-only property or __slots__: leave it
            pass
    for attribute in ("dim", "obs_dim"):
        dimension(model, attribute, where)
    return model


def dimension(model, attribute: str, where: str) -> int:
    """``model.<attribute>`` as a positive int, or a ModelError naming it (shared with :mod:`dtpf.entity.model_check`)."""
    try:
        value = getattr(model, attribute)
    except AttributeError:
        raise ModelError(f"{where}: the model has no attribute {attribute}, expected a positive int") from None
    except Exception as exc:
        raise ModelError(f"{where}: reading {attribute} raised {_describe(exc)}") from exc
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ModelError(f"{where}: {attribute} is {value!r}, expected a positive int")
    return int(value)


# --- messages ---------------------------------------------------------------------------------------------

_first_line = references.first_line
_describe = references.describe
_pip_hint = references.pip_hint
_a = references.a
