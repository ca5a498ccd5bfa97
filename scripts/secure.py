"""``dtpf secure init DIR``: what a secured twin needs, certificates, passwords and access control.

Writes (every file owner-only, every folder 0700)::

    DIR/ca/ca.pem, ca.key        the certificate authority (keep ca.key off the twin's machines)
    DIR/tls/                     mutual TLS: a role is the common name of its certificate
        dtpf-secure.json         what the folder is (dtpf.shell.secure)
        ca.pem                   the authority's certificate, to check the others
        router.json5             the router: tls/ listener, mTLS, the access-control list
        <role>.json5             one per role: client mode, its certificate and key
        certs/<role>.pem, keys/<role>.key

The TLS configurations hold the certificates and keys themselves (Zenoh's
``*_base64`` keys), so any Zenoh client opens them from any working
directory: ``zenoh.open(zenoh.Config.from_file("DIR/tls/viewer.json5"))``.
    DIR/usrpwd/                  the same roles by user name and password, over plain tcp/
        dtpf-secure.json, router.json5, <role>.json5, passwords.txt

The access control (:func:`access_control`) denies by default; each role may
put only on its own keys (``dtpf/<twin>/<role>/**``, its status and liveliness
token included), the layers, the recorder and the viewer may read the twin's
keys and ask it (its state, forecast and history: queries, which change nothing), a sensor reads only
its entity's status. Certificates and keys come from
the ``cryptography`` package (ECDSA P-256, SHA-256), not from code of ours.
"""
from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import json
import os
import secrets
import sys
from pathlib import Path

from dtpf.shell.secure import MANIFEST, PUTTING_ROLES, READING_ROLES, ROLES

__all__ = ["access_control", "init", "export", "register", "main", "DEFAULT_PORT"]

#: The router's endpoint written into the files (``dtpf launch --secure`` picks a free port instead).
DEFAULT_PORT = 7447
DEFAULT_HOSTS = ("127.0.0.1", "localhost")


def _twin_keys(twins: str, rest: str) -> str:
    return f"dtpf/{twins}/{rest}" if rest else ("dtpf/**" if twins == "*" else f"dtpf/{twins}/**")


