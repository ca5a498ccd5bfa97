"""Only a twin's own layers can steer it (mutual TLS or user/password, and access control).

Real launches on free loopback ports. An attacker session watches the run and,
for every particle set the entity publishes, forges the answers a layer would
give: a preprocessed set with every particle at 100 and a PS command of 0.
Against a plain launch the forgeries land (the control test: the attack can
change the numbers); against a secured launch the router's access control drops
them, and the run's numbers are those of the in-process run, number for number.
"""
from __future__ import annotations

import contextlib
import json
import stat
import threading
import time
from collections import Counter

import numpy as np
import pytest
import zenoh

from dtpf.messages.codec import MessageError, decode_for_key, encode
from dtpf.messages.config import RunConfig
from dtpf.messages.models import Estimate, ParticleSet, ParticleSetKind, PSCommand
from dtpf.scripts import inprocess, secure
from dtpf.scripts.launch import LaunchError, launch
from dtpf.shell.bus import BusError, Inbox, free_port, open_session, publisher, zenoh_config
from dtpf.shell.secure import ROLES, SecureError, open_secure_dir, role_config

pytest.importorskip("cryptography")

N, STEPS = 200, 40


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("secure")
    secure.init(root / "deploy")
    return root / "deploy"


class Attacker:
    """A session on the twin's router that forges a layer's answer to every particle set it sees."""

    def __init__(self, twin: str, **config):
        self.twin = twin
        self.session = open_session(zenoh_config(mode="client", **config))
        self.inbox = Inbox(self.session, f"dtpf/{twin}/entity/particles", f"dtpf/{twin}/entity/estimate")
        self.forged = 0
        self.estimates = 0
        self.publishers = {key: self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                           for key in (f"dtpf/{twin}/information/preprocessed", f"dtpf/{twin}/system/ps",
                                       f"dtpf/{twin}/system/status")}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            item = self.inbox.get(timeout=0.05)
            if item is None:
                continue
            try:
                message = decode_for_key(item.key, item.payload)
            except MessageError:
                continue
            if isinstance(message, Estimate):
                self.estimates += 1
                continue
            header = dict(run_id=message.run_id, twin_id=message.twin_id, step=message.step)
            forged_set = ParticleSet(**header, layer="information", kind=ParticleSetKind.PREPROCESSED,
                                     particles=np.full_like(message.particles, 100.0), weights=message.weights,
                                     observation=message.observation, ps=0.0, threshold=0.5)
            forged_ps = PSCommand(**header, layer="system", ps=0.0, applies_from_step=message.step,
                                  policy="fixed", reason="forged")
            self.publishers[f"dtpf/{self.twin}/information/preprocessed"].put(encode(forged_set))
            self.publishers[f"dtpf/{self.twin}/system/ps"].put(encode(forged_ps))
            self.forged += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.inbox.close()
        self.session.close()


def attacked_launch(tmp_path, twin: str, attacker_config, *, secure_dir=None):
    """A launch of (N, STEPS) with an attacker connected as soon as the router listens."""
    config = RunConfig(particles=N, steps=STEPS, seed=5, twin=twin)
    port = free_port()
    outcome: dict = {}

    def run():
        try:
            outcome["result"] = launch(config, log_path=tmp_path / f"{twin}.mcap", port=port, timeout=5.0,
                                       rate=40.0, notify=lambda text: None, secure=secure_dir)
        except Exception as error:  # the test reads it
            outcome["error"] = error

    launcher = threading.Thread(target=run)
    launcher.start()
    attacker = None
    try:
        deadline = time.monotonic() + 30
        while attacker is None:  # the launcher's router is not listening at once
            try:
                attacker = Attacker(twin, **attacker_config(port))
            except BusError:
                if time.monotonic() > deadline or not launcher.is_alive():
                    raise
                time.sleep(0.1)
        launcher.join(timeout=120)
    finally:
        if attacker is not None:
            attacker.close()
        launcher.join(timeout=60)
    assert "error" not in outcome, outcome.get("error")
    return config, outcome["result"], attacker


def means(result) -> list[float]:
    return [float(np.asarray(e.mean).ravel()[0]) for e in sorted(result.estimates, key=lambda e: e.step)]


