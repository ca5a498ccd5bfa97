"""dtpf.entity.observations: a user's observations from .csv, .npy and .npz files.

Numbers are written with repr() and must come back exactly; every bad file
raises ObservationError with a one-line message that starts with the file
name. The tests run inside tmp_path (monkeypatch.chdir) so that messages
start with the short names a user would type ("obs.csv line 7: ...").
"""
from __future__ import annotations

import os
import re

import numpy as np
import pytest

from dtpf.entity import observations as obs_module
from dtpf.entity.observations import ObservationError, ObservationTable, read_observations

HEADER = "time,range,bearing,truth_x,truth_y,truth_vx,truth_vy"


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


def write(name: str, text: str) -> str:
    with open(name, "w", encoding="utf-8", newline="") as handle:
        handle.write(text)
    return name


def csv_text(header: str, rows, *, end: str = "\n") -> str:
    return header + end + "".join(",".join(repr(float(v)) for v in row) + end for row in rows)


def fails(path, match: str, **kwargs) -> ObservationError:
    """read_observations(path) raises ObservationError matching ``match``, in one line starting with path."""
    with pytest.raises(ObservationError, match=match) as caught:
        read_observations(path, **kwargs)
    message = str(caught.value)
    assert "\n" not in message and "\r" not in message, message
    assert message.startswith(os.fspath(path)), message
    return caught.value


def exact(message: str) -> str:
    """A pattern matching exactly ``message``."""
    return "^" + re.escape(message) + "$"


# --- CSV: reading back ------------------------------------------------------------------

def test_csv_time_observations_and_truth_read_back_exactly():
    rng = np.random.default_rng(1)
    values = rng.standard_normal((50, 7)) * 10.0 ** rng.integers(-300, 300, (50, 7))
    values[:, 0] = np.cumsum(rng.random(50))  # times, increasing
    write("obs.csv", csv_text(HEADER, values))

    table = read_observations("obs.csv", obs_dim=2, state_dim=4)

    assert table.steps == 50
    assert table.source == "obs.csv"
    assert table.columns == ("range", "bearing")
    assert table.truth_columns == ("truth_x", "truth_y", "truth_vx", "truth_vy")
    assert np.array_equal(table.times, values[:, 0])
    assert np.array_equal(table.observations, values[:, 1:3])
    assert np.array_equal(table.truth, values[:, 3:])
    for a in (table.observations, table.truth, table.times):
        assert a.dtype == np.float64 and a.flags.c_contiguous and not a.flags.writeable
    assert table.observations.shape == (50, 2) and table.truth.shape == (50, 4) and table.times.shape == (50,)


def test_csv_without_truth_or_time_gives_none():
    values = np.array([[1.5, -2.25], [3.0, 4.0e-7]])
    write("obs.csv", csv_text("range,bearing", values))
    table = read_observations("obs.csv")
    assert table.truth is None and table.truth_columns == ()
    assert table.times is None
    assert np.array_equal(table.observations, values)


def test_csv_time_may_be_absent_with_truth_present():
    write("obs.csv", "z,truth\n1.0,2.0\n3.0,4.0\n")
    table = read_observations("obs.csv", state_dim=1)
    assert table.times is None
    assert table.columns == ("z",) and table.truth_columns == ("truth",)
    assert table.truth.tolist() == [[2.0], [4.0]]


@pytest.mark.parametrize("time_name", ["time", "t", "timestamp", "stamp", "Time", "T", "TIMESTAMP", "Stamp"])
def test_csv_time_column_names_are_case_insensitive(time_name):
    write("obs.csv", f"a,{time_name},b\n1,0.5,2\n3,0.75,4\n")
    table = read_observations("obs.csv")
    assert table.times.tolist() == [0.5, 0.75]
    assert table.columns == ("a", "b")


def test_csv_truth_columns_by_name_in_file_order():
    write("obs.csv", "True_b,obs1,truth,TRUTH_a,obs2,truthy\n1,2,3,4,5,6\n")
    table = read_observations("obs.csv")
    assert table.truth_columns == ("True_b", "truth", "TRUTH_a")
    assert table.truth.tolist() == [[1.0, 3.0, 4.0]]
    assert table.columns == ("obs1", "obs2", "truthy")  # 'truthy' is neither 'truth' nor 'truth_...'
    assert table.observations.tolist() == [[2.0, 5.0, 6.0]]