def access_control(kind: str, twins: str = "*") -> dict:
    """The router's ``access_control`` section: default deny, each role puts on its own keys only.

    A role is the common name of its certificate (``kind`` "tls") or its user
    name ("usrpwd"). ``twins``: the twin names the roles may act for (a Zenoh
    key chunk: "*" for every twin, or one twin's name).
    """
    rules = [
        {"id": "read", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
         "key_exprs": [_twin_keys(twins, "")]},
        {"id": "delivered", "permission": "allow", "flows": ["egress"],
         "messages": ["put", "liveliness_token"], "key_exprs": [_twin_keys(twins, "")]},
        {"id": "read-entity-status", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_subscriber"], "key_exprs": [_twin_keys(twins, "entity/status")]},
        {"id": "watch-liveliness", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_liveliness_subscriber", "liveliness_query"],
         "key_exprs": [_twin_keys(twins, "*/alive")]},
        {"id": "delivered-entity-status", "permission": "allow", "flows": ["egress"],
         "messages": ["put", "liveliness_token"],
         "key_exprs": [_twin_keys(twins, "entity/status"), _twin_keys(twins, "*/alive")]},
    ]
    # A publisher learns of the subscribers of the twin, so that its puts are sent at all: a client sends
    # only what a subscriber it knows of matches, and a recorder's dtpf/<twin>/** is not inside
    # dtpf/<twin>/entity/** (the access control compares declarations by inclusion).
    rules.append({"id": "hears-subscribers", "permission": "allow", "flows": ["egress"],
                  "messages": ["declare_subscriber"], "key_exprs": [_twin_keys(twins, "")]})
    for role in PUTTING_ROLES:
        rules.append({"id": f"{role}-puts", "permission": "allow", "flows": ["ingress"],
                      "messages": ["put", "liveliness_token"], "key_exprs": [_twin_keys(twins, f"{role}/**")]})
    # Questions (dtpf ask): a reader may ask the entity's and the recorder's queryables and hear their answers;
    # the entity and the recorder may declare them and answer. A query only reads: none changes the twin.
    questions = [_twin_keys(twins, "entity/state"), _twin_keys(twins, "entity/forecast"),
                 _twin_keys(twins, "recorder/history")]
    rules += [
        {"id": "ask", "permission": "allow", "flows": ["ingress"], "messages": ["query"], "key_exprs": questions},
        {"id": "hear-answers", "permission": "allow", "flows": ["egress"], "messages": ["reply", "declare_queryable"],
         "key_exprs": questions},
    ]
    for role, answered in (("entity", questions[:2]), ("recorder", questions[2:])):
        rules += [{"id": f"{role}-answers", "permission": "allow", "flows": ["ingress"],
                   "messages": ["declare_queryable", "reply"], "key_exprs": answered},
                  {"id": f"{role}-asked", "permission": "allow", "flows": ["egress"], "messages": ["query"],
                   "key_exprs": answered}]
    # Zenoh's advanced publishers and subscribers (a recorder's recovery of what it missed, a service's history of
    # its twins' statuses) talk on <key>/@adv/...: a publisher's cache answers queries, beats and declares its
    # liveliness token on <key>/@adv/pub/<zid>/<eid>/..., a subscriber asks and listens there and declares its own
    # token on <key>/@adv/sub/.... '**' does not match the verbatim chunk '@adv', so these keys have rules of their
    # own. Every role may ask and listen; a role may answer, beat and announce only under its own keys, so a
    # recovered message is as trustworthy as a live one.
    caches = "dtpf/**/@adv/**" if twins == "*" else f"dtpf/{twins}/**/@adv/**"
    listening = ["query", "declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "liveliness_token"]
    rules += [
        {"id": "cache-listen", "permission": "allow", "flows": ["ingress"], "messages": listening,
         "key_exprs": [caches]},
        {"id": "cache-delivered", "permission": "allow", "flows": ["egress"],
         "messages": [*listening, "put", "reply", "declare_queryable"], "key_exprs": [caches]},
    ]
    # A cache answers with the messages themselves, on their own keys: a role replies only on its own.
    rules.append({"id": "cache-replies-delivered", "permission": "allow", "flows": ["egress"], "messages": ["reply"],
                  "key_exprs": [_twin_keys(twins, "")]})
    for role in PUTTING_ROLES:
        rules.append({"id": f"{role}-cache", "permission": "allow", "flows": ["ingress"],
                      "messages": ["put", "reply", "declare_queryable", "liveliness_token"],
                      "key_exprs": [_twin_keys(twins, f"{role}/**/@adv/**")]})
        rules.append({"id": f"{role}-cache-replies", "permission": "allow", "flows": ["ingress"],
                      "messages": ["reply"], "key_exprs": [_twin_keys(twins, f"{role}/**")]})
    # Large particle sets travel by reference (dtpf.shell.shared_sets): a reader on another host asks the
    # publisher's queryable <key>/@slot for a set's bytes. Every role may ask and hear the answer; a role may
    # declare such a queryable, and answer, only under its own keys.
    slots = _twin_keys(twins, "*/*/@slot")
    rules += [
        {"id": "slot-ask", "permission": "allow", "flows": ["ingress"], "messages": ["query"], "key_exprs": [slots]},
        {"id": "slot-answers-delivered", "permission": "allow", "flows": ["egress"],
         "messages": ["reply", "declare_queryable"], "key_exprs": [slots]},
    ]
    for role in PUTTING_ROLES:
        rules += [{"id": f"{role}-slots", "permission": "allow", "flows": ["ingress"],
                   "messages": ["declare_queryable", "reply"], "key_exprs": [_twin_keys(twins, f"{role}/*/@slot")]},
                  {"id": f"{role}-slots-asked", "permission": "allow", "flows": ["egress"], "messages": ["query"],
                   "key_exprs": [_twin_keys(twins, f"{role}/*/@slot")]}]
    field = "cert_common_names" if kind == "tls" else "usernames"
    subjects = [{"id": role, field: [role]} for role in ROLES]
    policies = [{"id": "readers", "rules": ["read", "delivered"], "subjects": list(READING_ROLES)},
                {"id": "sensor-reads", "rules": ["read-entity-status", "watch-liveliness", "delivered-entity-status"],
                 "subjects": ["sensor"]}]
    policies += [{"id": f"{role}-writes", "rules": [f"{role}-puts", "hears-subscribers"],
                  "subjects": [role]} for role in PUTTING_ROLES]
    policies += [{"id": "askers", "rules": ["ask", "hear-answers"], "subjects": list(READING_ROLES)}]
    policies += [{"id": "caches", "rules": ["cache-listen", "cache-delivered", "cache-replies-delivered"],
                  "subjects": list(ROLES)}]
    policies += [{"id": f"{role}-caches", "rules": [f"{role}-cache", f"{role}-cache-replies"], "subjects": [role]}
                 for role in PUTTING_ROLES]
    policies += [{"id": f"{role}-answers", "rules": [f"{role}-answers", f"{role}-asked"], "subjects": [role]}
                 for role in ("entity", "recorder")]
    policies += [{"id": "slot-readers", "rules": ["slot-ask", "slot-answers-delivered"], "subjects": list(ROLES)}]
    policies += [{"id": f"{role}-slot-answers", "rules": [f"{role}-slots", f"{role}-slots-asked"],
                  "subjects": [role]} for role in PUTTING_ROLES]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _base(mode: str, endpoint: str) -> dict:
    where = {"listen": {"endpoints": [endpoint]}} if mode == "router" else {"connect": {"endpoints": [endpoint]}}
    return {"mode": mode, **where,
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}


# --- certificates (cryptography) -------------------------------------------------------------

def _key():
    from cryptography.hazmat.primitives.asymmetric import ec
    return ec.generate_private_key(ec.SECP256R1())


def _pem_key(key) -> bytes:
    from cryptography.hazmat.primitives import serialization
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _pem_cert(cert) -> bytes:
    from cryptography.hazmat.primitives import serialization
    return cert.public_bytes(serialization.Encoding.PEM)


def _certificate(subject_cn: str, key, issuer_cert, issuer_key, days: int, *, ca: bool = False,
                 hosts: tuple[str, ...] = (), server: bool = False):
    """An X.509 v3 certificate for ``key``, signed by the issuer (self-signed when ``issuer_cert`` is None)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    name = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "dtpf"),
                      x509.NameAttribute(NameOID.COMMON_NAME, subject_cn)])
    now = dt.datetime.now(dt.timezone.utc)
    builder = (x509.CertificateBuilder()
               .subject_name(name)
               .issuer_name(issuer_cert.subject if issuer_cert is not None else name)
               .public_key(key.public_key())
               .serial_number(x509.random_serial_number())
               .not_valid_before(now - dt.timedelta(minutes=5))
               .not_valid_after(now + dt.timedelta(days=days))
               .add_extension(x509.BasicConstraints(ca=ca, path_length=0 if ca else None), critical=True))
    if ca:
        builder = builder.add_extension(x509.KeyUsage(
            digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
            key_encipherment=False, data_encipherment=False, key_agreement=False, encipher_only=False,
            decipher_only=False), critical=True)
    else:
        builder = builder.add_extension(x509.KeyUsage(
            digital_signature=True, key_cert_sign=False, crl_sign=False, content_commitment=False,
            key_encipherment=False, data_encipherment=False, key_agreement=True, encipher_only=False,
            decipher_only=False), critical=True)
        usages = [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH] if server \
            else [ExtendedKeyUsageOID.CLIENT_AUTH]
        builder = builder.add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        names = []
        for host in hosts or (subject_cn,):
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(host)))
            except ValueError:
                names.append(x509.DNSName(host))
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return builder.sign(issuer_key if issuer_key is not None else key, hashes.SHA256())


# --- writing ---------------------------------------------------------------------------------

def _write(path: Path, data: bytes | str) -> None:
    """Write ``path`` readable by its owner only (created so; never world-readable in between)."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    if isinstance(data, str):
        data = data.encode("utf-8")
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "wb") as handle:
        handle.write(data)
    os.chmod(path, 0o600)


#: Written into every folder of secrets: git (and tools that read .gitignore) leave its contents out.
GITIGNORE = "# dtpf secure: private keys and passwords; never commit this folder\n*\n"


def _keep_out_of_git(folder: Path) -> Path:
    """A .gitignore that ignores everything in ``folder`` (itself included)."""
    path = folder / ".gitignore"
    _write(path, GITIGNORE)
    return path


def _inline(folder: Path, **files: str) -> dict:
    """Zenoh's ``<name>_base64`` keys holding the files' contents: a configuration that names no path works
    from any working directory and in any Zenoh client (Zenoh resolves a relative path against the working
    directory, not against the file). The files stay in the folder beside it."""
    import base64

    return {f"{name}_base64": base64.b64encode((folder / file).read_bytes()).decode("ascii")
            for name, file in files.items()}


def _json(data) -> str:
    return json.dumps(data, indent=2) + "\n"


def init(folder, *, hosts: tuple[str, ...] = DEFAULT_HOSTS, port: int = DEFAULT_PORT, twins: str = "*",
         days: int = 365, force: bool = False) -> list[Path]:
    """Write a secure deployment into ``folder``; returns the files written.

    ``hosts``: the router's addresses (its certificate's names, the first one
    in every endpoint). Refuses a folder that holds files unless ``force``.
    """
    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()) and not force:
        raise FileExistsError(f"{folder} is not empty; pass --force to replace what is there")
    if not hosts:
        raise ValueError("at least one --host is needed")
    if "/" in twins or twins in ("", "**"):
        raise ValueError(f"--twin takes one twin name or '*', got {twins!r}")
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    written: list[Path] = [_keep_out_of_git(folder)]

    def put(path: Path, data) -> None:
        _write(path, data)
        written.append(path)

    ca_key = _key()
    ca_cert = _certificate("dtpf twin authority", ca_key, None, None, days=max(days, 3650), ca=True)
    put(folder / "ca" / "ca.key", _pem_key(ca_key))
    put(folder / "ca" / "ca.pem", _pem_cert(ca_cert))

    tls = folder / "tls"
    tls_endpoint = f"tls/{hosts[0]}:{port}"
    put(tls / "ca.pem", _pem_cert(ca_cert))
    for name in ("router", *ROLES):
        key = _key()
        cert = _certificate(name, key, ca_cert, ca_key, days, hosts=hosts if name == "router" else (),
                            server=name == "router")
        put(tls / "keys" / f"{name}.key", _pem_key(key))
        put(tls / "certs" / f"{name}.pem", _pem_cert(cert))
    router = _base("router", tls_endpoint)
    router["transport"] = {"link": {"tls": {
        **_inline(tls, root_ca_certificate="ca.pem", listen_certificate="certs/router.pem",
                  listen_private_key="keys/router.key"), "enable_mtls": True}}}
    router["access_control"] = access_control("tls", twins)
    put(tls / "router.json5", _json(router))
    for role in ROLES:
        client = _base("client", tls_endpoint)
        client["transport"] = {"link": {"tls": {
            **_inline(tls, root_ca_certificate="ca.pem", connect_certificate=f"certs/{role}.pem",
                      connect_private_key=f"keys/{role}.key"), "enable_mtls": True}}}
        put(tls / f"{role}.json5", _json(client))
    put(tls / MANIFEST, _json({"kind": "tls", "roles": list(ROLES), "twins": twins, "hosts": list(hosts)}))

    usrpwd = folder / "usrpwd"
    tcp_endpoint = f"tcp/{hosts[0]}:{port}"
    passwords = {role: secrets.token_urlsafe(24) for role in ROLES}
    put(usrpwd / "passwords.txt", "".join(f"{role}:{password}\n" for role, password in passwords.items()))
    router = _base("router", tcp_endpoint)
    router["transport"] = {"auth": {"usrpwd": {"dictionary_file": "passwords.txt"}}}
    router["access_control"] = access_control("usrpwd", twins)
    put(usrpwd / "router.json5", _json(router))
    for role in ROLES:
        client = _base("client", tcp_endpoint)
        client["transport"] = {"auth": {"usrpwd": {"user": role, "password": passwords[role]}}}
        put(usrpwd / f"{role}.json5", _json(client))
    put(usrpwd / MANIFEST, _json({"kind": "usrpwd", "roles": list(ROLES), "twins": twins, "hosts": list(hosts)}))
    return written