def test_a_forging_session_steers_a_plain_launch(tmp_path):
    """The control: without security the same attack changes the run (so the tests below can fail)."""
    config, result, attacker = attacked_launch(
        tmp_path, "t-plain", lambda port: dict(connect=[f"tcp/127.0.0.1:{port}"]))
    assert attacker.forged >= STEPS // 2
    reference = inprocess.run(config)
    attacked, clean = np.array(means(result)), np.ravel(reference.means)
    assert attacked.shape == clean.shape
    assert np.sum(attacked != clean) >= STEPS // 4  # the forged sets and PS landed on many steps


@pytest.mark.parametrize("kind", ["tls", "usrpwd"])
def test_a_viewer_reads_a_secured_launch_but_its_forgeries_are_dropped(tmp_path, folder, kind):
    deployment = open_secure_dir(folder / kind)
    config, result, attacker = attacked_launch(
        tmp_path, f"t-viewer-{kind}",
        lambda port: dict(secure=deployment, role="viewer", connect=[deployment.endpoint("127.0.0.1", port)]),
        secure_dir=deployment.path)
    assert attacker.estimates >= STEPS - 1  # it can watch the run
    assert attacker.forged >= STEPS - 1     # and it tried at every step
    reference = inprocess.run(config)
    np.testing.assert_array_equal(means(result), np.ravel(reference.means))  # number for number: nothing it sent arrived
    assert not any(e.degraded for e in result.estimates)
    assert result.rejected == {"entity": 0, "information": 0, "recorder": 0, "system": 0}