def test_csv_explicit_roles_select_by_name_in_the_order_given():
    write("obs.csv", "seconds,label,b,a,truth_x,pos\n0,x,1,2,9,7\n1,y,3,4,9,8\n")
    table = read_observations("obs.csv", observation_columns=["a", "b"], truth_columns=["pos"],
                              time_column="seconds")
    assert table.columns == ("a", "b")
    assert table.observations.tolist() == [[2.0, 1.0], [4.0, 3.0]]
    assert table.truth_columns == ("pos",) and table.truth.tolist() == [[7.0], [8.0]]
    assert table.times.tolist() == [0.0, 1.0]  # 'label' holds text but is not read


def test_csv_explicit_empty_truth_columns_means_no_truth():
    write("obs.csv", "time,z,truth_x\n0,1,2\n")
    table = read_observations("obs.csv", truth_columns=[])
    assert table.truth is None and table.columns == ("z",)


def test_csv_explicit_observation_may_be_a_time_named_column():
    write("obs.csv", "t,z\n5,1\n4,2\n")  # 't' decreases: fine, it is an observation here
    table = read_observations("obs.csv", observation_columns=["t", "z"])
    assert table.times is None and table.columns == ("t", "z")
    assert table.observations.tolist() == [[5.0, 1.0], [4.0, 2.0]]


def test_csv_quotes_whitespace_bom_comments_crlf_and_trailing_blank_lines():
    text = ("\ufeff# a comment before the header\r\n"
            ' time , "range" ,bearing \r\n'
            '0, "1.5", 2\r\n'
            "  # an indented comment, with \"an unbalanced quote\r\n"
            "1 ,  3.25 ,-4e-3\r\n"
            "\r\n\r\n   \r\n")
    write("obs.csv", text)
    table = read_observations("obs.csv")
    assert table.columns == ("range", "bearing")
    assert table.times.tolist() == [0.0, 1.0]
    assert table.observations.tolist() == [[1.5, 2.0], [3.25, -4e-3]]


def test_csv_equal_times_are_allowed():
    write("obs.csv", "time,z\n1,0\n1,1\n2,2\n")
    assert read_observations("obs.csv").times.tolist() == [1.0, 1.0, 2.0]


def test_csv_extension_is_case_insensitive():
    write("OBS.CSV", "z\n1\n")
    assert read_observations("OBS.CSV").observations.tolist() == [[1.0]]


def test_path_objects_are_accepted_and_kept_as_given(in_tmp):
    path = in_tmp / "obs.csv"
    write(str(path), "z\n1\n")
    assert read_observations(path).source == str(path)


def test_csv_of_1e5_rows_reads_correctly():
    rng = np.random.default_rng(2)
    values = rng.standard_normal((100_000, 5))
    values[:, 0] = np.arange(100_000) * 0.1
    write("big.csv", csv_text("time,range,bearing,truth_x,truth_y", values))
    table = read_observations("big.csv", obs_dim=2, state_dim=2)
    assert table.steps == 100_000
    assert np.array_equal(table.observations, values[:, 1:3])
    assert np.array_equal(table.truth, values[:, 3:])
    assert np.array_equal(table.times, values[:, 0])


# --- steps and head ----------------------------------------------------------------------

def test_steps_truncates_csv_and_stops_reading():
    # Line 5 is broken: with steps=2 the reader stops before it.
    write("obs.csv", "time,z\n0,1\n1,2\n2,3\nbroken\n")
    table = read_observations("obs.csv", steps=2)
    assert table.steps == 2 and table.observations.tolist() == [[1.0], [2.0]]
    assert table.times.tolist() == [0.0, 1.0]
    fails("obs.csv", exact("obs.csv line 5: 1 value, the header has 2 columns (time, z)"))
    assert read_observations("obs.csv", steps=3).steps == 3


def test_steps_larger_than_the_file_keeps_every_row():
    write("obs.csv", "z\n1\n2\n")
    assert read_observations("obs.csv", steps=10).steps == 2