def export(folder, roles, target) -> list[Path]:
    """Copy what ``roles`` of the secure folder need on their machine into ``target``, and nothing else:
    the manifest, the authority's certificate, each role's configuration and, for TLS, its certificate and
    key (never another role's key, never the authority's). ``roles`` may include "router"."""
    from dtpf.shell.secure import open_secure_dir, role_config

    source = open_secure_dir(folder)
    target = Path(target)
    if target.exists() and any(target.iterdir()):
        raise FileExistsError(f"{target} is not empty")
    for role in roles:
        role_config(source, role)  # every role exists and its files are there, before anything is written
    written: list[Path] = []
    for role in roles:
        names = [f"{role}.json5"]
        if source.kind == "tls":
            names += ["ca.pem", f"certs/{role}.pem", f"keys/{role}.key"]
        elif role == "router":
            names += ["passwords.txt"]
        for name in names:
            _write(target / name, (source.path / name).read_bytes())
            written.append(target / name)
    manifest = json.loads((source.path / MANIFEST).read_text(encoding="utf-8"))
    manifest["roles"] = [role for role in roles if role != "router"]
    _write(target / MANIFEST, _json(manifest))
    written.append(target / MANIFEST)
    written.append(_keep_out_of_git(target))
    os.chmod(target, 0o700)
    return sorted(set(written))


