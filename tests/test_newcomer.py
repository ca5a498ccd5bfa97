"""What a new user met first: a silent slow first launch, progress bars in piped output, a sensor
command that could not reach its twin, position-only truth refused, ``dtpf cat`` without values, a
NaN without its step, ``dtpf plot`` fixed on x[0], and comments that cited what the repository lacks."""
from __future__ import annotations

import io
import math
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT
from dtpf.entity import models
from dtpf.entity.filter import FilterError, ParticleFilter
from dtpf.entity.observations import ObservationError, read_observations
from dtpf.messages.codec import encode
from dtpf.messages.config import RunConfig
from dtpf.messages.keys import key_for
from dtpf.messages.models import Estimate, ParticleSet, ParticleSetKind, Status
from dtpf.recording.writer import McapRecording
from dtpf.scripts import cli
from dtpf.scripts.console import ProgressBar, TaskProgress
from dtpf.scripts.logs import plot as plot_log
from dtpf.scripts.logs.plot import PlotError, RunLog, plot_run


def dtpf_command(*args: str) -> list[str]:
    """The arguments of ``dtpf ARGS`` for the ``processes`` fixture (which prepends the interpreter)."""
    return ["-m", "dtpf.scripts.cli", *args]


def wait_for_output(processes, process, pattern: str, timeout: float) -> re.Match:
    """The first match of ``pattern`` in the process's output, waiting up to ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = re.search(pattern, processes.output(process))
        if found:
            return found
        if process.poll() is not None:
            found = re.search(pattern, processes.output(process))
            assert found, f"{process.name} exited {process.returncode} without {pattern!r}:\n{processes.output(process)}"
            return found
        time.sleep(0.05)
    raise AssertionError(f"no {pattern!r} within {timeout} s:\n{processes.output(process)}")


def wait_exit(process, timeout: float) -> int:
    try:
        return process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"{process.name} still running after {timeout} s") from None


# --- 1. the first launch says it compiles ------------------------------------------------

def _fake_cache(folder: Path, older_than_source: bool = False) -> None:
    """Index files of numba's cache for every kernel module, as numba names them, in ``folder``."""
    import importlib.util

    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    for module in (*cli.KERNEL_MODULES, cli.GROWTH_KERNELS):
        source = Path(importlib.util.find_spec(module).origin)
        index = folder / f"{source.parent.name}_0123abcd" / f"{source.stem}.kernel-10.{tag}.nbi"
        index.parent.mkdir(parents=True, exist_ok=True)
        index.write_bytes(b"index")
        if older_than_source:
            stamp = source.stat().st_mtime - 60
            os.utime(index, (stamp, stamp))


def test_kernels_cold_on_an_empty_or_stale_cache_and_warm_on_a_fresh_one(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "empty"))
    assert "dtpf.entity._merge" in cli.kernels_cold()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "stale"))
    _fake_cache(tmp_path / "stale", older_than_source=True)
    assert set(cli.kernels_cold()) == {*cli.KERNEL_MODULES, cli.GROWTH_KERNELS}
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "fresh"))
    _fake_cache(tmp_path / "fresh")
    assert cli.kernels_cold() == []