def test_steps_truncates_npy_and_npz():
    z = np.arange(20.0).reshape(10, 2)
    np.save("obs.npy", z)
    np.savez("obs.npz", observations=z, truth=z * 2, time=np.arange(10.0))
    assert np.array_equal(read_observations("obs.npy", steps=3).observations, z[:3])
    table = read_observations("obs.npz", steps=4)
    assert np.array_equal(table.observations, z[:4]) and np.array_equal(table.truth, z[:4] * 2)
    assert table.times.tolist() == [0.0, 1.0, 2.0, 3.0]


def test_head_returns_the_first_rows():
    write("obs.csv", "time,z,truth_x\n0,1,10\n1,2,20\n2,3,30\n")
    table = read_observations("obs.csv")
    head = table.head(2)
    assert head.steps == 2 and head.observations.tolist() == [[1.0], [2.0]]
    assert head.truth.tolist() == [[10.0], [20.0]] and head.times.tolist() == [0.0, 1.0]
    assert head.columns == table.columns and head.truth_columns == table.truth_columns
    assert head.source == "obs.csv"
    assert head.observations.flags.c_contiguous
    assert table.head(None).steps == 3 and table.head(99).steps == 3
    with pytest.raises(ValueError, match="steps must be a positive integer, got 0"):
        table.head(0)


def test_table_is_frozen_and_checks_its_shapes():
    table = ObservationTable(observations=np.ones((2, 1)), truth=None, times=None, columns=("z",),
                             truth_columns=(), source="mem")
    with pytest.raises(AttributeError):
        table.source = "other"
    with pytest.raises(ValueError):
        table.observations[0, 0] = 5.0
    with pytest.raises(ValueError, match="2 column names for 1 observation columns"):
        ObservationTable(observations=np.ones((2, 1)), truth=None, times=None, columns=("a", "b"),
                         truth_columns=(), source="mem")
    with pytest.raises(ValueError, match=r"truth must have shape \(2, d\)"):
        ObservationTable(observations=np.ones((2, 1)), truth=np.ones((3, 1)), times=None, columns=("z",),
                         truth_columns=("x",), source="mem")


def test_table_copies_a_callers_writeable_array():
    z = np.ones((2, 1))
    table = ObservationTable(observations=z, truth=None, times=None, columns=("z",), truth_columns=(),
                             source="mem")
    z[0, 0] = 7.0
    assert table.observations[0, 0] == 1.0 and z.flags.writeable


# --- .npy and .npz -----------------------------------------------------------------------

def test_npy_two_dimensional():
    z = np.random.default_rng(3).standard_normal((6, 3))
    np.save("obs.npy", z)
    table = read_observations("obs.npy", obs_dim=3)
    assert np.array_equal(table.observations, z)
    assert table.columns == ("z0", "z1", "z2")
    assert table.truth is None and table.times is None and table.truth_columns == ()


def test_npy_one_dimensional_is_one_column():
    np.save("obs.npy", np.array([1.5, 2.5, -3.0]))
    table = read_observations("obs.npy", obs_dim=1)
    assert table.observations.shape == (3, 1) and table.observations[:, 0].tolist() == [1.5, 2.5, -3.0]
    assert table.columns == ("z0",)


def test_npy_integers_fortran_order_and_big_endian():
    z = np.arange(12).reshape(4, 3)
    np.save("ints.npy", z)
    np.save("fortran.npy", np.asfortranarray(z.astype(np.float32)))
    np.save("big.npy", z.astype(">f8"))
    for name in ("ints.npy", "fortran.npy", "big.npy"):
        table = read_observations(name)
        assert table.observations.dtype == np.float64 and table.observations.flags.c_contiguous
        assert np.array_equal(table.observations, z), name
    assert np.array_equal(read_observations("fortran.npy", steps=2).observations, z[:2])


def test_npz_with_truth_and_time():
    rng = np.random.default_rng(4)
    z, x, t = rng.standard_normal((5, 2)), rng.standard_normal((5, 4)), np.arange(5.0)
    np.savez("obs.npz", observations=z, truth=x, time=t)
    table = read_observations("obs.npz", obs_dim=2, state_dim=4)
    assert np.array_equal(table.observations, z) and np.array_equal(table.truth, x)
    assert np.array_equal(table.times, t)
    assert table.columns == ("z0", "z1") and table.truth_columns == ("x0", "x1", "x2", "x3")


