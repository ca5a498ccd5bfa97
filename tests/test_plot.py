"""``dtpf plot``: the figure of a recorded run, from a real launch and from made-up logs."""
from __future__ import annotations

import struct
import subprocess
import sys

import numpy as np
import pytest
from mcap.reader import make_reader

from dtpf.messages.codec import encode
from dtpf.messages.config import RunConfig
from dtpf.messages.keys import key_for
from dtpf.messages.models import Estimate, ParticleSet, PSCommand
from dtpf.recording.writer import McapRecording
from dtpf.scripts.launch import launch
from dtpf.scripts.logs import plot as plot_log
from dtpf.scripts.logs.plot import FIGSIZE, PlotError, RunLog, plot_run, read_log

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
TWIN = "t-plot"
STEPS = 20
N = 200


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """A log with DT preprocessing and one without, from real launches (about 4 s each)."""
    from types import SimpleNamespace

    from dtpf.recording.logfile import read_log as read_recording

    folder = tmp_path_factory.mktemp("plot")
    runs = {}
    for name, preprocess in (("dt", True), ("plain", False)):
        # The lockstep timeout of the other launch tests: a step of a loaded machine needs more than 2 s at times.
        result = launch(RunConfig(particles=N, steps=STEPS, twin=TWIN, preprocess=preprocess),
                        log_path=folder / f"{name}.mcap", timeout=5.0)
        assert result.failure is None, result.failure
        # What the plots draw is the log: its estimates, every step once.
        estimates = sorted((m for _, m in read_recording(result.log_path).decoded(
            lambda topic: topic.endswith("/entity/estimate"))), key=lambda e: e.step)
        assert [e.step for e in estimates] == list(range(1, STEPS + 1)), f"the {name} log lacks steps"
        errors = np.array([np.subtract(e.mean, e.truth) for e in estimates])
        runs[name] = SimpleNamespace(log_path=result.log_path, estimates=estimates,
                                     rmse=float(np.sqrt(np.mean(errors ** 2))))
    return runs


def png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path} is not a PNG: starts with {data[:8]!r}"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def titles(figure) -> list[str]:
    return [ax.get_title(loc="left") + ax.get_title() for ax in figure.axes]


# --- the command on real logs ------------------------------------------------