def test_launch_on_a_cold_cache_says_it_compiles_once(processes, tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    launcher = processes.start("launch", dtpf_command("launch", "--steps", "2", "-q", "-o", str(tmp_path / "run.mcap")))
    wait_for_output(processes, launcher, r"compiling numba kernels on first use \(once per install\)", 60)
    line = [text for text in processes.output(launcher).splitlines() if "compiling numba" in text]
    assert len(line) == 1


# --- 2. progress only on a terminal ------------------------------------------------------

class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_writes_only_on_a_terminal_unless_forced(monkeypatch):
    monkeypatch.delenv("DTPF_PROGRESS", raising=False)
    piped, terminal, forced = io.StringIO(), Terminal(), io.StringIO()
    for stream, bar in ((piped, ProgressBar(piped)), (terminal, ProgressBar(terminal)),
                        (forced, ProgressBar(forced, force=True))):
        for k in range(1, 11):
            bar(k, 10)
    assert piped.getvalue() == ""
    assert "step 10/10" in terminal.getvalue() and "step 10/10" in forced.getvalue()
    monkeypatch.setenv("DTPF_PROGRESS", "1")
    environment = io.StringIO()
    ProgressBar(environment)(10, 10)
    assert "step 10/10" in environment.getvalue()


def test_task_progress_is_quiet_off_a_terminal(monkeypatch, capsys):
    monkeypatch.delenv("DTPF_PROGRESS", raising=False)
    progress = TaskProgress("table", 10)
    for k in range(11):
        progress(k)
    assert capsys.readouterr().err == ""
    forced = TaskProgress("table", 10, force=True)
    forced(10)
    assert "table: 10/10 runs" in capsys.readouterr().err


def test_dtpf_run_piped_has_no_progress_but_its_summary():
    env = {k: v for k, v in os.environ.items() if k != "DTPF_PROGRESS"}
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "run", "--steps", "5", "-n", "200"],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "step" not in done.stderr and "[#" not in done.stderr
    assert "RMSE" in done.stdout and "T = 5" in done.stdout


# --- 3. the sensor command a live launch prints works as printed -------------------------

def test_live_launch_prints_a_sensor_command_that_reaches_the_twin(processes, tmp_path):
    cold = cli.kernels_cold()
    launcher = processes.start("launch", dtpf_command("launch", "--policy", "fixed", "--observations", "live", "--seed", "3", "-n", "200",
                                                      "-q", "-o", str(tmp_path / "live.mcap")))
    found = wait_for_output(processes, launcher, r"another terminal: (dtpf sensor [^\n]*)\n", 60)
    words = shlex.split(found.group(1))
    assert words[:2] == ["dtpf", "sensor"]
    assert "--connect" in words and re.fullmatch(r"tcp/127\.0\.0\.1:\d+", words[words.index("--connect") + 1])
    assert words[words.index("--twin") + 1] == "ungm-1" and words[words.index("--seed") + 1] == "3"
    sensor = processes.start("sensor", dtpf_command(*words[1:], "--steps", "4", "--rate", "0"))
    assert wait_exit(launcher, 180) == 0, processes.output(launcher)
    assert wait_exit(sensor, 60) == 0, processes.output(sensor)
    output = processes.output(launcher)
    assert re.search(r"^steps\s+4\b", output, re.M), output
    if not cold:
        assert "compiling numba" not in output


def test_sensor_command_names_model_secure_role_and_run():
    from dtpf.scripts.sensor import sensor_command

    config = RunConfig(model="pkg.mod:MODEL", twin="cv", run_id="r7", observations="live")
    words = shlex.split(sensor_command(config, "tls/127.0.0.1:7447", "/tmp/my secure"))
    assert words == ["dtpf", "sensor", "--model", "pkg.mod:MODEL", "--twin", "cv", "--run-id", "r7",
                     "--connect", "tls/127.0.0.1:7447", "--secure", "/tmp/my secure", "--role", "sensor"]


# --- 4. truth of a part of the state -----------------------------------------------------

def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_position_only_truth_is_the_leading_components(tmp_path):
    table = read_observations(write(tmp_path / "pos.csv", "z0,z1,truth_x,truth_y\n1,2,3,4\n5,6,7,8\n"),
                              obs_dim=2, state_dim=4)
    assert table.truth.tolist() == [[3.0, 4.0], [7.0, 8.0]]
    assert table.truth_components == (0, 1) and not table.covers(4) and table.head(1).truth_components == (0, 1)


def test_truth_columns_numbered_by_component(tmp_path):
    table = read_observations(write(tmp_path / "n.csv", "z,truth_x3,truth_x1\n1,2,3\n"), obs_dim=1, state_dim=4)
    assert table.truth_components == (3, 1)
    np.savez(tmp_path / "a.npz", z=np.ones((3, 2)), x=np.ones((3, 2)))
    assert read_observations(tmp_path / "a.npz", obs_dim=2, state_dim=4).truth_components == (0, 1)