def cmd_export(args: argparse.Namespace) -> int:
    try:
        written = export(args.dir, args.role, args.target)
    except (FileExistsError, ValueError, OSError) as error:
        print(f"dtpf secure export: error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {len(written)} files into {args.target} (owner-only) for {', '.join(args.role)}")
    return 0


def main(args: argparse.Namespace) -> int:
    try:
        written = init(args.dir, hosts=tuple(args.host or DEFAULT_HOSTS), port=args.port, twins=args.twin,
                       days=args.days, force=args.force)
    except (FileExistsError, ValueError, OSError) as error:
        print(f"dtpf secure init: error: {error}", file=sys.stderr)
        return 2
    folder = Path(args.dir)
    print(f"wrote {len(written)} files into {folder} (owner-only)")
    print(f"  {folder / 'tls'}      mutual TLS, roles: {', '.join(ROLES)}")
    print(f"  {folder / 'usrpwd'}   user and password over tcp/ (weaker: see docs/guides/security.md)")
    print(f"  {folder / 'ca'}       the certificate authority: keep ca.key off the twin's machines")
    print(f"run a secured twin:  dtpf launch --secure {folder / 'tls'}")
    return 0


def register(subparsers) -> None:
    """``dtpf secure init``."""
    secure = subparsers.add_parser(
        "secure", help="make what a secured twin needs (certificates, passwords, access control)",
        description="Secured deployments: mutual TLS or user/password, and an access-control list on the "
                    "router so that only a twin's own layers can steer it. See docs/guides/security.md.")
    actions = secure.add_subparsers(dest="secure_command", metavar="ACTION", required=True)
    make = actions.add_parser(
        "init", help="write a certificate authority, a certificate and key per role, and Zenoh configurations",
        description="Write DIR/tls (mutual TLS) and DIR/usrpwd (user/password) with one Zenoh configuration per "
                    "role (" + ", ".join(ROLES) + ") and the router's, whose access control lets each role put "
                    "only on its own keys (dtpf/<twin>/<role>/**) and the viewer put nothing. Files are "
                    "owner-only. Then: dtpf launch --secure DIR/tls, or each service with --secure DIR/tls "
                    "--role NAME --connect tls/HOST:PORT.")
    make.add_argument("dir", metavar="DIR", help="the folder to write (must be empty or new)")
    make.add_argument("--host", action="append", metavar="HOST",
                      help="an address of the router (IP or DNS name), put in its certificate; the first is "
                           "the endpoint in the files (repeatable; default: 127.0.0.1 and localhost)")
    make.add_argument("--port", type=int, default=DEFAULT_PORT,
                      help=f"the router's port in the files (default {DEFAULT_PORT}; dtpf launch picks its own)")
    make.add_argument("--twin", default="*", metavar="NAME",
                      help="the twin the roles may act for (default '*': every twin)")
    make.add_argument("--days", type=int, default=365, help="how long the role certificates are valid (default 365)")
    make.add_argument("--force", action="store_true", help="write into a folder that is not empty")
    make.set_defaults(handler=main)
    out = actions.add_parser(
        "export", help="copy what some roles need on their machine, and nothing else",
        description="Copy into TARGET what the given roles need (the manifest, ca.pem, each role's configuration, "
                    "certificate and key; the router's password list for 'router' with usrpwd), never another "
                    "role's key nor the authority's. Copy TARGET to that machine and pass --secure TARGET.")
    out.add_argument("dir", metavar="DIR", help="the secure folder (DIR/tls or DIR/usrpwd)")
    out.add_argument("target", metavar="TARGET", help="the folder to write (must be empty or new)")
    out.add_argument("--role", action="append", required=True, metavar="NAME",
                     help="a role to export (repeatable): " + ", ".join(("router", *ROLES)))
    out.set_defaults(handler=cmd_export)