def test_npz_without_truth():
    z = np.ones((3, 2))
    np.savez_compressed("obs.npz", observations=z)
    table = read_observations("obs.npz", state_dim=7)  # no truth: state_dim has nothing to check
    assert table.truth is None and table.times is None and np.array_equal(table.observations, z)


def test_npz_aliases_and_one_dimensional_truth():
    np.savez("obs.npz", z=np.array([1.0, 2.0]), x=np.array([3.0, 4.0]), t=np.array([0.0, 0.5]))
    table = read_observations("obs.npz")
    assert table.observations.tolist() == [[1.0], [2.0]]
    assert table.truth.tolist() == [[3.0], [4.0]] and table.truth_columns == ("x0",)
    assert table.times.tolist() == [0.0, 0.5]


def test_npz_single_array_of_any_name_is_the_observations():
    np.savez("obs.npz", measurements=np.arange(6.0).reshape(3, 2))
    table = read_observations("obs.npz")
    assert table.observations.tolist() == [[0.0, 1.0], [2.0, 3.0], [4.0, 5.0]]
    assert table.truth is None


def test_npz_other_arrays_are_ignored():
    np.savez("obs.npz", observations=np.ones(2), notes=np.array(["a", "b"]))
    assert read_observations("obs.npz").observations.tolist() == [[1.0], [1.0]]


# --- errors: CSV ---------------------------------------------------------------------------

def test_ragged_row():
    write("obs.csv", "time,range,bearing\n" + "0,1,2\n" * 5 + "6,1\n")
    err = fails("obs.csv", exact("obs.csv line 7: 2 values, the header has 3 columns (time, range, bearing)"))
    assert err.line == 7 and err.source == "obs.csv"


def test_row_with_too_many_values():
    write("obs.csv", "time,range\n0,1,2\n")
    fails("obs.csv", exact("obs.csv line 2: 3 values, the header has 2 columns (time, range)"))


def test_value_not_a_number():
    write("obs.csv", "time,range,bearing\n0,1,2\n1,1,2\n2,1,2\n3,abc,2\n")
    err = fails("obs.csv", exact("obs.csv line 5, column 'range': 'abc' is not a number"))
    assert err.column == "range" and err.line == 5


def test_long_bad_value_is_shortened():
    write("obs.csv", "z\n" + "x" * 5000 + "\n")
    err = fails("obs.csv", r"^obs\.csv line 2, column 'z': 'x+'\.\.\. is not a number$")
    assert len(str(err)) < 100


def test_nan_value():
    write("obs.csv", "time,range,bearing\n" + "".join(f"{i},1,2\n" for i in range(7)) + "7,1,nan\n")
    fails("obs.csv", exact("obs.csv line 9, column 'bearing': NaN (observations must be finite)"))


def test_infinite_values_in_truth_and_time():
    write("truth.csv", "z,truth_x\n1,2\n1,-inf\n")
    fails("truth.csv", exact("truth.csv line 3, column 'truth_x': -inf (truth must be finite)"))
    write("time.csv", "time,z\ninf,1\n")
    fails("time.csv", exact("time.csv line 2, column 'time': inf (times must be finite)"))


def test_empty_value():
    write("obs.csv", "time,range\n0,1\n1,2\n2,\n")
    fails("obs.csv", exact("obs.csv line 4, column 'range': empty"))
    write("blank.csv", "time,range\n0,  \n")
    fails("blank.csv", exact("blank.csv line 2, column 'range': empty"))


def test_time_before_the_line_above():
    write("obs.csv", "time,z\n" + "".join(f"{i}.0,0\n" for i in range(5)) + "4.0,0\n3.0,0\n")
    err = fails("obs.csv", exact("obs.csv line 8, column 'time': 3.0 is before 4.0 on the line above"))
    assert err.line == 8 and err.column == "time"


