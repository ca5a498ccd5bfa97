"""dtpf compare: its statistics against values computed by hand, its variants, and the command end to end
(the table's rows, the CSV that resumes, the one-line refusals, Ctrl-C keeping every finished run)."""
from __future__ import annotations

import csv
import math
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from dtpf.messages.config import RunConfig, RunInputError
from dtpf.scripts import compare_stats as stats
from dtpf.scripts.compare_csv import HEADER, CompareCsv
from dtpf.scripts.compare_variants import parse_variant

from conftest import ROOT


# --- statistics, against values worked out by hand ---------------------------------------------------------

def test_mean_interval_is_the_mean_and_1_96_sample_sd_over_root_s():
    # [1, 2, 3, 4]: mean 2.5, sample variance (2.25 + 0.25 + 0.25 + 2.25) / 3 = 5/3, half 1.96 sqrt(5/3) / 2
    mean, half = stats.mean_interval([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5
    assert half == pytest.approx(1.2651745, abs=1e-7)
    assert math.isnan(stats.mean_interval([7.0])[1])


def test_paired_difference_and_its_verdict_each_way():
    values, baseline = [3.0, 5.0, 4.0, 6.0], [2.0, 3.0, 3.0, 4.0]
    # differences 1, 2, 1, 2: mean 1.5, sample sd sqrt(1/3), half 1.96 sqrt(1/3) / 2 = 0.5658
    difference, half = stats.paired_difference(values, baseline)
    assert difference == 1.5
    assert half == pytest.approx(0.5658033, abs=1e-7)
    assert stats.verdict(difference, half, higher_is_better=False) == "worse"
    assert stats.verdict(difference, half, higher_is_better=True) == "better"
    assert stats.verdict(-difference, half, higher_is_better=False) == "better"
    assert stats.verdict(0.5, half, higher_is_better=False) == "not significantly different"
    assert stats.verdict(0.5, math.nan, higher_is_better=False) == "not significantly different"


def test_relative_change_is_the_ratio_of_means_with_the_delta_method():
    values, baseline = [3.0, 5.0, 4.0, 6.0], [2.0, 3.0, 3.0, 4.0]
    # means 4.5 and 3: +50%; a - 1.5 b = 0, 0.5, -0.5, 0: sd sqrt(1/6); half 100 * 1.96 sqrt(1/6) / (2 * 3)
    change, half = stats.relative_change(values, baseline)
    assert change == pytest.approx(50.0)
    assert half == pytest.approx(13.3361, abs=1e-4)


def test_relative_change_of_a_negative_baseline_keeps_the_difference_s_sign():
    # log predictive: baseline mean -3, variant mean -2.5 (higher, better): +16.7% of |-3|;
    # R = 5/6, a - R b = 2/3, -1/3, 1/3, -2/3: sd sqrt(10/27), half 100 * 1.96 sd / (2 * 3) = 19.880%
    values, baseline = [-1.0, -2.0, -3.0, -4.0], [-2.0, -2.0, -4.0, -4.0]
    change, half = stats.relative_change(values, baseline)
    assert change == pytest.approx(100 / 6)
    assert half == pytest.approx(19.8803, abs=1e-4)
    row = stats.compare(values, baseline, higher_is_better=True)
    assert (row.difference, row.verdict) == (0.5, "not significantly different")  # 0.5 +- 0.5658


def test_compare_gives_the_baseline_its_own_row_and_refuses_unpaired_values():
    row = stats.compare([1.0, 2.0], [1.0, 2.0], higher_is_better=False, is_baseline=True)
    assert (row.runs, row.mean, row.difference, row.verdict) == (2, 1.5, 0.0, "baseline")
    with pytest.raises(ValueError, match="same seeds"):
        stats.compare([1.0, 2.0], [1.0], higher_is_better=False)


def test_intervals_print_three_digits_of_the_half_width():
    assert stats.format_interval(25.0812, 1.5312) == "25.08 ± 1.53"
    assert stats.format_interval(4.36912, 0.15231) == "4.369 ± 0.152"
    assert stats.format_interval(0.0021, 0.0312) == "0.0021 ± 0.0312"
    assert stats.format_interval(3.0, math.nan) == "3"
    assert stats.format_interval(0.0, 0.0) == "0 ± 0" and stats.format_change(0.0, 0.0) == "+0% ± 0%"
    assert stats.format_change(11.94, 6.61) == "+11.9% ± 6.6%"
    assert stats.format_change(-0.4, 0.45) == "-0.40% ± 0.45%"


# --- variants ----------------------------------------------------------------------------------------------

def test_a_variant_s_values_may_hold_colons_and_commas():
    variant = parse_variant("mine:model=path/to/file.py:Target,ros2_fields=point.x,point.y,ps=0.5")
    assert variant.label == "mine"
    assert variant.fields == {"model": "path/to/file.py:Target", "ros2_fields": "point.x,point.y", "ps": "0.5"}
    assert parse_variant("mine:resampler=my.py:fn").fields == {"resampler": "my.py:fn"}
    assert parse_variant("DT, PS = 0.5:policy=fixed,ps=0.5").label == "DT, PS = 0.5"
    assert parse_variant("plain").fields == {} and parse_variant("plain:").fields == {}


def test_a_variant_s_config_is_the_base_with_its_fields_and_the_seed():
    config = parse_variant("dt:policy=rule,ps=0.5,preprocess=false,resample-below=none").config(
        RunConfig(particles=30, steps=10, resample_below=0.5), seed=7)
    assert (config.policy, config.ps, config.preprocess, config.resample_below) == ("rule", 0.5, False, None)
    assert (config.particles, config.steps, config.seed) == (30, 10, 7)


@pytest.mark.parametrize("text, message", [
    ("x:bogus=1", "variant 'x': unknown field 'bogus'"),
    ("x:seed=3", "variant 'x': seed is each run's own"),
    (":ps=1", "no label"),
    ("x:ps", "variant 'x': 'ps' is not FIELD=VALUE"),
    ("x:ps=0.5,ps=0.6", "variant 'x': ps is given twice"),
])
def test_a_bad_variant_is_one_line_naming_it(text, message):
    with pytest.raises(RunInputError, match=message):
        parse_variant(text)


def test_a_bad_value_names_the_variant_and_the_field():
    with pytest.raises(RunInputError, match=r"variant 'dt': ps: "):
        parse_variant("dt:ps=2").config(RunConfig(), seed=0)


# --- the command ---------------------------------------------------------------------------------------------

def dtpf(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "compare", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


VARIANTS = ("--variant", "plain:preprocess=false", "--variant", "dt:policy=fixed,ps=0.81",
            "--variant", "rough:preprocess=false,jitter=roughening")
SMALL = ("-n", "30", "-T", "10", "--workers", "2")


def table_rows(stdout: str) -> dict[str, list[str]]:
    """The Markdown table's rows by variant: their cells."""
    rows = {}
    for line in stdout.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if line.startswith("| ") and cells[0] not in ("variant",):
            rows[cells[0]] = cells
    return rows


def test_compare_prints_the_table_writes_the_csv_and_resumes_it(tmp_path):
    table, plot, markdown = tmp_path / "c.csv", tmp_path / "c.png", tmp_path / "c.md"
    first = dtpf(*VARIANTS, "--seeds", "3", *SMALL, "--csv", str(table), "--plot", str(plot),
                 "--markdown", str(markdown))
    assert first.returncode == 0, first.stderr
    rows = table_rows(first.stdout)
    assert list(rows) == ["plain", "dt", "rough"]
    assert "| variant | runs | MSE (lower is better) | difference vs plain | change | verdict | ms / step |" \
        in first.stdout
    assert all(row[1] == "3" for row in rows.values())
    assert rows["plain"][3:6] == ["-", "-", "baseline"]
    assert markdown.read_text() == first.stdout
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    with open(table, newline="") as handle:
        lines = list(csv.reader(handle))
    assert tuple(lines[0]) == HEADER and len(lines) == 1 + 3 * 3
    held, note = CompareCsv(table).read()
    assert note is None and set(held) == {("", label, seed) for label in ("plain", "dt", "rough") for seed in range(3)}
    # A row is the in-process run of its variant and seed, to the last digit.
    from dtpf.scripts.inprocess import run
    assert held[("", "plain", 1)].value == run(RunConfig(particles=30, steps=10, seed=1, preprocess=False)).mse
    # The table is the statistics of the rows.
    plain = [held[("", "plain", seed)].value for seed in range(3)]
    dt = [held[("", "dt", seed)].value for seed in range(3)]
    expected = stats.compare(dt, plain, higher_is_better=False)
    assert rows["dt"][2] == stats.format_interval(expected.mean, expected.mean_half)
    assert rows["dt"][3] == stats.format_interval(expected.difference, expected.difference_half)
    assert rows["dt"][4] == stats.format_change(expected.change, expected.change_half)
    assert rows["dt"][5] == expected.verdict

    again = dtpf(*VARIANTS, "--seeds", "3", *SMALL, "--csv", str(table))
    assert again.returncode == 0, again.stderr
    assert f"{table} holds 9 of the 9 runs (3 variants x 3 seeds); skipping them, nothing to run" in again.stderr
    assert again.stdout == first.stdout
    assert len(table.read_text().splitlines()) == 1 + 9

    more = dtpf(*VARIANTS, "--seeds", "4", *SMALL, "--csv", str(table))
    assert more.returncode == 0, more.stderr
    assert "holds 9 of the 12 runs (3 variants x 4 seeds); skipping them, running the other 3" in more.stderr
    assert len(table.read_text().splitlines()) == 1 + 12
    assert all(row[1] == "4" for row in table_rows(more.stdout).values())


def test_compare_refuses_a_csv_of_something_else_or_of_other_settings(tmp_path):
    other = tmp_path / "other.csv"
    other.write_text("scenario,seed,error\nungm,0,1.5\n")
    done = dtpf(*VARIANTS, "--seeds", "2", *SMALL, "--csv", str(other))
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"dtpf compare: error: --csv {other}: not a dtpf compare CSV (its header is 'scenario,seed,error'); "
        f"give another file"]

    table = tmp_path / "c.csv"
    assert dtpf("--variant", "plain:preprocess=false", "--seeds", "2", *SMALL, "--csv", str(table)).returncode == 0
    done = dtpf("--variant", "plain:preprocess=false", "--seeds", "2", "-n", "40", "-T", "10", "--csv", str(table))
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"dtpf compare: error: --csv {table}: variant 'plain' was run there with particles 30 (now 40); "
        f"give another --csv or another label"]


def test_a_bad_variant_exits_2_with_one_line_before_any_run(tmp_path):
    table = tmp_path / "c.csv"
    for variant, message in [("dt:ps=2", "variant 'dt': ps: Input should be less than or equal to 1"),
                             ("dt:bogus=1", "variant 'dt': unknown field 'bogus'"),
                             ("dt:model=nowhere.py:Target", "variant 'dt': "),
                             ("dt:resampler=nowhere.py:resample", "variant 'dt': ")]:
        done = dtpf("--variant", "plain:preprocess=false", "--variant", variant, *SMALL, "--csv", str(table))
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"dtpf compare: error: {message}"), lines
        assert not table.exists()  # nothing ran, nothing was written