def test_plot_command_writes_a_png_of_the_expected_size(logs, tmp_path, capsys):
    out = tmp_path / "deep" / "run.png"
    assert plot_log.main([str(logs["dt"].log_path), "-o", str(out), "--dpi", "50"]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    assert png_size(out) == (round(FIGSIZE[0] * 50), round(FIGSIZE[1] * 50))


def test_default_output_is_the_log_with_png_suffix_at_default_dpi(logs, tmp_path):
    log = tmp_path / "copy.mcap"
    log.write_bytes(logs["dt"].log_path.read_bytes())
    assert plot_log.main([str(log)]) == 0
    assert png_size(tmp_path / "copy.png") == (round(FIGSIZE[0] * 100), round(FIGSIZE[1] * 100))


def test_figure_has_every_panel(logs):
    run = read_log(logs["dt"].log_path, steps_at=[5, 15])
    figure = plot_run(run, steps_at=[5, 15])
    axes = figure.axes
    assert len(axes) == 3 + 2 * 2, titles(figure)
    state, error, health, *particles = axes
    assert "estimate" in state.get_title(loc="left") and "95%" in state.get_title(loc="left")
    assert state.get_xlabel() == "time step k" and state.get_ylabel() == "state x"
    labels = state.get_legend_handles_labels()[1]
    assert any("truth" in label for label in labels) and any("observation" in label for label in labels)
    assert "Error" in error.get_title(loc="left") and "RMSE" in error.get_title(loc="left")
    assert any("half-width" in label for label in error.get_legend_handles_labels()[1])
    assert "ESS/N" in health.get_title(loc="left") and "PS" in health.get_title(loc="left")
    assert health.get_ylabel() == "ESS/N, PS"
    assert [("before" in ax.get_title(), "after" in ax.get_title()) for ax in particles] == [
        (True, False), (False, True), (True, False), (False, True)]
    assert "k = 5" in particles[0].get_title() and "k = 15" in particles[2].get_title()
    assert all("particle value" in ax.get_xlabel() for ax in particles[1::2])
    assert "entity/particles" in particles[0].get_ylabel()
    assert "information/preprocessed" in particles[1].get_ylabel()
    suptitle = figure.get_suptitle()
    for fact in (f"twin {TWIN}", f"N = {N}", f"{STEPS} steps", f"RMSE {logs['dt'].rmse:.3f}", "ungm", "PS 0.81"):
        assert fact in suptitle, (fact, suptitle)


def test_figure_draws_the_logged_numbers(logs):
    run = read_log(logs["dt"].log_path, steps_at=[10])
    figure = plot_run(run, steps_at=[10])
    state, _, health, before, after = figure.axes
    means = [e.mean[0] for e in logs["dt"].estimates]
    estimate_line = next(line for line in state.lines if "estimate" in line.get_label())
    np.testing.assert_allclose(estimate_line.get_ydata(), means)
    ess_line = next(line for line in health.lines if line.get_label().startswith("ESS/N"))
    np.testing.assert_allclose(ess_line.get_ydata(), [e.ess_ratio for e in logs["dt"].estimates])
    # The processed particles (red) are exactly the ones the information layer moved.
    preprocessed = run.preprocessed[10]
    processed = next(c for c in after.collections if c.get_label().startswith("processed"))
    assert len(processed.get_offsets()) == preprocessed.n_processed > 0
    kept = sum(len(c.get_offsets()) for c in after.collections if c.get_label().startswith("large"))
    assert kept + preprocessed.n_processed == N
    assert sum(len(c.get_offsets()) for c in before.collections) == N


def test_default_particle_steps_are_three_evenly_spaced(logs):
    run = read_log(logs["dt"].log_path)
    assert sorted(run.propagated) == sorted(run.preprocessed) == plot_log.default_steps(run)
    steps = plot_log.default_steps(run)
    assert len(steps) == 3 and 1 < steps[0] < steps[1] < steps[2] < STEPS
    assert max(np.diff(steps)) - min(np.diff(steps)) <= 1
    # Every set in the log is counted (the recorder may miss one at the start, so compare with the summary).
    with open(logs["dt"].log_path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    counts = {channel.topic: summary.statistics.channel_message_counts.get(i, 0)
              for i, channel in summary.channels.items()}
    assert run.propagated_count == counts[f"dtpf/{TWIN}/entity/particles"] > 0
    assert run.preprocessed_count == counts[f"dtpf/{TWIN}/information/preprocessed"] > 0


def test_log_without_preprocessing_says_so_in_the_particle_panel(logs, tmp_path):
    out = tmp_path / "plain.png"
    assert plot_log.main([str(logs["plain"].log_path), "-o", str(out)]) == 0
    png_size(out)
    run = read_log(logs["plain"].log_path)
    figure = plot_run(run)
    assert len(figure.axes) == 4
    panel = figure.axes[3]
    assert "before" in panel.get_title(loc="left") and "after" in panel.get_title(loc="left")
    text = " ".join(t.get_text() for t in panel.texts)
    assert "No particle sets" in text and "--no-preprocess" in text
    assert "no preprocessing" in figure.get_suptitle()


# --- errors --------------------------------------------------------------------

def write_log(path, messages):
    with McapRecording(path) as recording:
        for message in messages:
            recording.write(key_for(message), encode(message))
    return path


def estimate(twin: str, step: int, **extra) -> Estimate:
    fields = dict(run_id="r", twin_id=twin, step=step, mean=[0.5 * step], var=[1.0], lower=[0.5 * step - 1.96],
                  upper=[0.5 * step + 1.96], ess=50.0, ess_ratio=0.5, resampled=True, degraded=False,
                  truth=[0.5 * step + 0.3], observation=[1.0], ps=0.81)
    fields.update(extra)
    return Estimate(**fields)


@pytest.mark.parametrize("content, expected", [
    (None, "no such file"),
    (b"", "is empty"),
    (b"step,mean\n1,0.5\n", "not an MCAP file"),
])
def test_unreadable_file_exits_1_with_a_clear_message(tmp_path, capsys, content, expected):
    log = tmp_path / "bad.mcap"
    if content is not None:
        log.write_bytes(content)
    assert plot_log.main([str(log), "-o", str(tmp_path / "out.png")]) == 1
    err = capsys.readouterr().err
    assert expected in err and str(log) in err
    assert not (tmp_path / "out.png").exists()


def test_truncated_log_exits_1(logs, tmp_path, capsys):
    log = tmp_path / "cut.mcap"
    log.write_bytes(logs["dt"].log_path.read_bytes()[:5000])
    assert plot_log.main([str(log), "-o", str(tmp_path / "out.png")]) == 1
    assert "cut short" in capsys.readouterr().err


def test_log_without_estimates_exits_1(tmp_path, capsys):
    command = PSCommand(run_id="r", twin_id="only-ps", step=1, ps=0.5, applies_from_step=2, policy="fixed",
                        reason="test")
    log = write_log(tmp_path / "ps.mcap", [command])
    assert plot_log.main([str(log), "-o", str(tmp_path / "out.png")]) == 1
    err = capsys.readouterr().err
    assert "no estimates" in err and "system/ps" in err


def test_twin_choice(tmp_path, capsys):
    log = write_log(tmp_path / "two.mcap", [estimate(twin, k) for k in (1, 2, 3) for twin in ("b-twin", "a-twin")])
    out = tmp_path / "out.png"
    assert plot_log.main([str(log), "-o", str(out)]) == 2
    assert "2 twins: a-twin, b-twin" in capsys.readouterr().err
    assert plot_log.main([str(log), "-o", str(out), "--twin", "zz"]) == 2
    assert "twin 'zz' is not in" in capsys.readouterr().err
    assert not out.exists()
    assert plot_log.main([str(log), "-o", str(out), "--twin", "b-twin"]) == 0
    png_size(out)
    assert read_log(log, twin="a-twin").twin == "a-twin"


def test_bad_options_exit_2(logs, tmp_path, capsys):
    log = str(logs["dt"].log_path)
    out = str(tmp_path / "out.png")
    assert plot_log.main([log, "-o", out, "--steps-at", "3", str(STEPS + 5)]) == 2
    assert f"no estimate at step {STEPS + 5}" in capsys.readouterr().err
    assert plot_log.main([log, "-o", out, "--dpi", "0"]) == 2
    assert "--dpi" in capsys.readouterr().err
    assert plot_log.main([log, "-o", str(tmp_path / "out.nope")]) == 2
    assert "nope" in capsys.readouterr().err


def test_errors_print_no_traceback(tmp_path):
    missing = tmp_path / "missing.mcap"
    result = subprocess.run([sys.executable, "-m", "dtpf.scripts.logs.plot", str(missing)], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 1
    assert result.stderr.strip() == f"dtpf plot: error: no such file: {missing}"


def test_register_adds_a_plot_subcommand():
    import argparse

    parser = argparse.ArgumentParser(prog="dtpf")
    commands = parser.add_subparsers(dest="command")
    plot_log.register(commands)
    args = parser.parse_args(["plot", "x.mcap", "-o", "y.png", "--twin", "t", "--steps-at", "4", "8", "--dpi", "72"])
    assert (args.command, args.log.name, args.output.name, args.twin, args.steps_at, args.dpi) == (
        "plot", "x.mcap", "y.png", "t", [4, 8], 72.0)
    assert args.handler is plot_log.cmd_plot
    assert "Fig" in commands.choices["plot"].description


# --- the plot function on data made in memory -------------------------------------

def test_plot_marks_degraded_steps_and_ps_changes_without_a_file():
    estimates = [estimate("mem", k, degraded=k in (4, 7), ps=None if k in (4, 7) else (0.81 if k < 6 else 0.5))
                 for k in range(1, 11)]
    commands = [PSCommand(run_id="r", twin_id="mem", step=k, ps=0.81 if k < 5 else 0.5, applies_from_step=k + 1,
                          policy="test", reason="test") for k in range(1, 10)]
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 1))
    w = rng.random(50)
    w /= w.sum()
    before = ParticleSet(run_id="r", twin_id="mem", step=5, kind="propagated", particles=x, weights=w)
    run = RunLog(twin="mem", estimates=estimates, ps_commands=commands, propagated={5: before},
                 propagated_count=1)
    figure = plot_run(run, steps_at=[5])
    health = figure.axes[2]
    labels = [line.get_label() for line in health.lines]
    degraded = health.lines[labels.index(next(label for label in labels if label.startswith("degraded")))]
    assert list(degraded.get_xdata()) == [4, 7]
    changed = health.lines[labels.index("PS changed by the system layer")]
    assert list(changed.get_xdata()) == [2, 6] and list(changed.get_ydata()) == [0.81, 0.5]
    assert "2 degraded steps" in health.get_title(loc="left")
    after = figure.axes[4]
    assert "no preprocessed sets in this log" in " ".join(t.get_text() for t in after.texts)
    assert "N = 50" in figure.get_suptitle()  # N from the particle set when the log has no configuration


def test_plot_run_without_estimates_fails():
    with pytest.raises(PlotError, match="no estimates"):
        plot_run(RunLog(twin="t", estimates=[]))