def test_time_before_an_earlier_line_across_a_comment():
    write("obs.csv", "time,z\n4.0,0\n# pause\n3.0,0\n")
    fails("obs.csv", exact("obs.csv line 4, column 'time': 3.0 is before 4.0 on line 2"))


def test_no_observation_column():
    write("obs.csv", "time,truth_x\n0,1\n")
    fails("obs.csv", exact("obs.csv: no observation column; header: time, truth_x"))


def test_observation_columns_against_the_model():
    write("obs.csv", "time,range,truth_x\n0,1,2\n")
    fails("obs.csv", exact("obs.csv: 1 observation column (range), the model observes 2 values per step"),
          obs_dim=2)


def test_truth_columns_against_the_model():
    # Fewer truth columns than the state: its leading components; more than the state: refused.
    write("obs.csv", "z,truth_x,truth_y,truth_vx\n0,1,2,3\n")
    table = read_observations("obs.csv", state_dim=4)
    assert table.truth.shape == (1, 3) and table.truth_components == (0, 1, 2)
    fails("obs.csv", exact("obs.csv: 3 truth columns (truth_x, truth_y, truth_vx), more than the "
                           "model's state has (2 dimensions)"), state_dim=2)


def test_model_checks_come_before_reading_rows():
    write("obs.csv", "z\nnot a number\n")
    fails("obs.csv", exact("obs.csv: 1 observation column (z), the model observes 3 values per step"), obs_dim=3)


def test_no_data_rows():
    write("obs.csv", "time,range\n\n# nothing\n")
    fails("obs.csv", exact("obs.csv: no data rows"))


def test_not_found():
    fails("obs.csv", exact("obs.csv: not found"))


def test_a_directory():
    os.mkdir("dir.csv")
    fails("dir.csv", exact("dir.csv: is a directory, not a file"))


def test_no_header_in_an_empty_file():
    write("obs.csv", "")
    fails("obs.csv", exact("obs.csv line 1: no header (the file is empty)"))
    write("comments.csv", "# only\n# comments\n")
    fails("comments.csv", exact("comments.csv line 3: no header (the file holds only comments)"))


def test_no_header_when_the_first_line_is_blank():
    write("obs.csv", "\ntime,z\n0,1\n")
    fails("obs.csv", r"^obs\.csv line 1: no header \(an empty line")


def test_no_header_when_the_first_line_holds_numbers():
    write("obs.csv", "0.0,1.5,2\n1.0,2.5,3\n")
    fails("obs.csv", r"^obs\.csv line 1: no header: the first line holds numbers \(0\.0, 1\.5, 2\)")


def test_blank_line_in_the_middle():
    write("obs.csv", "time,z\n0,1\n\n1,2\n")
    fails("obs.csv", exact("obs.csv line 3: empty line"))


def test_duplicate_column_names():
    write("obs.csv", "time,range, range\n0,1,2\n")
    fails("obs.csv", exact("obs.csv line 1: duplicate column name 'range' (columns 2 and 3)"))


def test_column_without_a_name():
    write("obs.csv", "time,range,\n0,1,2\n")
    fails("obs.csv", exact("obs.csv line 1: column 3 has no name; header: time, range, "))


def test_two_time_columns():
    write("obs.csv", "time,T,z\n0,0,1\n")
    fails("obs.csv", exact("obs.csv: 2 time columns (time, T); name one with time_column"))
    assert read_observations("obs.csv", time_column="T").columns == ("z",)


def test_explicit_column_missing():
    write("obs.csv", "time,range,bearing\n0,1,2\n")
    fails("obs.csv", exact("obs.csv: no column 'rng' (observation_columns); header: time, range, bearing"),
          observation_columns=["rng"])
    fails("obs.csv", exact("obs.csv: no column 'x' (truth_columns); header: time, range, bearing"),
          truth_columns=["x"])
    fails("obs.csv", exact("obs.csv: no column 'clock' (time_column); header: time, range, bearing"),
          time_column="clock")


def test_header_with_too_many_columns():
    write("obs.csv", ",".join(f"c{i}" for i in range(10_001)) + "\n" + ",".join(["1"] * 10_001) + "\n")
    fails("obs.csv", exact("obs.csv line 1: 10001 columns, more than the limit of 10000 (MAX_COLUMNS)"))
    write("ok.csv", ",".join(f"c{i}" for i in range(10_000)) + "\n" + ",".join(["1"] * 10_000) + "\n")
    assert read_observations("ok.csv").observations.shape == (1, 10_000)


