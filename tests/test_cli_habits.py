"""Small things a newcomer hit (issue 14): --version, dtpf play with nobody to hear it, dtpf plot on a cut log."""
from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import ROOT
from messages.config import RunConfig
from scripts.launch import launch


def dtpf(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "scripts.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("habits") / "run.mcap"
    result = launch(RunConfig(particles=100, steps=10, twin="t-habits"), log_path=path, notify=lambda text: None)
    assert result.exit_codes["entity"] == 0
    return path


def test_version():
    import importlib.metadata

    done = dtpf("--version")
    assert done.returncode == 0
    assert done.stdout.strip() == f"dtpf {importlib.metadata.version('dtpf')}"


def test_play_without_connect_says_nobody_can_hear_it(small_log):
    done = dtpf("play", str(small_log), "--rate", "0", "--wait", "0.2", "-q")
    assert done.returncode == 0, done.stderr
    assert "warning: no --connect" in done.stderr
    published = int(done.stderr.split("published ")[1].split()[0])
    assert f"{published} of them had no subscriber" in done.stderr


def test_plot_on_a_cut_log_says_what_is_missing_and_points_to_recover(small_log, tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(small_log.read_bytes()[: small_log.stat().st_size // 2])
    done = dtpf("plot", str(cut), "-o", str(tmp_path / "cut.png"))
    assert done.returncode != 0
    assert "Traceback" not in done.stderr
    assert "log cut short" in done.stderr and f"dtpf recover {cut} -o fixed.mcap" in done.stderr
