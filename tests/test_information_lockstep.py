"""The information layer's wait for the system layer's PS decision, without a bus.

A stand-in shell holds the inboxes and the system layer's liveliness, so that
the order in which a decision, a token and a particle set arrive is chosen
by the test, not by the machine's load.
"""
from __future__ import annotations

import logging
from collections import deque

import numpy as np
import pytest

from dtpf.entity import sources
from dtpf.information.service import TwinInformation
from dtpf.messages.config import RunConfig
from dtpf.messages.models import ParticleSet, ParticleSetKind, PSCommand, WeightState

N = 64


class StandInInbox:
    def __init__(self, key_expr: str):
        self.key_expr = key_expr
        self.items: deque = deque()

    def get(self, timeout=None):
        return self.items.popleft() if self.items else None

    def __len__(self) -> int:
        return len(self.items)

    def ring(self) -> None:
        pass


class StandInPresence:
    def __init__(self):
        self.alive: set[str] = set()


class StandInShell:
    """What :class:`TwinInformation` uses of a service shell; messages pass as objects."""

    def __init__(self, config: RunConfig):
        self.config = config
        self.presence = StandInPresence()
        self.log = logging.getLogger("dtpf.information")
        self.inboxes: dict[tuple[str, str], StandInInbox] = {}
        self.published: list = []
        self.rejected: list = []
        self.stopping = False

    def expect(self, shape) -> None:
        pass

    def inbox(self, layer: str, topic: str) -> StandInInbox:
        return self.inboxes.setdefault((layer, topic), StandInInbox(f"dtpf/{self.config.twin}/{layer}/{topic}"))

    def receive(self, item, expected):
        return item

    def take(self, inbox, expected):
        return inbox.get(timeout=0)

    def reject(self, reason, detail=None, key=None) -> None:
        self.rejected.append(detail or reason)

    def publish(self, message, payload=None) -> None:
        self.published.append(message)

    def header(self, step: int) -> dict:
        return {"run_id": self.config.run_id, "twin_id": self.config.twin, "step": step}

    def answered(self) -> list[int]:
        """The steps whose preprocessed set went out, in order."""
        return [m.step for m in self.published if isinstance(m, ParticleSet)]


@pytest.fixture
def twin():
    config = RunConfig(particles=N, steps=10, seed=5, twin="lock-1", policy="rule", ps=0.81)
    shell = StandInShell(config)
    return shell, TwinInformation(shell, config, sources.load_model(config), timeout=2.0)


def send_set(shell: StandInShell, step: int) -> None:
    rng = np.random.default_rng(step)
    weights = rng.random(N) + 0.1
    shell.inbox("entity", "particles").items.append(ParticleSet(
        **shell.header(step), kind=ParticleSetKind.PROPAGATED, particles=rng.normal(size=(N, 1)),
        weights=weights / weights.sum(), observation=[0.5]))


def send_decision(shell: StandInShell, step: int, ps: float) -> None:
    shell.inbox("system", "ps").items.append(PSCommand(
        **shell.header(step), ps=ps, applies_from_step=step + 1, policy="rule", reason="test"))


def test_a_set_waits_for_the_decision_of_the_step_before_while_the_system_token_has_not_come(twin):
    # The system layer's token can reach a fleet's information service steps after its first decisions do;
    # a set that went on without the decision then used the old PS and left the twin's solo run.
    shell, info = twin
    send_set(shell, 1)
    assert info.poll(now=0.0) is None and shell.answered() == [1]
    for step in (2, 3, 4):
        send_set(shell, step)
        assert info.poll(now=float(step)) == pytest.approx(step + 2.0), step  # waits, up to the timeout
        assert shell.answered() == list(range(1, step)), step
        send_decision(shell, step - 1, ps=0.5 + 0.1 * step)
        assert info.poll(now=step + 0.5) is None
        assert shell.answered() == list(range(1, step + 1))
        assert shell.published[-2].ps == pytest.approx(0.5 + 0.1 * step)  # the decision applied
    assert shell.rejected == []


def test_a_system_layer_never_seen_is_waited_for_once_then_the_last_ps_is_kept(twin, caplog):
    shell, info = twin
    send_set(shell, 1)
    info.poll(now=0.0)
    send_set(shell, 2)
    assert info.poll(now=1.0) == pytest.approx(3.0)
    with caplog.at_level(logging.WARNING, logger="dtpf.information"):
        assert info.poll(now=3.0) is None  # the deadline passed
    assert shell.answered() == [1, 2] and shell.published[-2].ps == pytest.approx(0.81)
    assert "no PS decision of step 1 within 2.0 s, keeping PS = 0.81" in caplog.text
    send_set(shell, 3)
    assert info.poll(now=3.1) is None and shell.answered() == [1, 2, 3]  # not waited for again


def test_a_system_layer_seen_and_gone_is_not_waited_for(twin, caplog):
    shell, info = twin
    shell.presence.alive.add("system")
    send_set(shell, 1)
    info.poll(now=0.0)
    send_set(shell, 2)
    assert info.poll(now=1.0) == pytest.approx(3.0)
    send_decision(shell, 1, ps=0.6)
    assert info.poll(now=1.5) is None
    shell.presence.alive.discard("system")
    with caplog.at_level(logging.WARNING, logger="dtpf.information"):
        send_set(shell, 3)
        assert info.poll(now=2.0) is None
    assert shell.answered() == [1, 2, 3] and shell.published[-2].ps == pytest.approx(0.6)
    assert "step 3: the system layer is gone, keeping PS = 0.6" in caplog.text
    weight_states = [m for m in shell.published if isinstance(m, WeightState)]
    assert [m.step for m in weight_states] == [1, 2, 3]