def test_line_too_long(monkeypatch):
    monkeypatch.setattr(obs_module, "MAX_LINE_CHARS", 20)
    write("obs.csv", "z\n1\n" + "1" * 30 + "\n")
    fails("obs.csv", exact("obs.csv line 3: longer than 20 characters (MAX_LINE_CHARS)"))


def test_file_larger_than_the_limit_is_refused_before_reading(monkeypatch):
    write("obs.csv", "z\n1\n2\n")
    monkeypatch.setattr(obs_module, "MAX_FILE_BYTES", 5)
    fails("obs.csv", r"^obs\.csv: 6 bytes \(0\.0 GiB\), larger than the limit of 5 bytes .*\(MAX_FILE_BYTES\)$")


def test_limit_constant():
    assert obs_module.MAX_FILE_BYTES == 2 * 1024**3


def test_not_utf8_names_the_line():
    with open("obs.csv", "wb") as handle:
        handle.write(b"z\n" + b"1\n" * 3000 + b"\xff\n")
    fails("obs.csv", exact("obs.csv line 3002: not UTF-8 text (byte 0xff)"))


def test_stray_quote_is_a_bad_value_and_an_overlong_field_is_invalid_csv():
    write("obs.csv", 'z\n1"2\n')
    fails("obs.csv", exact("obs.csv line 2, column 'z': '1\"2' is not a number"))
    write("long.csv", "z\n1\n" + "1" * 200_000 + "\n")
    fails("long.csv", r"^long\.csv line 3: not valid CSV \(field larger than field limit")


def test_binary_file_named_csv():
    np.save("obs.npy", np.ones(3))
    os.rename("obs.npy", "obs.csv")
    fails("obs.csv", exact("obs.csv: a .npy file, not CSV text (rename it to .npy)"))


def test_unknown_extension():
    write("obs.txt", "z\n1\n")
    fails("obs.txt", exact("obs.txt: unknown observation file type '.txt'; expected .csv, .npy or .npz"))
    write("obs", "z\n1\n")
    fails("obs", exact("obs: unknown observation file type ''; expected .csv, .npy or .npz"))


def test_newline_in_a_quoted_name_stays_on_one_line():
    write("obs.csv", '"a\nb",z\n1\n')
    fails("obs.csv", r"^obs\.csv line 3: 1 value, the header has 2 columns \(a\\nb, z\)$")


# --- errors: .npy and .npz ------------------------------------------------------------------

def test_npy_nan_names_row_and_column():
    z = np.zeros(6)
    z[3] = np.nan
    np.save("obs.npy", z)
    err = fails("obs.npy", exact("obs.npy row 3, column 0: nan (observations must be finite)"))
    assert err.row == 3 and err.column == 0


def test_npy_shape():
    np.save("obs.npy", np.zeros((3, 4, 5)))
    fails("obs.npy", exact("obs.npy: shape (3, 4, 5), expected (T, m) or (T,)"))
    np.save("scalar.npy", np.float64(1.0))
    fails("scalar.npy", exact("scalar.npy: shape (), expected (T, m) or (T,)"))
    np.save("empty.npy", np.zeros((0, 2)))
    fails("empty.npy", exact("empty.npy: no rows (shape (0, 2))"))
    np.save("nocols.npy", np.zeros((2, 0)))
    fails("nocols.npy", exact("nocols.npy: no columns (shape (2, 0))"))


def test_npy_against_the_model():
    np.save("obs.npy", np.zeros((4, 3)))
    fails("obs.npy", exact("obs.npy: 3 observation columns (z0, z1, z2), the model observes 2 values per step"),
          obs_dim=2)


def test_npy_not_numeric():
    np.save("obs.npy", np.array(["a", "b"]))
    fails("obs.npy", exact("obs.npy: dtype <U1 is not numeric; expected integers or floats"))
    np.save("complex.npy", np.ones(2, dtype=complex))
    fails("complex.npy", r"^complex\.npy: dtype complex128 is not numeric")