@pytest.mark.parametrize("header, expected", [
    ("z,truth_a,truth_b,truth_c,truth_d,truth_e", "5 truth columns (truth_a, truth_b, truth_c, truth_d, truth_e), "
                                                   "more than the model's state has (4 dimensions)"),
    ("z,truth_x0,truth_y", "mix names numbered by state component with names that are not (truth_y)"),
    ("z,truth_0,truth_7", "truth column truth_7 names state component 7, the model's state has 4 dimensions"),
    ("z,truth_1,true_1", "name a state component twice"),
])
def test_truth_that_does_not_fit_the_state_is_refused_in_one_line(tmp_path, header, expected):
    path = write(tmp_path / "bad.csv", header + "\n" + ",".join(["1"] * len(header.split(","))) + "\n")
    with pytest.raises(ObservationError) as caught:
        read_observations(path, obs_dim=1, state_dim=4)
    assert expected in str(caught.value) and "\n" not in str(caught.value)


def _four_d_run(tmp_path: Path) -> tuple[Path, Path, np.ndarray]:
    model = write(tmp_path / "m4.py", "from dtpf.entity.models import DriftModel\nMODEL = DriftModel(dim=4)\n")
    truth, z = models.DriftModel(dim=4).simulate(15, np.random.default_rng(5))
    rows = ["z0,z1,z2,z3,truth_x,truth_y"] + [",".join(repr(float(v)) for v in (*o, *t[:2])) for o, t in zip(z, truth)]
    return model, write(tmp_path / "pos.csv", "\n".join(rows) + "\n"), truth


def test_run_rmse_covers_the_components_with_truth(tmp_path):
    from dtpf.scripts.inprocess import run

    model, observations, truth = _four_d_run(tmp_path)
    result = run(RunConfig(model=f"{model}:MODEL", observations=str(observations), particles=300))
    assert result.components == (0, 1) and result.partial_truth
    expected = math.sqrt(np.mean((result.means[:, :2] - truth[:, :2]) ** 2))
    assert result.rmse == pytest.approx(expected, rel=1e-12)
    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "run", "--policy", "fixed", "--model", f"{model}:MODEL",
                           "--observations", str(observations), "-n", "300", "-q"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"RMSE            {expected:.4f} over x[0], x[1] of the state's 4 components " \
           f"(truth columns truth_x, truth_y)" in done.stdout


# --- 5. dtpf cat shows values ------------------------------------------------------------