def test_without_truth_the_metric_is_the_log_predictive_higher_is_better(tmp_path):
    from dtpf.scripts.inprocess import simulate

    _, observations = simulate(RunConfig(steps=10, seed=3))
    np.save(tmp_path / "z.npy", observations)
    done = dtpf("--variant", "plain:preprocess=false", "--variant", "dt", "--seeds", "2", "-n", "30",
                "--observations", str(tmp_path / "z.npy"), "--workers", "1")
    assert done.returncode == 0, done.stderr
    assert "| variant | runs | log predictive (higher is better) |" in done.stdout
    assert list(table_rows(done.stdout)) == ["plain", "dt"]


def _as_a_background_job():
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # what a non-interactive shell does to a job started with &


def test_ctrl_c_leaves_every_finished_run_in_the_csv(tmp_path):
    # Started as a script's background job (SIGINT ignored), as when someone runs it with & and then kill -INT.
    table = tmp_path / "c.csv"
    process = subprocess.Popen([sys.executable, "-m", "dtpf.scripts.cli", "compare", *VARIANTS, "--seeds", "500",
                                "-n", "30", "-T", "30", "--workers", "2", "--csv", str(table)],
                               cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=_as_a_background_job)
    try:
        deadline = time.monotonic() + 120
        while not (table.exists() and len(table.read_text().splitlines()) > 3):  # three runs written
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, "no run finished in 120 s"
            time.sleep(0.05)
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, err
    assert "interrupted after" in err and "holds every finished run" in err
    held, note = CompareCsv(table).read()
    assert note is None and 3 <= len(held) < 1500
    assert len(table.read_text().splitlines()) == 1 + len(held)
    assert all(math.isfinite(row.value) and row.steps == 30 for row in held.values())
    assert out == ""  # no table for an interrupted compare