@pytest.mark.parametrize("kind", ["tls", "usrpwd"])
def test_a_secured_router_lets_in_no_session_without_credentials(folder, kind):
    deployment = open_secure_dir(folder / kind)
    port = free_port()
    router = open_session(zenoh_config(secure=deployment, role="router",
                                       listen=[deployment.endpoint("127.0.0.1", port)]))
    try:
        with pytest.raises(BusError, match="Unable to connect"):  # plain tcp/, no certificate or password
            open_session(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
        if kind == "tls":
            with pytest.raises(BusError, match="Unable to connect"):  # TLS that checks the router, but no client certificate
                open_session(zenoh_config(mode="client", connect=[f"tls/127.0.0.1:{port}"], cfg=[
                    f"transport/link/tls/root_ca_certificate:{json.dumps(str(deployment.path / 'ca.pem'))}"]))
        else:
            text = role_config(deployment, "viewer").replace('"password": "', '"password": "x')
            with pytest.raises(BusError, match="Unable to connect"):  # a wrong password
                open_session(zenoh.Config.from_json5(text))
    finally:
        router.close()


@pytest.mark.parametrize("kind", ["tls", "usrpwd"])
def test_each_role_puts_only_on_its_own_layers_keys(folder, kind):
    """The entity's puts on system/** and information/** never reach anyone; its own keys do."""
    deployment = open_secure_dir(folder / kind)
    port = free_port()
    endpoint = deployment.endpoint("127.0.0.1", port)
    router = open_session(zenoh_config(secure=deployment, role="router", listen=[endpoint]))
    sessions = []
    try:
        def client(role):
            sessions.append(open_session(zenoh_config(secure=deployment, role=role, connect=[endpoint])))
            return sessions[-1]

        viewer_inbox = Inbox(client("viewer"), "dtpf/**")
        senders = {role: client(role) for role in ("entity", "information", "system", "sensor")}
        # The viewer's subscription has reached a sender once the viewer hears it on a key of its own layer
        # (a fixed wait for that was too short on a loaded machine).
        ready = {role: publisher(session, f"dtpf/t-acl/{role}/ready") for role, session in senders.items()}
        heard_ready: set[str] = set()
        deadline = time.monotonic() + 60.0
        while heard_ready != set(senders) and time.monotonic() < deadline:
            for role in set(senders) - heard_ready:
                ready[role].put(role.encode())
            item = viewer_inbox.get(timeout=0.1)
            while item is not None:
                if item.key.endswith("/ready"):
                    heard_ready.add(item.payload.decode())
                item = viewer_inbox.get(timeout=0)
        assert heard_ready == set(senders)
        layers = ("entity", "information", "system", "sensor", "recorder")
        publishers = {(role, layer): publisher(session, f"dtpf/t-acl/{layer}/probe")
                      for role, session in senders.items() for layer in layers}  # as the services publish
        time.sleep(0.3)
        tried = 0
        for _ in range(3):  # not only the first put of a publisher: every one (the recorder's case)
            for (role, layer), probe in publishers.items():
                probe.put(role.encode())
                tried += 1
            time.sleep(0.2)
        heard = Counter()
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and sum(heard.values()) < 3 * len(senders):
            item = viewer_inbox.get(timeout=0.1)
            if item is not None and not item.key.endswith("/ready"):  # a late one of the handshake
                heard[item.payload.decode(), item.key] += 1
        time.sleep(0.5)  # what should never come would have come by now
        while (item := viewer_inbox.get(timeout=0)) is not None:
            if not item.key.endswith("/ready"):
                heard[item.payload.decode(), item.key] += 1
        assert heard == {(role, f"dtpf/t-acl/{role}/probe"): 3 for role in senders}
        assert tried == 60
    finally:
        for session in sessions:
            session.close()
        router.close()


def test_a_secured_launch_gives_the_plain_numbers_and_a_log_that_verifies(tmp_path, folder):
    from dtpf.recording.logfile import read_log
    from dtpf.scripts.logs.verify import verify

    config = RunConfig(particles=N, steps=STEPS, seed=9, twin="t-secured")
    result = launch(config, log_path=tmp_path / "secured.mcap", timeout=5.0, notify=lambda text: None,
                    secure=folder)
    np.testing.assert_array_equal(means(result), np.ravel(inprocess.run(config).means))
    assert result.exit_codes == {"recorder": 0, "system": 0, "information": 0, "entity": 0}
    log = read_log(tmp_path / "secured.mcap")
    verification = verify(log)
    assert verification.ok and verification.checked == list(range(1, STEPS + 1))
    # Every message a plain launch records is recorded: a publisher whose only subscriber is the recorder
    # (dtpf/<twin>/**) still sends (the access control lets it hear of that subscriber).
    plain = read_log(tmp_path / "plain.mcap") if launch(config, log_path=tmp_path / "plain.mcap", timeout=5.0,
                                                        notify=lambda text: None) else None
    # No key and no password of the folder is in the log (statuses carry the run configuration only).
    recorded = (tmp_path / "secured.mcap").read_bytes()
    secrets = [line for path in (folder / "tls" / "keys").iterdir()
               for line in path.read_text().splitlines() if "PRIVATE KEY" not in line]
    secrets += [line.split(":", 1)[1] for line in
                (folder / "usrpwd" / "passwords.txt").read_text().splitlines()]
    assert len(secrets) >= 7 and not [secret for secret in secrets if secret.encode() in recorded]
    secured, clean = (Counter(m.topic for m in each.messages) for each in (log, plain))
    steps_of = lambda counts: {topic: count for topic, count in counts.items() if not topic.endswith("/status")}
    assert steps_of(secured) == steps_of(clean)  # statuses are also periodic: their number varies with time
    assert secured["dtpf/t-secured/entity/cloud"] == STEPS
    for layer in ("entity", "information", "system", "recorder"):  # the first and the last status at least
        assert secured[f"dtpf/t-secured/{layer}/status"] >= 2


def test_a_secure_folder_keeps_its_secrets_out_of_git(tmp_path, folder):
    """git status in a repository holding the folder lists none of its files (keys and passwords)."""
    import shutil
    import subprocess

    repository = tmp_path / "repo"
    repository.mkdir()
    shutil.copytree(folder, repository / "deploy")
    secure.export(folder / "tls", ["entity"], repository / "machine-b")
    (repository / "notes.txt").write_text("a file of the user's")
    git = shutil.which("git")
    if git is None:
        pytest.skip("git is not installed")
    subprocess.run([git, "init", "-q"], cwd=repository, check=True)
    listed = subprocess.run([git, "status", "--porcelain", "--untracked-files=all"], cwd=repository,
                            capture_output=True, text=True, check=True).stdout.split()
    assert "notes.txt" in listed and not [name for name in listed if name.startswith(("deploy", "machine-b"))]


def test_secure_init_writes_owner_only_files_and_refuses_a_full_folder(tmp_path, folder):
    modes = {path.relative_to(folder): stat.S_IMODE(path.stat().st_mode) for path in folder.rglob("*")}
    assert {mode for path, mode in modes.items() if (folder / path).is_file()} == {0o600}
    assert {mode for path, mode in modes.items() if (folder / path).is_dir()} == {0o700}
    for kind in ("tls", "usrpwd"):
        deployment = open_secure_dir(folder / kind)
        assert deployment.roles == ROLES and deployment.kind == kind
    with pytest.raises(FileExistsError, match="not empty"):
        secure.init(folder)
    # The router's certificate names loopback; each role's names the role (the ACL's subject).
    from cryptography import x509
    router_cert = x509.load_pem_x509_certificate((folder / "tls" / "certs" / "router.pem").read_bytes())
    names = router_cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "127.0.0.1" in {str(ip) for ip in names.get_values_for_type(x509.IPAddress)}
    for role in ROLES:
        cert = x509.load_pem_x509_certificate((folder / "tls" / "certs" / f"{role}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)[0].value == role


def test_a_secure_folder_that_does_not_fit_is_a_clear_error(tmp_path, folder):
    with pytest.raises(SecureError, match="not a secure folder"):
        open_secure_dir(tmp_path)
    with pytest.raises(BusError, match="does not fit the secure folder"):
        zenoh_config(secure=folder / "tls", role="entity", connect=["tcp/127.0.0.1:7447"])
    with pytest.raises(BusError, match="no role 'intruder'"):
        zenoh_config(secure=folder / "tls", role="intruder")
    with pytest.raises(BusError, match="needs --role"):
        zenoh_config(secure=folder / "tls")
    with pytest.raises(LaunchError, match="not a secure folder"):
        launch(RunConfig(steps=2), log_path=tmp_path / "x.mcap", secure=tmp_path)


def test_export_copies_only_the_files_of_the_roles_asked_for(tmp_path, folder):
    target = tmp_path / "machine-b"
    written = secure.export(folder / "tls", ["information", "system"], target)
    assert {path.relative_to(target).as_posix() for path in written} == {
        "dtpf-secure.json", "ca.pem", "information.json5", "system.json5", "certs/information.pem",
        "certs/system.pem", "keys/information.key", "keys/system.key", ".gitignore"}
    exported = open_secure_dir(target)
    assert exported.roles == ("information", "system")
    json.loads(role_config(exported, "system"))  # its paths resolve inside the exported folder
    with pytest.raises(SecureError, match="no role 'entity'"):
        role_config(exported, "entity")
    with pytest.raises(SecureError, match="no role 'intruder'"):
        secure.export(folder / "tls", ["system", "intruder"], tmp_path / "nothing")
    assert not (tmp_path / "nothing").exists()  # nothing written when a role is wrong


def test_dtpf_router_enforces_the_folder_and_stops_on_sigint(processes, folder):
    import signal

    deployment = open_secure_dir(folder / "tls")
    port = free_port()
    endpoint = deployment.endpoint("127.0.0.1", port)
    router = processes.start("router", ["-m", "dtpf.scripts.cli", "router", "--secure", str(folder), "--listen", endpoint])
    viewer = None
    deadline = time.monotonic() + 20
    while viewer is None:
        try:
            viewer = open_session(zenoh_config(secure=deployment, role="viewer", connect=[endpoint]))
        except BusError:
            assert time.monotonic() < deadline and router.poll() is None, processes.output(router)
            time.sleep(0.2)
    try:
        with pytest.raises(BusError, match="Unable to connect"):
            open_session(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
    finally:
        viewer.close()
    router.send_signal(signal.SIGINT)
    assert router.wait(timeout=10) == 0
    assert f"routing on {endpoint}" in processes.output(router)


def test_a_message_on_a_layers_key_must_name_that_layer_and_twin():
    """What the access control cannot see: the entity may put on its own keys, but not pass a message
    off there as another layer's or another twin's (services count it as a rejection)."""
    from dtpf.messages.models import Status

    def status(layer: str, twin: str = "t-own") -> bytes:
        return encode(Status(run_id="run", twin_id=twin, step=0, layer=layer, state="running", pid=1,
                             received=0, rejected=0))

    assert decode_for_key("dtpf/t-own/entity/status", status("entity")).layer.value == "entity"
    with pytest.raises(MessageError, match="does not belong on this key: layer 'system'"):
        decode_for_key("dtpf/t-own/entity/status", status("system"))
    with pytest.raises(MessageError, match="twin_id 't-other'"):
        decode_for_key("dtpf/t-own/entity/status", status("entity", twin="t-other"))


@contextlib.contextmanager
def secured_bus(path):
    """A router enforcing the secure folder ``path``: yields ``client(role)`` (a session of that role) and a list
    of declarations to undeclare; everything is closed at the end, pass or fail."""
    deployment = open_secure_dir(path)
    endpoint = deployment.endpoint("127.0.0.1", free_port())
    router = open_session(zenoh_config(secure=deployment, role="router", listen=[endpoint]))
    sessions, declared = [], []

    def client(role):
        sessions.append(open_session(zenoh_config(secure=deployment, role=role, connect=[endpoint])))
        return sessions[-1]

    try:
        yield client, declared
    finally:
        for thing in reversed(declared):
            thing.undeclare()
        for session in sessions:
            session.close()
        router.close()


@pytest.mark.parametrize("kind", ["tls", "usrpwd"])
def test_a_recorder_recovers_from_a_layers_cache_and_no_other_role_can_answer_for_it(folder, kind):
    """Zenoh's advanced publishers and subscribers talk on <key>/@adv/..., which '**' does not match: the access
    rules let a recorder ask the entity's cache for what it missed, and refuse a viewer's queryable that offers
    forged messages under the entity's keys."""
    with secured_bus(folder / kind) as (client, declared):
        key = "dtpf/t-cache/entity/estimate"
        entity = publisher(client("entity"), key, cache_samples=50)
        declared.append(entity)
        for step in range(1, 21):  # before the recorder subscribes: only the cache has them
            entity.put(f"step {step}".encode())
        viewer = client("viewer")
        declared.append(viewer.liveliness().declare_token(f"{key}/@adv/pub/forged/1/_"))
        declared.append(viewer.declare_queryable(f"{key}/@adv/pub/forged/1/_",
                                                 lambda query: query.reply(key, b"forged")))
        inbox = Inbox(client("recorder"), "dtpf/t-cache/**", recover=True)
        heard: list[bytes] = []
        deadline = time.monotonic() + 60.0
        while len(heard) < 20 and time.monotonic() < deadline:
            item = inbox.get(timeout=0.1)
            if item is not None and item.payload:
                heard.append(item.payload)
        time.sleep(0.5)  # a forged answer would have come with the cache's
        while (item := inbox.get(timeout=0)) is not None:
            heard.append(item.payload)
        assert heard == [f"step {step}".encode() for step in range(1, 21)]
        inbox.close()


@pytest.mark.parametrize("kind", ["tls", "usrpwd"])
def test_a_reader_on_another_host_gets_a_set_from_its_publisher_and_no_other_role_can_answer_for_it(folder, kind):
    """A set sent by reference is asked of its publisher's queryable <key>/@slot by a reader on another host;
    '**' does not match '@slot': the rules let every role ask, and only the set's own layer answer."""
    from dtpf.shell.shared_sets import SetPublisher, slot_key
    from dtpf.shell.slots import Reference

    with secured_bus(folder / kind) as (client, declared):
        key = "dtpf/t-slot/entity/particles"
        entity = client("entity")
        sets = SetPublisher(entity, key, publisher(entity, key))
        values = np.arange(40_000, dtype=float)
        sets.put_parts([b"HEADER!!", values], 8 + values.nbytes)
        declared.append(client("viewer").declare_queryable(
            slot_key(key), lambda query: query.reply(query.key_expr, b"forged".ljust(8 + values.nbytes))))
        writer = sets.writer.id
        recorder = client("recorder")
        answers = []
        deadline = time.monotonic() + 60.0
        while not answers and time.monotonic() < deadline:  # until the router knows the entity's queryable
            answers = [reply.ok.payload.to_bytes() for reply in
                       recorder.get(f"{slot_key(key)}?writer={writer};seq=1", timeout=5.0) if reply.ok is not None]
        assert answers == [b"HEADER!!" + values.tobytes()]
        assert Reference.parse(sets.writer.write([b"x"])).seq == 2
        sets.undeclare(drain=0)
