"""Small things a newcomer hit: --version, dtpf play with nobody to hear it, dtpf plot on a cut log."""
from __future__ import annotations

import subprocess
import sys

import pytest

from dtpf.messages.config import RunConfig
from dtpf.scripts.launch import launch

from conftest import ROOT


def dtpf(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("habits") / "run.mcap"
    # The lockstep timeout of the other launch tests: under a loaded suite a 2 s wait was once too short, a
    # step went on degraded and the log's RMSE was not the in-process run's.
    result = launch(RunConfig(particles=100, steps=10, twin="t-habits"), log_path=path, timeout=5.0,
                    notify=lambda text: None)
    assert result.exit_codes["entity"] == 0
    assert not any(e.degraded for e in result.estimates)
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


def test_cat_json_gives_every_chosen_message_with_particle_arrays(small_log):
    import json

    done = dtpf("cat", str(small_log), "--topics", "entity/particles", "entity/estimate", "--steps", "3:5", "--json")
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert sorted((line["topic"].rsplit("/", 1)[1], line["message"]["step"]) for line in lines) == \
        sorted((topic, step) for topic in ("particles", "estimate") for step in (3, 4, 5))
    sets = [line["message"] for line in lines if line["topic"].endswith("/particles")]
    assert all(len(s["particles"]) == 100 and len(s["weights"]) == 100 for s in sets)
    assert abs(sum(sets[0]["weights"]) - 1.0) < 1e-9


def test_info_json_holds_the_same_counts(small_log):
    import json

    info = json.loads(dtpf("info", "--json", str(small_log)).stdout)
    assert info["complete"] is True
    estimates = next(t for t in info["topics"] if t["topic"].endswith("/entity/estimate"))
    assert estimates["count"] == 10 and estimates["first_step"] == 1 and estimates["last_step"] == 10


def test_filter_writes_a_smaller_log_that_verify_passes_on_its_steps(small_log, tmp_path):
    part = tmp_path / "part.mcap"
    done = dtpf("filter", str(small_log), "-o", str(part), "--steps", "2:6")
    assert done.returncode == 0, done.stderr
    verified = dtpf("verify", str(part))
    assert verified.returncode == 0, verified.stdout
    assert "OK: 5 steps reproduced exactly" in verified.stdout
    summary = dtpf("summary", str(part)).stdout
    assert "steps         5 of 10 (2-6)" in summary
    assert dtpf("filter", str(part), "-o", str(part)).returncode == 2


def test_play_from_a_step_starts_at_its_first_message(small_log):
    done = dtpf("play", str(small_log), "--start-step", "9", "--rate", "0", "--wait", "0", "-q")
    assert done.returncode == 0, done.stderr
    played = int(done.stderr.split("playing ")[1].split()[0])
    everything = int(dtpf("play", str(small_log), "--rate", "0", "--wait", "0", "-q").stderr.split("playing ")[1].split()[0])
    # What comes from the first message of step 9 on, in the log's order (the status messages a process sends
    # while it waits are step 0 and their number depends on timing: counted from the log, not assumed).
    from dtpf.messages.codec import decode_for_key
    from dtpf.recording.logfile import read_log

    items = read_log(small_log).messages
    first = next(i for i, item in enumerate(items) if decode_for_key(item.topic, item.data).step >= 9)
    assert 0 < played == len(items) - first < everything


def test_a_recorded_configuration_runs_again_from_its_file_and_flags_override_it(small_log, tmp_path):
    toml = tmp_path / "run.toml"
    done = dtpf("summary", str(small_log), "--config-out", str(toml))
    assert done.returncode == 0, done.stderr
    assert "particles = 100" in toml.read_text() and 'twin = "t-habits"' in toml.read_text()
    recorded = dtpf("summary", str(small_log)).stdout.split("RMSE")[1].split()[0]
    again = dtpf("run", "--config", str(toml), "-q")
    assert again.returncode == 0, again.stderr
    assert f"RMSE            {recorded}" in again.stdout  # the same run, number for number
    smaller = dtpf("run", "--config", str(toml), "--particles", "50", "-q")
    assert "N = 50" in smaller.stdout
    (tmp_path / "bad.toml").write_text("particles = 100\nparticle = 5\n")
    bad = dtpf("run", "--config", str(tmp_path / "bad.toml"))
    assert bad.returncode == 2 and "keys that are not run settings: particle" in bad.stderr


def test_layout_names_the_twins_topics_in_its_panels(tmp_path):
    import json

    out = tmp_path / "layout.json"
    done = dtpf("layout", "--twin", "t-lay", "-o", str(out))
    assert done.returncode == 0, done.stderr
    text = out.read_text()
    layout = json.loads(text)
    assert layout["content"]["type"] == "split"
    panels = []

    def walk(node):
        if node.get("type") == "panel":
            panels.append(node["panelType"])
        for item in node.get("items", []):
            walk(item["content"])

    walk(layout["content"])
    assert sorted(panels) == ["Image", "Plot", "Plot", "Plot", "ThreeDee"]
    strings = set()

    def strings_of(node):
        if isinstance(node, dict):
            for key, value in node.items():
                strings.add(key)
                strings_of(value)
        elif isinstance(node, list):
            for value in node:
                strings_of(value)
        elif isinstance(node, str):
            strings.add(node)

    strings_of(layout)
    for topic in ('"dtpf/t-lay/entity/estimate".mean[0]', "dtpf/t-lay/entity/cloud", "dtpf/t-lay/entity/frame",
                  "dtpf/t-lay/entity/annotations", '"dtpf/t-lay/entity/forecast_band".ahead[:].upper[0]'):
        assert topic in strings, topic


def test_the_help_of_dtpf_and_of_every_command_formats():
    """``dtpf --help`` lists every command and each command's help formats (a bare '%' in a help text
    made argparse raise a TypeError instead of printing the help)."""
    import argparse

    from dtpf.scripts.cli import build_parser

    parser = build_parser()
    top = parser.format_help()
    (commands,) = [action for action in parser._actions if isinstance(action, argparse._SubParsersAction)]
    assert len(commands.choices) >= 10
    for name, command in commands.choices.items():
        assert name in top
        assert command.format_help().startswith("usage: "), name