def test_help_explains_the_variant_syntax_with_an_example():
    done = dtpf("--help")
    assert done.returncode == 0
    assert "LABEL:FIELD=VALUE" in done.stdout and "example:" in done.stdout and "--seed-list" in done.stdout


# --- metrics, grids, the CSV's layouts --------------------------------------------------------------------------

class _Result:
    """What a metric reads of a run: its errors over the components the truth covers, and the log predictives."""

    def __init__(self, errors, components=None, log_predictive=(-1.0, -2.0)):
        self.errors = np.asarray(errors, dtype=np.float64)
        self.components = tuple(range(self.errors.shape[1])) if components is None else components
        self.log_predictive = np.asarray(log_predictive)


def test_each_metric_against_values_worked_out_by_hand():
    from dtpf.scripts.compare_metrics import Metric

    result = _Result([[3.0, 4.0], [0.0, 0.0]])  # distances 5 and 0
    assert Metric("mse").of(result) == 6.25  # (9 + 16 + 0 + 0) / 4
    assert Metric("rmse").of(result) == 2.5
    assert Metric("squared-distance").of(result) == 12.5  # (25 + 0) / 2
    assert Metric("distance").of(result) == 2.5  # (5 + 0) / 2
    assert Metric("mse", (1,)).of(result) == 8.0  # (16 + 0) / 2
    assert Metric("log-predictive").of(result) == -1.5
    # A file whose truth covers components 2 and 4 of the state: the metric picks them by state component.
    partial = _Result([[1.0, 2.0], [3.0, 4.0]], components=(2, 4))
    assert Metric("squared-distance", (4,)).of(partial) == 10.0  # (4 + 16) / 2
    assert Metric("mse").higher_is_better is False and Metric("log-predictive").higher_is_better is True