def test_cat_text_shows_the_main_fields_and_summarises_arrays(tmp_path, capsys):
    estimate = Estimate(run_id="r", twin_id="t", step=3, mean=[1.23456, -2.0], var=[0.5, 0.25],
                        lower=[0.0, -3.0], upper=[2.5, -1.0], ess=812.5, ess_ratio=0.8125, resampled=True,
                        degraded=False, truth=[1.3, -2.1], observation=[1.2], ps=0.81)
    particles = np.linspace(-1.0, 4.0, 20).reshape(10, 2)
    cloud = ParticleSet(run_id="r", twin_id="t", step=3, kind=ParticleSetKind.PROPAGATED, observation=[1.2],
                        particles=particles, weights=np.full(10, 0.1))
    path = tmp_path / "run.mcap"
    with McapRecording(path) as recording:
        for message in (estimate, cloud):
            recording.write(key_for(message), encode(message))
    assert cli.main(["cat", str(path), "--steps", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    assert "step 3 [Estimate]" in lines[0]
    for shown in ("mean=[1.235, -2]", "ess=812.5", "truth=[1.3, -2.1]", "ps=0.81", "resampled=true"):
        assert shown in lines[0]
    assert "particles=(10x2 array, -1 .. 4)" in lines[1] and "weights=(10 array, 0.1 .. 0.1)" in lines[1]


def test_cat_text_cuts_long_lists():
    from dtpf.scripts.logs.select import as_text

    status = Status(run_id="r", twin_id="t", step=0, layer="entity", state="running", pid=1, received=2,
                    rejected=0, last_error="x" * 500)
    text = as_text(status)
    assert "state=running" in text and "received=2" in text and len(text) < 200


# --- 6. a NaN log-likelihood names its step ----------------------------------------------

def test_nan_log_likelihood_names_the_step_and_observation():
    class Broken(models.GrowthModel):
        def log_likelihood(self, particles, observation, k):
            out = super().log_likelihood(particles, observation, k)
            return np.full_like(out, np.nan) if k == 3 else out

    with pytest.raises(FilterError) as caught:
        list(ParticleFilter(Broken(), np.array([0.5, 1.0, 2.25, 3.0]), 50))
    message = str(caught.value)
    assert message.startswith("step 3: ") and "NaN" in message and "z = [2.25]" in message


# --- 7. dtpf plot draws a chosen component -----------------------------------------------

def _two_d_log(path: Path) -> Path:
    with McapRecording(path) as recording:
        for k in range(1, 6):
            message = Estimate(run_id="r", twin_id="t", step=k, mean=[0.1 * k, 10.0 + k], var=[1.0, 4.0],
                               lower=[0.1 * k - 1.96, 10.0 + k - 3.92], upper=[0.1 * k + 1.96, 10.0 + k + 3.92],
                               ess=50.0, ess_ratio=0.5, resampled=True, degraded=False,
                               truth=[0.1 * k, 10.5 + k], observation=[1.0, 11.0 + k])
            recording.write(key_for(message), encode(message))
    return path


def test_plot_component_draws_that_component(tmp_path):
    run = plot_log.read_log(_two_d_log(tmp_path / "two.mcap"))
    figure = plot_run(run, component=1)
    state = figure.axes[0]
    assert "component x[1] of d = 2" in state.get_title(loc="left")
    estimate = [line for line in state.get_lines() if line.get_label().startswith("estimate")][0]
    assert estimate.get_ydata().tolist() == [10.0 + k for k in range(1, 6)]
    with pytest.raises(PlotError, match=r"--component 2: the state has 2 components \(0 \.\. 1\)"):
        plot_run(run, component=2)


def test_plot_component_option(tmp_path, capsys):
    log = _two_d_log(tmp_path / "two.mcap")
    assert plot_log.main([str(log), "-o", str(tmp_path / "x1.png"), "--component", "1"]) == 0
    assert (tmp_path / "x1.png").stat().st_size > 0
    assert plot_log.main([str(log), "-o", str(tmp_path / "x5.png"), "--component", "5"]) == 2
    error = capsys.readouterr().err.strip()
    assert error == "dtpf plot: error: --component 5: the state has 2 components (0 .. 1)"
    with pytest.raises(SystemExit) as caught:
        plot_log.main([str(log), "--component", "-1"])
    assert caught.value.code == 2


# --- 8. product comments state facts, not their history ----------------------------------

#: Files another engineer owns; their comments are theirs to change.
_NOT_OURS = {"scripts/record.py", "scripts/secure.py", "dtpf/shell/secure.py"}
_HISTORY = re.compile(r"issue \d+|\b(DESIGN|ECOSYSTEM|PERF-ANCHORS|STYLE)\.md|this stop|the code before|ran here",
                      re.IGNORECASE)


def test_product_code_cites_no_issue_numbers_or_missing_documents():
    found = []
    for folder in ("entity", "information", "system", "messages", "scripts", "dtpf"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            relative = path.relative_to(ROOT).as_posix()
            if relative in _NOT_OURS or relative.startswith("dtpf/recording/"):
                continue
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if _HISTORY.search(line):
                    found.append(f"{relative}:{number}: {line.strip()}")
    assert not found, "\n".join(found)