class _Trap:
    """Unpickling it would create a directory: the proof that something ran."""

    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return (os.mkdir, (self.path,))


def test_pickled_object_npy_is_refused_and_nothing_runs(in_tmp):
    trap = str(in_tmp / "unpickled")
    np.save("obs.npy", np.array([_Trap(trap), 1], dtype=object), allow_pickle=True)
    fails("obs.npy", r"^obs\.npy: holds Python objects \(a pickled object array, dtype object\)")
    assert not os.path.exists(trap)


def test_pickled_object_array_in_npz_is_refused_and_nothing_runs(in_tmp):
    trap = str(in_tmp / "unpickled")
    np.savez("obs.npz", observations=np.array([_Trap(trap)], dtype=object))
    fails("obs.npz", r"^obs\.npz array 'observations': holds Python objects")
    assert not os.path.exists(trap)


def test_npy_cut_short():
    np.save("obs.npy", np.zeros((100, 2)))
    size = os.path.getsize("obs.npy")
    with open("obs.npy", "r+b") as handle:
        handle.truncate(size - 8)
    fails("obs.npy", r"^obs\.npy: cut short: shape \(100, 2\) of float64 needs 1600 bytes of data, "
                     r"the file holds 1592: 99 whole rows of the 100 its header declares \(row 99 missing\)$")


def test_npy_and_npz_that_are_not_what_they_say():
    write("text.npy", "z\n1\n")
    fails("text.npy", exact("text.npy: not a NumPy .npy file (it starts with b'z\\n1\\n')"))
    np.savez("archive.npz", z=np.ones(2))
    os.rename("archive.npz", "archive.npy")
    fails("archive.npy", exact("archive.npy: not a NumPy .npy file; it is a .npz archive (rename it to .npz)"))
    write("text.npz", "z\n1\n")
    fails("text.npz", exact("text.npz: not a NumPy .npz archive (it starts with b'z\\n1\\n')"))
    np.save("array.npy", np.ones(2))
    os.rename("array.npy", "array.npz")
    fails("array.npz", exact("array.npz: not a NumPy .npz archive; it is a .npy file (rename it to .npy)"))


def test_npz_without_observations():
    np.savez("obs.npz", a=np.ones(2), b=np.ones(2))
    fails("obs.npz", exact("obs.npz: no array 'observations' (or 'z'); it holds: a, b"))
    np.savez("truth_only.npz", truth=np.ones(2))
    fails("truth_only.npz", exact("truth_only.npz: no array 'observations' (or 'z'); it holds: truth"))
    np.savez("empty.npz")
    fails("empty.npz", exact("empty.npz: no array 'observations' (or 'z'); it holds no arrays"))


def test_npz_both_name_and_alias():
    np.savez("obs.npz", observations=np.ones(2), z=np.ones(2))
    fails("obs.npz", exact("obs.npz: both 'observations' and 'z'; keep one observations array"))


def test_npz_lengths_differ():
    np.savez("obs.npz", observations=np.ones((5, 2)), truth=np.ones((4, 3)), time=np.arange(5.0))
    fails("obs.npz", exact("obs.npz: arrays differ in length (rows): 'observations' 5, 'truth' 4, 'time' 5"))


def test_npz_bad_values_name_the_array():
    np.savez("obs.npz", z=np.ones(3), x=np.array([[1.0, 2.0], [1.0, np.inf], [0.0, 0.0]]))
    fails("obs.npz", exact("obs.npz array 'x' row 1, column 1: inf (truth must be finite)"))
    np.savez("time.npz", z=np.ones(3), time=np.array([0.0, 2.0, 1.0]))
    fails("time.npz", exact("time.npz array 'time' row 2: 1.0 is before 2.0 in row 1"))
    np.savez("shape.npz", z=np.ones((3, 1, 1)))
    fails("shape.npz", exact("shape.npz array 'z': shape (3, 1, 1), expected (T, m) or (T,)"))
    np.savez("tshape.npz", z=np.ones(3), t=np.ones((3, 2)))
    fails("tshape.npz", exact("tshape.npz array 't': shape (3, 2), expected (T,)"))