def test_a_metric_is_named_as_the_csv_keeps_it_and_refused_where_a_run_cannot_give_it():
    from dtpf.scripts.compare_metrics import Metric, parse_metric

    assert parse_metric(None, None, has_truth=True) == Metric("mse")
    assert parse_metric(None, None, has_truth=False) == Metric("log-predictive")
    assert parse_metric("squared-distance", "0,1", has_truth=True).key == "squared-distance[0,1]"
    assert Metric("log-predictive").key == "log_predictive" and Metric("mse").key == "mse"
    assert Metric("distance", (0, 1)).title == "distance of components 0, 1 (lower is better)"
    for name, components, message in [("bogus", None, "--metric: one of mse, rmse"),
                                      ("mse", "0,x", "--components: state components are integers"),
                                      ("mse", "1,1", "--components: distinct components"),
                                      ("log-predictive", "0", "--components: the log predictive is of the whole")]:
        with pytest.raises(RunInputError, match=message):
            parse_metric(name, components, has_truth=True)
    with pytest.raises(RunInputError, match="--metric rmse needs the truth"):
        Metric("rmse").check(2, None)
    with pytest.raises(RunInputError, match="the state has components 0 .. 1, got 2"):
        Metric("mse", (2,)).check(2, (0, 1))
    with pytest.raises(RunInputError, match="the truth covers components 0, not 1"):
        Metric("mse", (1,)).check(2, (0,))


