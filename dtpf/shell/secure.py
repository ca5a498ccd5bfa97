"""A secured deployment's folder: the roles, what each may put, and the Zenoh configuration of a role.

``dtpf secure init DIR`` (:mod:`dtpf.scripts.secure`) writes two such folders,
``DIR/tls`` (mutual TLS, the roles named by their certificates' common names)
and ``DIR/usrpwd`` (Zenoh's user/password authentication over plain TCP).
Each holds ``dtpf-secure.json`` (what the folder is), ``router.json5`` (the
router's configuration, with the access-control list) and one
``<role>.json5`` per role. A TLS file holds its certificates and key inline
(Zenoh's ``*_base64`` keys), so it works from any working directory and in
any Zenoh client; a path inside a file (the router's password list, or a
folder written with paths) is relative to the folder and :func:`role_config`
resolves it, so the folder can move.

Every role may put only on its own keys (``dtpf/<twin>/<role>/**``); the
viewer puts nothing. This is the access control the router enforces; the
services check the rest (a message on a layer's key must name that layer,
:func:`dtpf.messages.codec.decode_for_key`).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from dtpf.messages.errors import DtpfError

__all__ = ["ROLES", "PUTTING_ROLES", "READING_ROLES", "MANIFEST", "KINDS", "SecureError", "SecureDir",
           "open_secure_dir", "role_config"]

#: Who takes part in a secured twin: the three layers, the recorder, a sensor and a read-only viewer.
ROLES = ("entity", "information", "system", "recorder", "sensor", "viewer")
#: The roles that put, each only on ``dtpf/<twin>/<role>/**`` (statuses, liveliness tokens included).
PUTTING_ROLES = ("entity", "information", "system", "recorder", "sensor")
#: The roles that read a twin's keys (``dtpf/<twin>/**``); a sensor reads only its entity's status.
READING_ROLES = ("entity", "information", "system", "recorder", "viewer")
#: The file that says what a secure folder is.
MANIFEST = "dtpf-secure.json"
#: The ways a secure folder authenticates: mutual TLS, or user and password over TCP.
KINDS = ("tls", "usrpwd")
#: Keys of a Zenoh configuration that hold paths, resolved against the folder.
_PATH_KEYS = (
    ("transport", "link", "tls", "root_ca_certificate"),
    ("transport", "link", "tls", "listen_certificate"),
    ("transport", "link", "tls", "listen_private_key"),
    ("transport", "link", "tls", "connect_certificate"),
    ("transport", "link", "tls", "connect_private_key"),
    ("transport", "auth", "usrpwd", "dictionary_file"),
)


class SecureError(DtpfError, ValueError):
    """A secure folder is missing, incomplete or does not fit the endpoint; the message says what."""


@dataclass(frozen=True)
class SecureDir:
    """A secure folder as its manifest describes it."""

    path: Path
    kind: str           #: "tls" or "usrpwd"
    roles: tuple[str, ...]
    twins: str          #: the twin pattern the access control covers ("*": every twin)

    @property
    def scheme(self) -> str:
        """The Zenoh link protocol of its endpoints: ``tls`` or ``tcp``."""
        return "tls" if self.kind == "tls" else "tcp"

    def endpoint(self, host: str, port: int) -> str:
        return f"{self.scheme}/{host}:{port}"

    def check_endpoint(self, endpoint: str) -> None:
        """SecureError unless ``endpoint`` uses this folder's link protocol."""
        if not endpoint.startswith(self.scheme + "/"):
            raise SecureError(f"endpoint {endpoint!r} does not fit the secure folder {self.path} "
                              f"({self.kind}): use {self.scheme}/HOST:PORT")

    def file_of(self, role: str) -> Path:
        """The Zenoh configuration file of ``role`` ("router" for the router's)."""
        if role != "router" and role not in self.roles:
            raise SecureError(f"the secure folder {self.path} has no role {role!r}; it has "
                              f"{', '.join(self.roles)}")
        return self.path / f"{role}.json5"


def open_secure_dir(path) -> SecureDir:
    """The secure folder at ``path``: a folder with a manifest, or one with ``tls/`` in it (its TLS half)."""
    path = Path(path)
    if not (path / MANIFEST).is_file() and (path / "tls" / MANIFEST).is_file():
        path = path / "tls"
    manifest = path / MANIFEST
    if not manifest.is_file():
        raise SecureError(f"{path} is not a secure folder (no {MANIFEST}); make one with: dtpf secure init DIR")
    try:
        data = json.loads(manifest.read_text(encoding="utf-8"))
        kind, roles, twins = data["kind"], tuple(data["roles"]), str(data.get("twins", "*"))
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise SecureError(f"cannot read {manifest}: {error}") from None
    if kind not in KINDS:
        raise SecureError(f"{manifest}: unknown kind {kind!r}; expected one of {', '.join(KINDS)}")
    return SecureDir(path.resolve(), kind, roles, twins)


def role_config(secure: SecureDir, role: str) -> str:
    """The JSON5 text of ``role``'s Zenoh configuration with its paths made absolute.

    The files are written by :mod:`dtpf.scripts.secure` as plain JSON (valid JSON5);
    a file edited into JSON5 proper is refused with the reason.
    """
    path = secure.file_of(role)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SecureError(f"the secure folder {secure.path} lacks {path.name}") from None
    except (OSError, ValueError) as error:
        raise SecureError(f"cannot read {path} (dtpf reads these files as JSON): {error}") from None
    for keys in _PATH_KEYS:
        node = data
        for key in keys[:-1]:
            node = node.get(key) if isinstance(node, dict) else None
        if isinstance(node, dict) and isinstance(node.get(keys[-1]), str):
            target = secure.path / node[keys[-1]]
            if not target.is_file():
                raise SecureError(f"{path.name} names {node[keys[-1]]!r}, which is not in {secure.path}")
            node[keys[-1]] = str(target)
    return json.dumps(data)