def test_npz_against_the_model():
    np.savez("obs.npz", z=np.ones((3, 2)), x=np.ones((3, 3)))
    table = read_observations("obs.npz", state_dim=4)  # the truth covers the state's first three components
    assert table.truth.shape == (3, 3) and table.truth_components == (0, 1, 2)
    fails("obs.npz", exact("obs.npz: 3 truth columns (x0, x1, x2), more than the model's state has (2 dimensions)"),
          state_dim=2)


def test_npz_unpacking_beyond_the_limit(monkeypatch):
    np.savez_compressed("obs.npz", z=np.zeros(100_000))
    monkeypatch.setattr(obs_module, "MAX_FILE_BYTES", os.path.getsize("obs.npz") + 10)
    fails("obs.npz", r"^obs\.npz: its arrays unpack to 800128 bytes .* more than the limit of .*\(MAX_FILE_BYTES\)$")


def test_column_options_apply_to_csv_only():
    np.save("obs.npy", np.ones(2))
    fails("obs.npy", r"^obs\.npy: observation_columns, truth_columns and time_column apply to \.csv files only",
          observation_columns=["z0"])


# --- invalid arguments ----------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, match", [
    ({"steps": 0}, "steps must be a positive integer, got 0"),
    ({"steps": 2.5}, "steps must be a positive integer, got 2.5"),
    ({"obs_dim": True}, "obs_dim must be a positive integer, got True"),
    ({"state_dim": -1}, "state_dim must be a positive integer, got -1"),
    ({"observation_columns": []}, "observation_columns is empty"),
    ({"observation_columns": "range"}, "observation_columns must be a list of column names"),
    ({"truth_columns": ["a", "a"]}, "truth_columns names column 'a' twice"),
    ({"observation_columns": ["a"], "truth_columns": ["a"]}, "column 'a' is in both observation_columns "
                                                             "and truth_columns"),
    ({"truth_columns": ["t"], "time_column": "t"}, "column 't' is in both truth_columns and time_column"),
])
def test_invalid_arguments_are_plain_value_errors(kwargs, match):
    write("obs.csv", "t,a\n0,1\n")
    with pytest.raises(ValueError, match=match) as caught:
        read_observations("obs.csv", **kwargs)
    assert not isinstance(caught.value, ObservationError)


def test_observation_error_is_a_value_error_in_one_line():
    err = ObservationError("a\nb\r\nc", source="f")
    assert isinstance(err, ValueError) and "\n" not in str(err) and "\r" not in str(err)
    assert err.source == "f" and err.line is None


# --- a run on a file: every row, in the library as on the command line --------------------------

def test_a_library_run_on_a_file_reads_every_row_as_dtpf_run_does(tmp_path):
    """dtpf.RunConfig(model=..., observations="file.csv") without steps reads every row, as dtpf run does
    (it was cut to RunConfig's default of 100 steps without a word); steps given, and simulations and live
    runs without steps, keep their numbers."""
    import argparse

    from conftest import ROOT

    from dtpf.messages.config import RunConfig, add_run_arguments, config_from_args
    from dtpf.scripts import inprocess

    lines = (ROOT / "docs/examples/range_bearing_no_truth.csv").read_text().splitlines()
    body = lines[1:]
    rows = [lines[0]] + [f"{k + 1}.0," + line.split(",", 1)[1] for k, line in enumerate(body + body[:80])]
    path = tmp_path / "long.csv"
    path.write_text("\n".join(rows) + "\n")
    model = f"{ROOT / 'docs/examples/range_bearing.py'}:RangeBearingTarget"
    config = RunConfig(model=model, observations=str(path), particles=50)
    assert config.steps is None
    parser = argparse.ArgumentParser()
    add_run_arguments(parser)
    assert config_from_args(parser.parse_args(["--model", model, "--observations", str(path), "-n", "50"])) == config
    assert inprocess.run(config).means.shape[0] == 180
    assert inprocess.run(RunConfig(model=model, observations=str(path), particles=50, steps=100)).means.shape[0] == 100
    assert RunConfig().steps == 100 and RunConfig(model=model, observations="live").steps == 100
    assert RunConfig(model=model, observations=str(path), steps=None).steps is None