def test_a_grid_is_every_combination_the_first_field_outermost():
    from dtpf.scripts.compare_plan import Cell, parse_grid

    assert parse_grid(None) == [Cell()]
    cells = parse_grid(["particles=100,1000", "scenario=ungm,drift"])
    assert [cell.name for cell in cells] == ["particles=100, scenario=ungm", "particles=100, scenario=drift",
                                             "particles=1000, scenario=ungm", "particles=1000, scenario=drift"]
    assert cells[1].fields == {"particles": "100", "scenario": "drift"}
    for texts, message in [(["particles"], "FIELD=VALUE"), (["bogus=1"], "unknown field 'bogus'"),
                           (["seed=1,2"], "each run's own"), (["particles=1,1"], "lists a value twice"),
                           (["particles=1", "particles=2"], "particles is given twice"), (["steps=5,"], "FIELD=VALUE")]:
        with pytest.raises(RunInputError, match=message):
            parse_grid(texts)


def test_the_statistics_take_another_quantile():
    mean, half = stats.mean_interval([1.0, 2.0, 3.0, 4.0], z=1.0)
    assert half == pytest.approx(math.sqrt(5 / 3) / 2)
    exact = stats.compare([3.0, 5.0, 4.0, 6.0], [2.0, 3.0, 3.0, 4.0], higher_is_better=False, z=1.959963984540054)
    assert exact.difference_half == pytest.approx(0.5658033 * 1.959963984540054 / 1.96, abs=1e-7)


def test_a_csv_of_the_first_layout_is_read_and_appended_to_in_its_own(tmp_path):
    from dtpf.scripts.compare_csv import FIRST_HEADER, RunRow

    path = tmp_path / "old.csv"
    path.write_text(",".join(FIRST_HEADER) + "\nplain,preprocess=false,{},0,mse,1.5,20.0,10,0.1\n")
    store = CompareCsv(path)
    held, _ = store.read()
    row = held[("", "plain", 0)]
    assert (row.value, row.cell) == (1.5, "") and math.isnan(row.distinct) and math.isnan(row.log_predictive)
    store.check(held, {("", "plain"): "{}"}, "mse")
    with pytest.raises(RunInputError, match=r"judged there by the metric mse \(now rmse\)"):
        store.check(held, {("", "plain"): "{}"}, "rmse")
    with pytest.raises(RunInputError, match="holds no cells; give another --csv for a --grid"):
        store.check(held, {("particles=10", "plain"): "{}"}, "mse")
    store.append(RunRow("plain", "preprocess=false", "{}", 1, "mse", 2.5, 21.0, 10, 0.2, distinct=0.5))
    lines = path.read_text().splitlines()
    assert lines[-1] == "plain,preprocess=false,{},1,mse,2.5,21.0,10,0.2"
    assert set(CompareCsv(path).read()[0]) == {("", "plain", 0), ("", "plain", 1)}


