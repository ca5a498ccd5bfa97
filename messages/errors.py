"""The root of dtpf's errors.

Every error dtpf raises for what a user or a peer gave it (a message, a file,
a model, an option, a port) is a :class:`DtpfError`; each subclass keeps the
built-in base it always had (``ValueError`` for bad values, ``RuntimeError``
for a service that could not start), so existing ``except`` clauses still
catch it. A command prints any of them as one line and exits 2::

    try:
        ...
    except DtpfError as error:
        print(f"dtpf run: error: {error}", file=sys.stderr)

The families, where they live:

==========================  ==============================================  ==============
error                       raised for                                      base
==========================  ==============================================  ==============
``MessageError``            bytes that are not a valid message for a key    ValueError
``RunInputError``           a run's options or inputs                       ValueError
``ModelError``              a model reference or a model that breaks        RunInputError
                            the contract
``ObservationError``        an observations file                            RunInputError
``FilterError``             weights no particle can explain, at a step      ValueError
``LogError``                a file that is not a dtpf MCAP log              ValueError
``SecureError``             a security folder                               ValueError
``BusError``                Zenoh: a port in use, a router not reached      RuntimeError
``LaunchError``             a service that did not start                    RuntimeError
``PlotError``               a log that cannot be plotted as asked           ValueError
==========================  ==============================================  ==============
"""
from __future__ import annotations

__all__ = ["DtpfError", "RunInputError"]


class DtpfError(Exception):
    """Something dtpf was given is wrong; the message says what, in one line."""


class RunInputError(DtpfError, ValueError):
    """What the user gave a run cannot be used: an option, a model, a component, an observation file. A service
    exits 2 with the one-line message, no traceback (dtpf.entity.model_ref.ModelError,
    dtpf.messages.references.ReferenceLoadError, dtpf.entity.observations.ObservationError). ``validation``:
    pydantic's error behind a bad option."""

    def __init__(self, message: str, *, validation=None):
        super().__init__(message)
        self.validation = validation
