"""``python -m dtpf.scripts.paper.experiments``: the reduced run writes every output, with finite numbers.

These tests check that the command works, not that it reproduces the paper:
the full run and its verdicts are in docs/results/experiments.md.
"""
from __future__ import annotations

import csv
import math

import pytest

from dtpf.scripts.paper import experiments
from dtpf.scripts.paper.experiments import QUICK, resampling_steps, run_one

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
CSV_FILES = ["runs", "table2", "table2_dt_change", "table2_degradation", "table2_reading_a", "fig4",
             "fig4_summary", "fig5", "fig5_stability", "figs6-8", "figs6-8_summary", "table3", "table3_raw"]
PNG_FILES = ["table2", "fig4", "fig5", "figs6-8", "table3"]


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """One reduced run of every experiment (about 20 s on 2 cores)."""
    out = tmp_path_factory.mktemp("experiments") / "experiments"
    assert experiments.main(["--quick", "--out", str(out)]) == 0
    return out


def rows_of(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_every_csv_exists_and_its_numbers_are_finite(quick):
    for name in CSV_FILES:
        rows = rows_of(quick / f"{name}.csv")
        assert rows, f"{name}.csv has no rows"
        for row in rows:
            for key, value in row.items():
                try:
                    number = float(value)
                except ValueError:
                    continue  # names (scenario, method, dates) and empty cells
                assert math.isfinite(number), f"{name}.csv: {key} = {value} in {row}"


def test_every_cell_of_table2_is_there(quick):
    rows = rows_of(quick / "table2.csv")
    cells = {(r["scenario"], int(r["N"]), int(r["S"]), r["method"]) for r in rows}
    expected = {(sc, n, s, m) for sc in experiments.SCENARIOS for n in QUICK.table2_particles
                for s in QUICK.table2_s for m in experiments.METHODS}
    assert cells == expected
    assert all(float(r["mse"]) > 0 for r in rows)


def test_figures_are_small_pngs(quick):
    for name in PNG_FILES:
        data = (quick / f"{name}.png").read_bytes()
        assert data[:8] == PNG_MAGIC, f"{name}.png is not a PNG"
        assert len(data) < 300_000, f"{name}.png has {len(data)} bytes"


def test_report_has_every_section_and_no_machine_path(quick):
    report = (quick.parent / "experiments.md").read_text()
    for heading in ("## Table 2", "## Fig. 4", "## Fig. 5", "## Figs. 6-8", "## Table 3", "## Section 5",
                    "## Closing note"):
        assert heading in report
    assert "QUICK run" in report
    assert "Not run yet" not in report
    assert str(quick.parent) not in report
    assert "](experiments/fig4.png)" in report


def test_the_one_command_also_runs_the_tracking_application(quick):
    tracking = quick.parent / "tracking"
    rows = rows_of(tracking / "summary.csv")
    assert {r["method"] for r in rows} == set(experiments.METHODS)
    assert all(math.isfinite(float(r["mean_error"])) and float(r["mean_error"]) > 0 for r in rows)
    assert (quick.parent / "tracking.md").exists()
    report = (quick.parent / "experiments.md").read_text()
    assert "](tracking.md)" in report
    assert sum(line.startswith("Tracking, ") for line in report.splitlines()) == len(rows)


def test_report_only_rebuilds_from_the_files(quick):
    path = quick.parent / "experiments.md"
    before = path.read_text()
    path.unlink()
    assert experiments.main(["--report-only", "--out", str(quick)]) == 0
    assert path.read_text() == before


def test_unknown_experiment_is_refused(capsys):
    with pytest.raises(SystemExit):
        experiments.main(["--only", "table9"])
    assert "invalid choice: 'table9'" in capsys.readouterr().err


@pytest.mark.parametrize("steps", [1, 7, 100])
def test_resampling_steps_are_s_distinct_steps_ending_at_t(steps):
    for s in range(1, steps + 1):
        chosen = resampling_steps(steps, s)
        assert len(chosen) == s
        assert max(chosen) == steps and min(chosen) >= 1
    assert resampling_steps(steps, steps) == set(range(1, steps + 1))


def test_resampling_steps_of_the_paper_settings():
    assert resampling_steps(100, 20) == set(range(5, 101, 5))
    assert resampling_steps(100, 1) == {100}
    with pytest.raises(ValueError, match="in 1..100, got 0"):
        resampling_steps(100, 0)


@pytest.mark.parametrize("method", ["systematic", "DT inherit"])
def test_a_run_resamples_exactly_s_times(method):
    result = run_one("ungm", 50, 30, method, seed=3, resamplings=6)
    assert result["resampled"] == 6
    every = run_one("ungm", 50, 30, method, seed=3)
    assert every["resampled"] == 30