def test_a_grid_gives_a_table_per_cell_and_a_metric_over_chosen_components(tmp_path):
    """--grid particles=20,30 with --metric squared-distance --components 0 on the range-bearing target: a table
    per cell, each row the metric of the in-process run worked out from its means and truth; the CSV holds each
    cell's rows, and the same command again runs nothing."""
    from dtpf.scripts.inprocess import run

    table = tmp_path / "grid.csv"
    model = "docs/examples/range_bearing.py:RangeBearingTarget"
    args = ("--model", model, "--variant", "plain:preprocess=false", "--variant", "rough:preprocess=false,jitter=roughening",
            "--grid", "particles=20,30", "--seeds", "2", "-T", "6", "--workers", "2", "--metric", "squared-distance",
            "--components", "0", "--csv", str(table))
    done = dtpf(*args)
    assert done.returncode == 0, done.stderr
    assert "2 variants x 2 seeds x 2 cells (seeds 0-1); metric: the mean over steps of the squared distance of the " \
           "posterior mean to the truth of component 0, lower is better" in done.stdout
    blocks = done.stdout.split("**particles=")
    assert [block.split("**")[0] for block in blocks[1:]] == ["20", "30"]
    assert "| variant | runs | squared distance of component 0 (lower is better) | difference vs plain |" in blocks[1]
    held, _ = CompareCsv(table).read()
    assert set(held) == {(f"particles={n}", label, seed) for n in (20, 30) for label in ("plain", "rough")
                         for seed in (0, 1)}
    row = held[("particles=30", "rough", 1)]
    result = run(RunConfig(model=str(ROOT / "docs/examples/range_bearing.py") + ":RangeBearingTarget", particles=30,
                           steps=6, seed=1, preprocess=False, jitter="roughening"))
    assert row.metric == "squared-distance[0]"
    assert row.value == pytest.approx(float(np.mean((result.means[:, 0] - result.truth[:, 0]) ** 2)), rel=1e-12)
    assert row.log_predictive == pytest.approx(float(np.mean(result.log_predictive)), rel=1e-12)
    assert row.distinct > 0 and row.preprocessed == 0.0
    values = [held[("particles=20", "rough", seed)].value - held[("particles=20", "plain", seed)].value
              for seed in (0, 1)]
    assert table_rows(blocks[1])["rough"][3] == stats.format_interval(*stats.paired_difference(values, [0.0, 0.0]))
    again = dtpf(*args)
    assert again.returncode == 0 and "holds 8 of the 8 runs (2 variants x 2 seeds x 2 cells); skipping them, " \
                                      "nothing to run" in again.stderr
    assert again.stdout == done.stdout


@pytest.mark.parametrize("extra, message", [
    (("--components", "3"), "dtpf compare: error: --components: the state has components 0 .. 0, got 3"),
    (("--grid", "particles=20,x"), "dtpf compare: error: --grid: cell 'particles=x': particles: "),
    (("--grid", "preprocess=true,false"), "dtpf compare: error: variant 'plain' sets preprocess, which --grid varies"),
])
def test_a_bad_metric_or_grid_is_one_line_before_any_run(extra, message):
    done = dtpf("--variant", "plain:preprocess=false", "--seeds", "2", "-n", "20", "-T", "4", *extra)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(message), lines


def test_a_worker_warms_each_model_over_all_its_steps_once_and_every_variant_a_few(monkeypatch):
    """What a model computes once per process when a step first needs it (the video's frame histograms) is not
    in any timed run: the first run of each model goes over all its steps, the others three, on few particles."""
    from dtpf.scripts import compare_runs, inprocess

    ran = []
    monkeypatch.setattr(inprocess, "run", lambda config, model=None: ran.append((config.scenario, config.particles,
                                                                                  config.steps)))
    monkeypatch.setattr(compare_runs, "_model", lambda config: None)
    compare_runs.warm_up([RunConfig(scenario="video", particles=400, steps=50),
                          RunConfig(scenario="video", particles=400, steps=50, preprocess=False),
                          RunConfig(scenario="drift", particles=20, steps=100)])
    assert ran == [("video", 50, 50), ("video", 50, 3), ("drift", 20, 100)]
