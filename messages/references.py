"""References to code: how dtpf finds a user's model, resampler, move, rule, policy or reader.

A reference names a Python object in one of three ways::

    package.module:NAME            NAME in an importable module
    path/to/file.py:NAME           NAME in a Python file (relative to the current directory)
    NAME                           a name an installed package registers in an entry-point group

``NAME`` may be a dotted attribute path (``models:Factory.build``). A reference
is a file path when the part before its last ``:`` ends with ``.py`` or contains
``/`` or ``\\``. A file is imported once per process, under a module name made
from its resolved path, and its folder is appended to ``sys.path``: a file may
import the modules beside it (``from helpers import G``), while dtpf's own
packages and the installed ones keep their precedence (the folder comes last,
and no process dtpf starts puts the working directory on its path).

Every mistake raises :class:`ReferenceLoadError` (or the subclass a caller
passes as ``error``), a :class:`~dtpf.messages.errors.RunInputError` with a
one-line message naming the reference and what is wrong.
:func:`file_sha256` gives the digest a log records beside a reference, so a
later re-run can tell whether the code changed.
"""
from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import inspect
import importlib.metadata
import importlib.util
import os
import re
import sys
import threading
import traceback
from pathlib import Path

from dtpf.messages.errors import RunInputError

__all__ = ["ReferenceLoadError", "is_reference", "is_path", "import_module", "load_file", "attribute",
           "entry_points", "load_entry_point", "file_sha256", "function_of", "Signature", "origin_of", "describe", "first_line"]

_MODULE_NAME = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")
_LOCK = threading.RLock()


class ReferenceLoadError(RunInputError):
    """A reference cannot be resolved, or what it names breaks its family's contract (one-line message)."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()) if "\n" in str(message) else str(message))


def is_reference(ref) -> bool:
    """Whether ``ref`` points to code (``module:NAME`` or ``file.py:NAME``) rather than naming a registered member."""
    return isinstance(ref, str) and ":" in ref


def is_path(source: str) -> bool:
    """Whether the part of a reference before its ``:`` is a file path rather than a module name."""
    return source.endswith(".py") or "/" in source or "\\" in source


def import_module(module_name: str, where: str, error: type[ReferenceLoadError] = ReferenceLoadError):
    """The module ``module_name``; ``where`` names the reference in the error."""
    if not _MODULE_NAME.match(module_name):
        raise error(f"{where}: {module_name!r} is neither a module name (package.module) nor a path to a .py file")
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = exc.name or ""
        if missing and (module_name == missing or module_name.startswith(missing + ".")):
            hint = ""
            if missing == module_name.split(".")[0]:
                hint = (f" (is the package installed? pip install {missing}; for a module of your own, "
                        f"add its folder to PYTHONPATH or write path/to/{module_name.replace('.', '/')}.py:NAME)")
            raise error(f"cannot import module {module_name!r} of {where}: {first_line(exc)}{hint}") from exc
        raise error(f"{where}: importing module {module_name!r} raised {describe(exc)}{pip_hint(exc)}") from exc
    except (Exception, SystemExit) as exc:
        raise error(f"{where}: importing module {module_name!r} raised {describe(exc)}") from exc


def resolved_path(source: str) -> Path:
    path = Path(os.path.expanduser(source))
    if not path.is_absolute():
        path = Path.cwd() / path
    return path.resolve()


def load_file(source: str, where: str, error: type[ReferenceLoadError] = ReferenceLoadError, *,
              noun: str = "file"):
    """Import the Python file ``source`` once per process, as a module named after its resolved path.

    Its folder is appended to ``sys.path`` (once), so the file may import the modules beside it; anything
    of the same name on the path before it (dtpf, the standard library, installed packages) wins.
    """
    path = resolved_path(source)
    if not path.exists():
        raise error(f"{where}: {noun} {source!r} not found (looked for {path})")
    if not path.is_file():
        raise error(f"{where}: {source!r} is not a file ({path})")
    digest = hashlib.sha1(str(path).encode()).hexdigest()[:12]
    stem = re.sub(r"\W", "_", path.stem) or "model"
    module_name = f"_dtpf_model_{stem}_{digest}"
    with _LOCK:
        module = sys.modules.get(module_name)
        if module is not None:
            return module
        folder = str(path.parent)
        if folder not in sys.path:
            sys.path.append(folder)
        loader = importlib.machinery.SourceFileLoader(module_name, str(path))
        spec = importlib.util.spec_from_file_location(module_name, path, loader=loader)
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module  # before exec: dataclasses and pickle look the module up
        try:
            spec.loader.exec_module(module)
        except (Exception, SystemExit) as exc:
            del sys.modules[module_name]
            raise error(f"{where}: importing {source} raised {describe(exc, path)}{pip_hint(exc)}") from exc
        return module


def attribute(module, attr: str, shown: str, where: str, error: type[ReferenceLoadError] = ReferenceLoadError,
              listing=None):
    """``module``'s attribute at the dotted path ``attr``; ``listing(module)``: what the module does define,
    for the error when the first name is missing."""
    if not attr:
        raise error(f"{where}: nothing after ':'; expected a NAME in {shown}")
    obj = module
    for i, part in enumerate(attr.split(".")):
        if not part.isidentifier():
            raise error(f"{where}: {attr!r} is not a Python name")
        try:
            obj = getattr(obj, part)
        except AttributeError:
            if i == 0:
                defined = listing(module) if listing is not None else None
                raise error(f"{where}: {shown} has no attribute {part!r}{'; ' + defined if defined else ''}") \
                    from None
            raise error(f"{where}: {'.'.join(attr.split('.')[:i])} has no attribute {part!r}") from None
        except Exception as exc:  # a property or module __getattr__ raising
            raise error(f"{where}: reading {attr} raised {describe(exc)}") from exc
    return obj


def load(ref: str, where: str, error: type[ReferenceLoadError] = ReferenceLoadError, *, listing=None,
         noun: str = "file"):
    """``(object, module)`` of a ``module:NAME`` or ``file.py:NAME`` reference."""
    source, _, attr = ref.rpartition(":")
    if is_path(source):
        module, shown = load_file(source, where, error, noun=noun), source
    else:
        module, shown = import_module(source, where, error), f"module {source!r}"
    return attribute(module, attr, shown, where, error, listing), module


class Signature:
    """The parameters of a user's function, as :func:`function_of` found them (none when it has no signature)."""

    def __init__(self, parameters):
        self.parameters = dict(parameters)

    def takes(self, keyword: str) -> bool:
        """Whether the function accepts ``keyword=...`` (by name or through ``**kwargs``); False if unknown."""
        return keyword in self.parameters or any(p.kind == p.VAR_KEYWORD for p in self.parameters.values())


