"""dtpf: a digital-twin particle filter.

A bootstrap particle filter (the entity) whose resampling a twin steers: an
information layer mirrors the particle weights and moves small-weight
particles towards large-weight ones before resampling (Eq. 28-30, degree PS),
and a system layer predicts degradation and sets PS. ``dtpf launch`` runs the
three layers as processes over Zenoh and records every message to MCAP; this
page is the same machinery in one process, for experiments::

    import dtpf

    result = dtpf.run(dtpf.RunConfig(scenario="ungm", particles=1000, steps=100, seed=7))
    result.rmse, result.mean_ess, result.ps          # figures of the run

    ancestors = dtpf.systematic(weights, rng)          # (weights, rng) -> ancestor indices
    moved = dtpf.preprocess(particles, weights, 0.81, rng)   # Eq. 28-30: moved.particles, moved.weights

    log = dtpf.read_log("runs/ungm-1.mcap")            # a recorded run, complete or cut short
    for item, message in log.decoded(): ...

The names, by what they are for:

- the filter: :class:`ParticleFilter` (an iterator, one step per ``next()``),
  :class:`StateSpaceModel` (the contract of a model; subclass it for your own),
  :func:`get_model` (a built-in model or ``"file.py:Name"`` / ``"module:Name"``);
- resampling, ``(weights, rng) -> ancestors``: :func:`multinomial`,
  :func:`stratified`, :func:`systematic`, :func:`residual`, :func:`ssp`,
  :func:`killing` (a resampler of your own has the same form; see
  :mod:`dtpf.messages.family` for every family a run takes your code in);
- a PS policy of your own: subclass :class:`PSPolicy`, return a
  :class:`PSDecision`;
- the preprocessing rules of the information layer: :func:`preprocess`
  (Eq. 28-30), :func:`threshold` (W of Eq. 28);
- a run: :class:`RunConfig` (every option of ``dtpf run`` and ``dtpf launch``),
  :func:`run` (the three layers in one process), :class:`RunResult`;
- logs: :func:`read_log` (any dtpf MCAP file), :func:`write_log`;
- a running twin: :func:`ask` (its state now, its recorded history, its forecast, over Zenoh queries:
  ``dtpf.ask("ungm-1", "forecast", connect="tcp/127.0.0.1:7447", horizon=5)``);
- errors: :class:`DtpfError`, the root of every error dtpf raises for bad
  input (a message, a file, a model, an option).

Names load on first use, so ``import dtpf`` costs nothing a process does not
use.

Where the code lives: the repository keeps one folder per layer of the paper
(``entity/``, ``information/``, ``system/``), the wire contract
(``messages/``) and the commands (``scripts/``); installed, they are the
subpackages ``dtpf.entity``, ``dtpf.information``, ``dtpf.system``,
``dtpf.messages`` and ``dtpf.scripts`` (``pyproject.toml`` maps each folder to
its name). This folder holds this page and the two rooms the layers share:
:mod:`dtpf.shell` (a layer's process on the bus) and :mod:`dtpf.recording`
(the MCAP log files). Floors, bottom up: messages < recording < shell <
entity < information < system < scripts < this page; a module imports its own
floor and those below.
"""
from __future__ import annotations

import importlib
from pathlib import Path

#: In a source checkout the layer folders sit beside this one; installed, inside it.
_CHECKOUT = Path(__file__).resolve().parent.parent
if not (Path(__file__).parent / "entity").is_dir() and (_CHECKOUT / "entity" / "__init__.py").is_file():
    __path__.append(str(_CHECKOUT))  # noqa: F821 - the package's own search path

_HOMES = {
    "ParticleFilter": "dtpf.entity.filter",
    "StateSpaceModel": "dtpf.entity.base",
    "multinomial": "dtpf.entity.resampling",
    "stratified": "dtpf.entity.resampling",
    "systematic": "dtpf.entity.resampling",
    "residual": "dtpf.entity.resampling",
    "ssp": "dtpf.entity.resamplers.ssp",
    "killing": "dtpf.entity.resamplers.killing",
    "PSPolicy": "dtpf.system.policy",
    "PSDecision": "dtpf.system.policy",
    "preprocess": "dtpf.information.rules",
    "threshold": "dtpf.information.rules",
    "RunConfig": "dtpf.messages.config",
    "run": "dtpf.scripts.inprocess",
    "RunResult": "dtpf.scripts.inprocess",
    "read_log": "dtpf.recording.logfile",
    "write_log": "dtpf.recording.logfile",
    "DtpfError": "dtpf.messages.errors",
    "ask": "dtpf.scripts.ask",
}
_RENAMED = {"get_model": ("dtpf.entity.model_ref", "resolve")}

__all__ = sorted([*_HOMES, *_RENAMED])


def __getattr__(name: str):
    if name in _HOMES:
        return getattr(importlib.import_module(_HOMES[name]), name)
    if name in _RENAMED:
        module, attribute = _RENAMED[name]
        return getattr(importlib.import_module(module), attribute)
    raise AttributeError(f"module 'dtpf' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