def function_of(obj, where: str, noun: str, form: str, arguments: tuple[str, ...],
                error: type[ReferenceLoadError] = ReferenceLoadError) -> Signature:
    """The signature of ``obj`` if it is a function that can be called with the positional ``arguments``
    (``noun``, ``form``: what a family calls a member and how it writes its contract, for the error), else one
    line naming what is wrong."""
    if isinstance(obj, type) or not callable(obj):
        raise error(f"{where}: expected a function {form}, got "
                    f"{'the class ' + obj.__name__ if isinstance(obj, type) else a(obj)}")
    try:
        parameters = inspect.signature(obj).parameters
    except (TypeError, ValueError):  # no signature (some builtins): called as the contract says
        return Signature({})
    kinds = [p.kind for p in parameters.values()]
    positional = [p for p in parameters.values() if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    required = [p for p in parameters.values() if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL,
                                                                                            p.VAR_KEYWORD)]
    if len(required) > len(arguments) or (len(positional) < len(arguments)
                                          and inspect.Parameter.VAR_POSITIONAL not in kinds):
        raise error(f"{where}: {noun} takes ({', '.join(arguments)}), got the parameters ({', '.join(parameters)})")
    return Signature(parameters)


def entry_points(group: str) -> dict[str, importlib.metadata.EntryPoint]:
    """The entry points of ``group`` by name (the first of a name wins); none when the metadata is unreadable."""
    found: dict[str, importlib.metadata.EntryPoint] = {}
    try:
        selected = importlib.metadata.entry_points(group=group)
    except Exception:  # a broken metadata folder somewhere on sys.path must not stop dtpf
        return found
    for point in selected:
        found.setdefault(point.name, point)
    return found


def entry_point_where(name: str, point: importlib.metadata.EntryPoint, group: str, kind: str) -> str:
    """How an error names an entry point: the reference, its value, group and package."""
    dist = getattr(getattr(point, "dist", None), "name", None)
    return f"{kind} {name!r} (entry point {point.value!r} of {group}{f' from package {dist!r}' if dist else ''})"


def load_entry_point(name: str, point: importlib.metadata.EntryPoint, where: str,
                     error: type[ReferenceLoadError] = ReferenceLoadError, *, listing=None):
    """``(object, module)`` an entry point names (``module:attr``, a file path, or a whole module)."""
    value = re.sub(r"\s*\[[^\]]*\]\s*$", "", point.value).strip()  # drop old-style [extras]
    module_name, _, attr = value.rpartition(":") if ":" in value else (value, "", "")
    module_name, attr = module_name.strip(), attr.strip()
    if is_path(module_name):
        module, shown = load_file(module_name, where, error), module_name
    else:
        module, shown = import_module(module_name, where, error), f"module {module_name!r}"
    obj = module if not attr else attribute(module, attr, shown, where, error, listing)
    return obj, module


def origin_of(module) -> Path | None:
    """The file a module was loaded from, if any."""
    path = getattr(module, "__file__", None)
    return Path(path) if path else None


def file_sha256(path) -> str | None:
    """The SHA-256 of a file's bytes, hex; None when it cannot be read."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


# --- messages ---------------------------------------------------------------------------------------------

def first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0].strip() if lines else ""


def describe(exc: BaseException, path=None) -> str:
    """``Type: first line of the message``, with the line of ``path`` where it was raised."""
    text = f"{type(exc).__name__}: {first_line(exc)}" if first_line(exc) else type(exc).__name__
    if path is not None:
        frames = [f for f in traceback.extract_tb(exc.__traceback__) if Path(f.filename) == Path(path)]
        if frames:
            text += f" (at {Path(path).name} line {frames[-1].lineno})"
        elif isinstance(exc, SyntaxError) and exc.lineno and "line" not in text:
            text += f" (at {Path(path).name} line {exc.lineno})"
    return text


def pip_hint(exc: BaseException) -> str:
    if isinstance(exc, ModuleNotFoundError) and exc.name:
        top = exc.name.split(".")[0]
        return f" (is the package installed? pip install {top})"
    return ""


def a(value) -> str:
    """'an int', 'a str', 'a module', 'None'."""
    if value is None:
        return "None"
    kind = type(value).__name__
    return f"{'an' if kind[0].lower() in 'aeiou' or kind == 'ndarray' else 'a'} {kind}"
