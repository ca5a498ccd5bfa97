"""Observations of a real system, read from a file: the twin's input.

A twin of a real system filters the measurements the system produced, not a
simulation. Give them as a file (``--observations FILE``); the filter runs
one step per row. Three kinds of file are read:

CSV (``.csv``)
    A header line naming the columns, then one row per step::

        # radar, 1 Hz; lines starting with '#' are comments
        time,range,bearing,truth_x,truth_y,truth_vx,truth_vy
        0.0,1012.5,0.7854,716.0,716.0,-5.0,3.0
        1.0,1006.1,0.7901,711.0,719.0,-5.0,3.0
        2.0,999.8,0.7949,706.0,722.0,-5.0,3.0

    Column roles come from the names: ``time``, ``t``, ``timestamp`` or
    ``stamp`` (any case, at most one such column) is the time of each row;
    ``truth`` and names starting with ``truth_`` or ``true_`` (any case) are
    the true state, when it is known (a test rig, a replayed simulation), in
    file order; every other column is an observation, in file order. Here the
    filter sees 2 values per step (range, bearing), the truth has 4
    dimensions. The truth may cover a part of the state: ``truth_x,truth_y``
    of a state (x, y, vx, vy) are its first two components (truth columns are
    the state's leading components, in file order), and names that end in a
    component number (``truth_0``, ``truth_x2``, ``true_3``) say which
    component each is; RMSE is then over those components. To choose otherwise, name the columns: ``observation_columns``,
    ``truth_columns`` (``[]`` for none) and ``time_column`` select by exact
    name, in the order given; columns a role leaves out are not read (a
    time- or truth-named column that is not chosen is ignored, never an
    observation). Values are comma-separated and may be quoted; whitespace
    around names and values, a UTF-8 byte-order mark and blank lines at the
    end are allowed.

NumPy array (``.npy``)
    The observations, shape ``(T, m)``, or ``(T,)`` for one value per step;
    integers or floats. Columns are named ``z0 .. z(m-1)``.

NumPy archive (``.npz``, as written by ``np.savez``)
    Arrays ``observations`` (or ``z``; an archive holding a single array may
    name it anything), ``truth`` (or ``x``; optional, ``(T, d)`` or ``(T,)``)
    and ``time`` (or ``t``; optional, ``(T,)``), all with the same ``T``.
    Truth columns are named ``x0 .. x(d-1)``, the state's leading components
    (a ``(T, 2)`` truth of a 4-d state: x[0], x[1]). Other arrays are ignored.

In Python::

    from dtpf.entity.observations import read_observations
    table = read_observations("radar.csv", obs_dim=2, state_dim=4)
    table.observations      # (T, 2) float64: range, bearing per step
    table.truth             # (T, 4) float64, or None without truth columns
    table.truth_components  # (0, 1, 2, 3): the state components the truth columns hold
    table.times             # (T,) float64, or None without a time column
    table.columns           # ('range', 'bearing')
    table.head(100)         # the first 100 steps

Every value must be a finite number; times must not decrease (equal times
are allowed). ``steps=K`` reads only the first K rows: nothing after them is
read, parsed or checked. ``obs_dim``/``state_dim`` (the model's) are checked
against the columns found, so a file for another model fails before step 1.

Every problem with a file raises :class:`ObservationError` (a
:class:`ValueError`) with a one-line message that starts with the file name
and names the line (CSV, counted from 1 as editors do) or the row (arrays,
counted from 0 as NumPy does), the column and the value::

    radar.csv line 7: 2 values, the header has 3 columns (time, range, bearing)
    radar.csv line 5, column 'range': 'abc' is not a number
    radar.csv line 9, column 'bearing': NaN (observations must be finite)
    radar.csv line 8, column 'time': 3.0 is before 4.0 on the line above
    radar.csv: 1 observation column (range), the model observes 2 values per step
    radar.csv: 5 truth columns (truth_x, ...), more than the model's state has (4 dimensions)
    radar.npy row 3, column 0: nan (observations must be finite)

Invalid arguments (``steps=0``, a name listed twice, one column in two
roles) raise a plain :class:`ValueError`.

What a hostile file can cost is bounded: files larger than
:data:`MAX_FILE_BYTES` (and archives whose arrays unpack to more) are refused
before reading; a CSV header may have at most :data:`MAX_COLUMNS` columns and
a line at most :data:`MAX_LINE_CHARS` characters; arrays are read with
``allow_pickle`` off and their headers are checked against the file's size
before any data is allocated, so nothing in a file is ever executed.
"""
from __future__ import annotations

import csv
import math
import operator
import os
import re
import zipfile
import zlib
from array import array
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.lib import format as npy_format

from dtpf.messages.config import RunInputError

__all__ = ["ObservationError", "ObservationTable", "read_observations",
           "MAX_FILE_BYTES", "MAX_COLUMNS", "MAX_LINE_CHARS"]

#: Largest file read (bytes); for an .npz archive, also the most its arrays
#: may unpack to. Checked before reading, so a mistaken path to a disk image
#: fails at once.
MAX_FILE_BYTES = 2 * 1024**3

#: Most columns a CSV header may have.
MAX_COLUMNS = 10_000

#: Longest CSV line read (characters): room for MAX_COLUMNS values of up to
#: 100 characters each. Without it one line without a newline could hold
#: the whole file.
MAX_LINE_CHARS = 100 * MAX_COLUMNS

#: Names of the time column (compared case-insensitively).
TIME_NAMES = frozenset({"time", "t", "timestamp", "stamp"})

#: Array names in an .npz archive: the role, then its names in order of preference.
NPZ_NAMES = {"observations": ("observations", "z"), "truth": ("truth", "x"), "time": ("time", "t")}

_SUFFIXES = (".csv", ".npy", ".npz")
_NPY_MAGIC = b"\x93NUMPY"
_ZIP_MAGIC = b"PK"


class ObservationError(RunInputError):
    """A file of observations cannot be used; the message is one line.

    Attributes
    ----------
    source : str or None
        The file, as given.
    line : int or None
        The CSV line (counted from 1), when the problem has one.
    row : int or None
        The array row (counted from 0), when the problem has one.
    column : str or int or None
        The CSV column name or the array column index.
    """

    def __init__(self, message: str, *, source: str | None = None, line: int | None = None,
                 row: int | None = None, column: str | int | None = None):
        super().__init__(" ".join(str(message).split("\n")).replace("\r", " "))
        self.source = source
        self.line = line
        self.row = row
        self.column = column


@dataclass(frozen=True, eq=False)  # eq=False: == on arrays has no single truth value; compare fields
class ObservationTable:
    """Observations of T steps, with the truth and times when the file has them.

    Attributes
    ----------
    observations : (T, m) ndarray
        float64, C-contiguous, read-only; row k is the observation of step k + 1.
    truth : (T, d) ndarray or None
        The true state per step (float64, read-only), when known.
    times : (T,) ndarray or None
        The time of each row (float64, non-decreasing, read-only).
    columns : tuple of str
        Names of the m observation columns (``z0 ..`` for arrays).
    truth_columns : tuple of str
        Names of the d truth columns (``x0 ..`` for arrays); empty without truth.
    source : str
        The file, as given.
    truth_components : tuple of int
        The state component each truth column holds (default: 0 .. d-1, the
        state's leading components); empty without truth.
    problem : str or None
        What the file lacked, when only part of it could be read (a rosbag2
        log cut short); None for a whole file.
    stamps : (T,) ndarray or None
        The time of each row as int64 nanoseconds since the Unix epoch, when
        the file's times are a clock's (a rosbag2 log's receive times, the
        step times of its run's estimates); None otherwise.
    """

    observations: np.ndarray
    truth: np.ndarray | None
    times: np.ndarray | None
    columns: tuple[str, ...]
    truth_columns: tuple[str, ...]
    source: str
    truth_components: tuple[int, ...] | None = None
    #: What the file lacked, in words, when only part of it could be read (a rosbag2 log cut short).
    problem: str | None = None
    stamps: np.ndarray | None = None

    def __post_init__(self):
        z = _frozen(self.observations)
        if z.ndim != 2 or z.shape[0] < 1 or z.shape[1] < 1:
            raise ValueError(f"observations must have shape (T, m) with T, m >= 1, got shape {z.shape}")
        columns = tuple(self.columns)
        if len(columns) != z.shape[1]:
            raise ValueError(f"{len(columns)} column names for {z.shape[1]} observation columns")
        truth, truth_columns = self.truth, tuple(self.truth_columns)
        if truth is not None:
            truth = _frozen(truth)
            if truth.ndim != 2 or truth.shape[0] != z.shape[0] or truth.shape[1] < 1:
                raise ValueError(f"truth must have shape ({z.shape[0]}, d), got shape {truth.shape}")
            if len(truth_columns) != truth.shape[1]:
                raise ValueError(f"{len(truth_columns)} truth column names for {truth.shape[1]} truth columns")
        elif truth_columns:
            raise ValueError(f"truth columns {truth_columns} without truth")
        components = self.truth_components
        if components is None:
            components = tuple(range(len(truth_columns)))
        components = tuple(int(c) for c in components)
        if len(components) != len(truth_columns) or len(set(components)) != len(components) \
                or any(c < 0 for c in components):
            raise ValueError(f"truth_components {components} must name a distinct state component (>= 0) for "
                             f"each of the {len(truth_columns)} truth columns")
        object.__setattr__(self, "truth_components", components)
        times = self.times
        if times is not None:
            times = _frozen(times)
            if times.shape != (z.shape[0],):
                raise ValueError(f"times must have shape ({z.shape[0]},), got shape {times.shape}")
        stamps = self.stamps
        if stamps is not None:
            stamps = np.array(stamps, dtype=np.int64, order="C", copy=True)  # integer ns: float64 would round
            stamps.flags.writeable = False
            if stamps.shape != (z.shape[0],):
                raise ValueError(f"stamps must have shape ({z.shape[0]},), got shape {stamps.shape}")
        for field, value in (("observations", z), ("truth", truth), ("times", times), ("stamps", stamps),
                             ("columns", columns), ("truth_columns", truth_columns)):
            object.__setattr__(self, field, value)
        object.__setattr__(self, "source", str(self.source))

    @property
    def steps(self) -> int:
        """T, the number of rows: one filter step each."""
        return self.observations.shape[0]

    def covers(self, state_dim: int) -> bool:
        """Whether the truth is the whole state of ``state_dim`` components, in order."""
        return self.truth is not None and self.truth_components == tuple(range(state_dim))

    def head(self, steps: int | None) -> ObservationTable:
        """The first ``steps`` rows (all of them if ``steps`` is None or at least T)."""
        steps = _check_count(steps, "steps")
        if steps is None or steps >= self.steps:
            return self
        return ObservationTable(
            observations=self.observations[:steps],
            truth=None if self.truth is None else self.truth[:steps],
            times=None if self.times is None else self.times[:steps],
            columns=self.columns, truth_columns=self.truth_columns, source=self.source,
            truth_components=self.truth_components, stamps=None if self.stamps is None else self.stamps[:steps])


def read_observations(path, *, obs_dim: int | None = None, state_dim: int | None = None,
                      steps: int | None = None, observation_columns: list[str] | None = None,
                      truth_columns: list[str] | None = None,
                      time_column: str | None = None, kind: str | None = None,
                      exact_stamps: bool = False) -> ObservationTable:
    """Read the observations in ``path`` (.csv, .npy or .npz); see the module docstring.

    Parameters
    ----------
    path : str or os.PathLike
        The file; its extension (any case) says how to read it.
    obs_dim : int, optional
        Values the model observes per step; the file must have that many
        observation columns.
    state_dim : int, optional
        Dimension of the model's state; truth, when the file has it, must
        have at most that many columns (a leading part of the state, or the
        components its names number).
    steps : int, optional
        Read only the first ``steps`` rows (all if None or if there are fewer).
    observation_columns, truth_columns : list of str, optional
        CSV only: the columns of each role, by exact name, in this order
        (``truth_columns=[]``: no truth). By default, roles come from the names.
    time_column : str, optional
        CSV only: the time column, by exact name.
    kind : str, optional
        ".csv", ".npy" or ".npz": read the file as that kind whatever its extension (default: by the
        extension).
    exact_stamps : bool
        Also give each row's time as integer nanoseconds (``stamps``), from the time column's text (CSV:
        exact to the nanosecond, never through a float; an .npz array ``stamps`` of integers is taken as it
        is, a float ``time`` array is rounded to the nanosecond). Times must then be >= 0.

    Returns
    -------
    ObservationTable

    Raises
    ------
    ObservationError
        Anything wrong with the file, or with the file for this model.
    ValueError
        Invalid arguments.
    """
    source = os.fsdecode(path)
    obs_dim = _check_count(obs_dim, "obs_dim")
    state_dim = _check_count(state_dim, "state_dim")
    steps = _check_count(steps, "steps")
    explicit = _check_roles(observation_columns, truth_columns, time_column)
    name = _show(source)
    suffix = os.path.splitext(source)[1] if kind is None else kind
    kind = suffix.lower()
    if kind not in _SUFFIXES:
        raise ObservationError(f"{name}: unknown observation file type {suffix!r}; expected .csv, .npy or .npz",
                               source=source)
    if kind != ".csv" and any(value is not None for value in explicit):
        raise ObservationError(f"{name}: observation_columns, truth_columns and time_column apply to .csv "
                               f"files only; a {kind} file has no column names", source=source)
    _open_check(source, name, kind)
    if kind == ".csv":
        table = _read_csv(source, name, steps, *explicit, obs_dim=obs_dim, state_dim=state_dim,
                          exact_stamps=exact_stamps)
    elif kind == ".npy":
        table = _read_npy(source, name, steps, obs_dim=obs_dim)
    else:
        table = _read_npz(source, name, steps, obs_dim=obs_dim, state_dim=state_dim)
        if exact_stamps and table.stamps is None and table.times is not None:
            table = _with_stamps(table, _float_stamps(table.times, name, source))
    if exact_stamps and table.stamps is None:
        raise ObservationError(f"{name}: no times; each row needs its time (a .csv time column, a .npz array "
                               f"'time' or 't' in seconds; a .npy array has none)", source=source)
    return table


def _with_stamps(table: ObservationTable, stamps: np.ndarray) -> ObservationTable:
    return ObservationTable(observations=table.observations, truth=table.truth, times=table.times,
                            columns=table.columns, truth_columns=table.truth_columns, source=table.source,
                            truth_components=table.truth_components, stamps=stamps)


#: The latest stamp a message's time can hold (uint32 seconds).
_LAST_STAMP = (2**32) * 1_000_000_000 - 1
_DECIMAL = re.compile(r"^\s*\+?(\d*)(?:\.(\d*))?\s*$")


def stamp_of_text(text: str) -> int | None:
    """Integer nanoseconds of a time in seconds written in decimal ('12.000000001'), exactly; None for text
    that is not a non-negative decimal number (an exponent, a sign, more than 9 decimals that are not 0)."""
    match = _DECIMAL.match(text)
    if match is None or not (match.group(1) or match.group(2)):
        return None
    whole, fraction = match.group(1) or "0", match.group(2) or ""
    if len(fraction) > 9 and fraction[9:].strip("0"):
        return None
    return int(whole) * 1_000_000_000 + int((fraction[:9]).ljust(9, "0"))


def _float_stamps(times: np.ndarray, name: str, source: str) -> np.ndarray:
    bad = np.flatnonzero((times < 0) | (times * 1e9 > _LAST_STAMP))
    if bad.size:
        r = int(bad[0])
        raise ObservationError(f"{name} row {r}: time {float(times[r])!r} is not between 0 and 2^32 s",
                               source=source, row=r)
    return np.round(times * 1e9).astype(np.int64)


# --- checks shared by every kind of file ----------------------------------------------

def _check_count(value, what: str) -> int | None:
    """None, or ``value`` as an int >= 1 (ValueError otherwise)."""
    if value is None:
        return None
    if isinstance(value, bool):
        raise ValueError(f"{what} must be a positive integer, got {value!r}")
    try:
        n = operator.index(value)
    except TypeError:
        raise ValueError(f"{what} must be a positive integer, got {value!r}") from None
    if n < 1:
        raise ValueError(f"{what} must be a positive integer, got {value!r}")
    return n


def _check_roles(observation_columns, truth_columns, time_column):
    """The explicit CSV roles as (tuple | None, tuple | None, str | None); ValueError if inconsistent."""
    lists = []
    for what, names in (("observation_columns", observation_columns), ("truth_columns", truth_columns)):
        if names is None:
            lists.append(None)
            continue
        if isinstance(names, str):
            raise ValueError(f"{what} must be a list of column names, got the string {names!r}")
        names = tuple(names)
        for n in names:
            if not isinstance(n, str):
                raise ValueError(f"{what} must hold column names (str), got {n!r}")
        seen = set()
        for n in names:
            if n in seen:
                raise ValueError(f"{what} names column {n!r} twice")
            seen.add(n)
        lists.append(names)
    obs, truth = lists
    if obs is not None and not obs:
        raise ValueError("observation_columns is empty; name at least one column, or pass None to choose by name")
    if time_column is not None and not isinstance(time_column, str):
        raise ValueError(f"time_column must be a column name (str), got {time_column!r}")
    roles = [("observation_columns", obs or ()), ("truth_columns", truth or ()),
             ("time_column", () if time_column is None else (time_column,))]
    for i, (what_a, names_a) in enumerate(roles):
        for what_b, names_b in roles[i + 1:]:
            both = [n for n in names_a if n in names_b]
            if both:
                raise ValueError(f"column {both[0]!r} is in both {what_a} and {what_b}")
    return obs, truth, time_column


def _open_check(source: str, name: str, kind: str) -> None:
    """Check the file exists, is not too large and starts as its kind of file should."""
    try:
        st = os.stat(source)
    except FileNotFoundError:
        raise ObservationError(f"{name}: not found", source=source) from None
    except OSError as exc:
        raise ObservationError(f"{name}: cannot read ({exc.strerror or exc})", source=source) from None
    if os.path.isdir(source):
        raise ObservationError(f"{name}: is a directory, not a file", source=source)
    limit = MAX_FILE_BYTES
    if st.st_size > limit:
        raise ObservationError(f"{name}: {_bytes(st.st_size)}, larger than the limit of {_bytes(limit)} "
                               f"(MAX_FILE_BYTES)", source=source)
    try:
        with open(source, "rb") as handle:
            magic = handle.read(8)
    except OSError as exc:
        raise ObservationError(f"{name}: cannot read ({exc.strerror or exc})", source=source) from None
    is_npy, is_zip = magic.startswith(_NPY_MAGIC), magic.startswith(_ZIP_MAGIC)
    if kind == ".csv" and (is_npy or is_zip):
        actual = ".npy" if is_npy else ".npz"
        raise ObservationError(f"{name}: a {actual} file, not CSV text (rename it to {actual})", source=source)
    if kind == ".npy" and not is_npy:
        hint = "; it is a .npz archive (rename it to .npz)" if is_zip else f" (it starts with {magic!r})"
        raise ObservationError(f"{name}: not a NumPy .npy file{hint}", source=source)
    if kind == ".npz" and not is_zip:
        hint = "; it is a .npy file (rename it to .npy)" if is_npy else f" (it starts with {magic!r})"
        raise ObservationError(f"{name}: not a NumPy .npz archive{hint}", source=source)


#: A truth column named by its state component: truth_0, truth_x2, true_3, x1 (the number is the component).
_NUMBERED_TRUTH = re.compile(r"^(?:(?:truth|true)_?)?[a-z]?(\d+)$", re.IGNORECASE)


def _check_model(name: str, source: str, columns, truth_columns, obs_dim, state_dim) -> tuple[int, ...]:
    """Check the columns against the model; the state component of each truth column."""
    m = len(columns)
    if obs_dim is not None and m != obs_dim:
        raise ObservationError(f"{name}: {_count(m, 'observation column')} ({_names(columns)}), "
                               f"the model observes {_count(obs_dim, 'value')} per step", source=source)
    d = len(truth_columns)
    if state_dim is not None and d > state_dim:
        raise ObservationError(f"{name}: {_count(d, 'truth column')} ({_names(truth_columns)}), more than the "
                               f"model's state has ({_count(state_dim, 'dimension')})", source=source)
    return _truth_components(name, source, truth_columns, state_dim)


def _truth_components(name: str, source: str, truth_columns, state_dim) -> tuple[int, ...]:
    """The state component of each truth column: the number its name ends in when every name has one
    (truth_0, truth_x2), else the leading components in file order."""
    numbers = [_NUMBERED_TRUTH.match(column) for column in truth_columns]
    if not truth_columns or not any(numbers):
        return tuple(range(len(truth_columns)))
    if not all(numbers):
        plain = [c for c, n in zip(truth_columns, numbers) if not n]
        raise ObservationError(f"{name}: truth columns {_names(truth_columns)} mix names numbered by state "
                               f"component with names that are not ({_names(plain)}); number all or none",
                               source=source)
    components = tuple(int(n.group(1)) for n in numbers)
    if len(set(components)) != len(components):
        raise ObservationError(f"{name}: truth columns {_names(truth_columns)} name a state component twice",
                               source=source)
    if state_dim is not None and max(components) >= state_dim:
        column = truth_columns[components.index(max(components))]
        raise ObservationError(f"{name}: truth column {_show(column)} names state component {max(components)}, "
                               f"the model's state has {_count(state_dim, 'dimension')} (0 .. {state_dim - 1})",
                               source=source, column=column)
    return components


def _frozen(a) -> np.ndarray:
    """``a`` as a read-only C-contiguous float64 array (a copy unless it already is one)."""
    if (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous
            and not a.flags.writeable):
        return a
    b = np.array(a, dtype=np.float64, order="C", copy=True)
    b.flags.writeable = False
    return b


# --- words --------------------------------------------------------------------------

def _show(text: str) -> str:
    """A name as it can appear in a one-line message."""
    return text if text.isprintable() else repr(text)[1:-1]


def _names(names: Sequence[str], limit: int = 12) -> str:
    shown = [_show(n) for n in names[:limit]]
    if len(names) > limit:
        shown.append(f"... ({len(names)} in all)")
    return ", ".join(shown)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def _bytes(n: int) -> str:
    return f"{n} bytes ({n / 1024**3:.1f} GiB)"


def _cell(text: str, limit: int = 40) -> str:
    return repr(text) if len(text) <= limit else repr(text[:limit]) + "..."


def _value(v: float) -> str:
    v = float(v)
    return "NaN" if math.isnan(v) else repr(v)


# --- CSV ----------------------------------------------------------------------------

class _Lines:
    """The lines of a text file for :mod:`csv`, without comments, counting them.

    ``number`` is the number of the last line handed out (from 1), so after
    the csv reader returns a row it is the row's (last) line.
    """

    def __init__(self, handle, name: str, source: str):
        self.handle, self.name, self.source = handle, name, source
        self.number = 0

    def __iter__(self):
        readline, limit = self.handle.readline, MAX_LINE_CHARS
        while True:
            line = readline(limit + 1)
            if not line:
                return
            self.number += 1
            if len(line) > limit and line[-1] not in "\r\n":
                raise ObservationError(f"{self.name} line {self.number}: longer than {limit} characters "
                                       f"(MAX_LINE_CHARS)", source=self.source, line=self.number)
            first = line[:1]
            if first == "#" or (first in " \t" and line.lstrip(" \t").startswith("#")):
                continue
            yield line


def _is_blank(row: list[str]) -> bool:
    return not row or (len(row) == 1 and not row[0].strip())


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_csv(source, name, steps, obs_names, truth_names, time_name, *, obs_dim, state_dim, exact_stamps=False):
    try:
        with open(source, encoding="utf-8-sig", newline="") as handle:
            lines = _Lines(handle, name, source)
            reader = csv.reader(lines, skipinitialspace=True)
            try:
                return _parse_csv(reader, lines, source, name, steps, obs_names, truth_names, time_name,
                                  obs_dim=obs_dim, state_dim=state_dim, exact_stamps=exact_stamps)
            except csv.Error as exc:
                raise ObservationError(f"{name} line {lines.number}: not valid CSV ({exc})",
                                       source=source, line=lines.number) from None
    except UnicodeDecodeError as exc:
        line, byte = _first_bad_utf8(source, exc)
        where = f" line {line}" if line else ""
        raise ObservationError(f"{name}{where}: not UTF-8 text (byte 0x{byte:02x})",
                               source=source, line=line) from None
    except OSError as exc:
        raise ObservationError(f"{name}: cannot read ({exc.strerror or exc})", source=source) from None


def _first_bad_utf8(source: str, exc: UnicodeDecodeError) -> tuple[int | None, int]:
    """The line and value of the first byte that is not UTF-8 (the text reader decodes ahead, so
    the line it stopped at is not the one to report)."""
    with open(source, "rb") as handle:
        number = 1
        while True:
            chunk = handle.readline(4 * MAX_LINE_CHARS + 4)
            if not chunk:
                break
            try:
                chunk.decode("utf-8")
            except UnicodeDecodeError as bad:
                return number, chunk[bad.start]
            number += chunk.endswith(b"\n")
    return None, exc.object[exc.start]


def _parse_csv(reader, lines, source, name, steps, obs_names, truth_names, time_name, *, obs_dim, state_dim,
               exact_stamps=False):
    # The header: the first line that is not a comment.
    try:
        header = next(reader)
    except StopIteration:
        why = "the file is empty" if lines.number == 0 else "the file holds only comments"
        raise ObservationError(f"{name} line {lines.number + 1}: no header ({why})",
                               source=source, line=lines.number + 1) from None
    hline = lines.number
    if _is_blank(header):
        raise ObservationError(f"{name} line {hline}: no header (an empty line; the first line must name "
                               f"the columns)", source=source, line=hline)
    if len(header) > MAX_COLUMNS:
        raise ObservationError(f"{name} line {hline}: {len(header)} columns, more than the limit of "
                               f"{MAX_COLUMNS} (MAX_COLUMNS)", source=source, line=hline)
    header = [h.strip() for h in header]
    if all(_is_number(h) for h in header):
        raise ObservationError(f"{name} line {hline}: no header: the first line holds numbers "
                               f"({_names(header, 6)}); it must name the columns, e.g. time,range,bearing",
                               source=source, line=hline)
    where: dict[str, int] = {}
    for i, h in enumerate(header):
        if not h:
            raise ObservationError(f"{name} line {hline}: column {i + 1} has no name; header: {_names(header)}",
                                   source=source, line=hline)
        if h in where:
            raise ObservationError(f"{name} line {hline}: duplicate column name {h!r} "
                                   f"(columns {where[h] + 1} and {i + 1})", source=source, line=hline, column=h)
        where[h] = i
    time_i, obs_i, truth_i = _csv_roles(name, source, header, where, obs_names, truth_names, time_name)
    columns = tuple(header[i] for i in obs_i)
    truth_columns = tuple(header[i] for i in truth_i)
    components = _check_model(name, source, columns, truth_columns, obs_dim, state_dim)

    # The rows: only the chosen columns are parsed, in file order.
    chosen = sorted(set(obs_i) | set(truth_i) | ({time_i} if time_i is not None else set()))
    position = {c: k for k, c in enumerate(chosen)}
    ncols, width = len(header), len(chosen)
    if chosen == list(range(ncols)):
        cells = None
    elif width == 1:
        only = chosen[0]

        def cells(row):
            return (row[only],)
    else:
        cells = operator.itemgetter(*chosen)
    parsed = array("d")  # the chosen values, row after row
    extend, numbers = parsed.extend, array("q")  # numbers: the line of each row
    blank = 0  # the line of a blank line not yet followed by a row
    if exact_stamps and time_i is None:
        raise ObservationError(f"{name}: no time column (time, t, timestamp or stamp, in seconds); each row "
                               f"needs its time", source=source)
    stamp_texts = [] if exact_stamps else None
    for row in reader:
        if len(row) == ncols:
            try:
                extend(map(float, row if cells is None else cells(row)))
            except ValueError:
                if ncols == 1 and not row[0].strip():
                    blank = blank or lines.number
                    continue
                if not blank:
                    raise _cell_error(name, source, lines.number, row, header, chosen) from None
            if blank:
                break
        elif _is_blank(row):
            blank = blank or lines.number
            continue
        elif not blank:
            raise ObservationError(f"{name} line {lines.number}: {_count(len(row), 'value')}, the header has "
                                   f"{_count(ncols, 'column')} ({_names(header)})", source=source,
                                   line=lines.number)
        else:
            break
        numbers.append(lines.number)
        if stamp_texts is not None:
            stamp_texts.append(row[time_i])
        if len(numbers) == steps:
            break
    else:
        blank = 0  # blank lines at the end
    if blank:
        raise ObservationError(f"{name} line {blank}: empty line", source=source, line=blank)
    count = len(numbers)
    if not count:
        raise ObservationError(f"{name}: no data rows", source=source)
    values = np.frombuffer(parsed, dtype=np.float64).reshape(count, width)

    finite = np.isfinite(values)
    if not finite.all():
        r, k = divmod(int(np.argmin(finite.ravel())), values.shape[1])
        c = chosen[k]
        role = "times" if c == time_i else "truth" if c in truth_i else "observations"
        raise ObservationError(f"{name} line {numbers[r]}, column {header[c]!r}: {_value(values[r, k])} "
                               f"({role} must be finite)", source=source, line=numbers[r], column=header[c])
    times = None
    if time_i is not None:
        times = values[:, position[time_i]].copy()
        back = np.flatnonzero(times[1:] < times[:-1])
        if back.size:
            r = int(back[0]) + 1
            above = "on the line above" if numbers[r - 1] == numbers[r] - 1 else f"on line {numbers[r - 1]}"
            raise ObservationError(f"{name} line {numbers[r]}, column {header[time_i]!r}: {float(times[r])!r} is "
                                   f"before {float(times[r - 1])!r} {above}", source=source, line=numbers[r],
                                   column=header[time_i])
        times.flags.writeable = False
    stamps = None
    if stamp_texts is not None:
        stamps = np.empty(count, dtype=np.int64)
        for r, text in enumerate(stamp_texts):
            stamp = stamp_of_text(text)
            if stamp is None or stamp > _LAST_STAMP:
                raise ObservationError(f"{name} line {numbers[r]}, column {header[time_i]!r}: {_cell(text)} is not "
                                       f"a time in seconds from 0 to 2^32 written as a decimal (e.g. 12.25)",
                                       source=source, line=numbers[r], column=header[time_i])
            stamps[r] = stamp
    observations = _take(values, [position[c] for c in obs_i])
    truth = _take(values, [position[c] for c in truth_i]) if truth_i else None
    return ObservationTable(observations=observations, truth=truth, times=times, columns=columns,
                            truth_columns=truth_columns, source=source, truth_components=components,
                            stamps=stamps)


def _take(values: np.ndarray, positions: list[int]) -> np.ndarray:
    if positions == list(range(values.shape[1])):
        out = values
    else:
        out = np.ascontiguousarray(values[:, positions])
    out.flags.writeable = False
    return out


def _cell_error(name, source, line, row, header, chosen) -> ObservationError:
    for c in chosen:
        text = row[c]
        if not text.strip():
            return ObservationError(f"{name} line {line}, column {header[c]!r}: empty",
                                    source=source, line=line, column=header[c])
        if not _is_number(text):
            return ObservationError(f"{name} line {line}, column {header[c]!r}: {_cell(text)} is not a number",
                                    source=source, line=line, column=header[c])
    raise AssertionError("a row that failed to parse has no bad cell")  # pragma: no cover


def _is_time_name(h: str) -> bool:
    return h.lower() in TIME_NAMES


def _is_truth_name(h: str) -> bool:
    low = h.lower()
    return low == "truth" or low.startswith("truth_") or low.startswith("true_")


def _csv_roles(name, source, header, where, obs_names, truth_names, time_name):
    """Column indices of (time or None, observations, truth)."""
    def lookup(names, what):
        for n in names:
            if n not in where:
                raise ObservationError(f"{name}: no column {n!r} ({what}); header: {_names(header)}",
                                       source=source, column=n)
        return [where[n] for n in names]

    claimed = set()
    obs_i = lookup(obs_names, "observation_columns") if obs_names is not None else None
    truth_i = lookup(truth_names, "truth_columns") if truth_names is not None else None
    claimed.update(obs_i or ())
    claimed.update(truth_i or ())
    if time_name is not None:
        time_i = lookup([time_name], "time_column")[0]
    else:
        found = [i for i, h in enumerate(header) if _is_time_name(h) and i not in claimed]
        if len(found) > 1:
            raise ObservationError(f"{name}: {len(found)} time columns ({_names([header[i] for i in found])}); "
                                   f"name one with time_column", source=source)
        time_i = found[0] if found else None
    if time_i is not None:
        claimed.add(time_i)
    if truth_i is None:
        truth_i = [i for i, h in enumerate(header) if _is_truth_name(h) and i not in claimed]
        claimed.update(truth_i)
    if obs_i is None:
        obs_i = [i for i, h in enumerate(header)
                 if i not in claimed and not _is_time_name(h) and not _is_truth_name(h)]
        if not obs_i:
            raise ObservationError(f"{name}: no observation column; header: {_names(header)}", source=source)
    return time_i, obs_i, truth_i


# --- .npy and .npz ------------------------------------------------------------------

@dataclass
class _Header:
    shape: tuple[int, ...]
    fortran: bool
    dtype: np.dtype
    data_bytes: int  # bytes of data after the header (in the file or archive member)


def _npy_header(fp, where: str, source: str, size: int) -> _Header:
    """Read and check the header of a .npy stream of ``size`` bytes; leave ``fp`` at the data."""
    try:
        version = npy_format.read_magic(fp)
        if version == (1, 0):
            shape, fortran, dtype = npy_format.read_array_header_1_0(fp)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = npy_format.read_array_header_2_0(fp)
        else:
            raise ValueError(f"format version {version} is not supported")
    except (ValueError, EOFError, SyntaxError, TypeError) as exc:
        raise ObservationError(f"{where}: not a valid .npy array ({exc})", source=source) from None
    if dtype.hasobject:
        raise ObservationError(f"{where}: holds Python objects (a pickled object array, dtype {dtype}); only "
                               f"numbers are read, and pickles never are", source=source)
    if dtype.kind not in "iuf" or dtype.names is not None or dtype.shape:
        raise ObservationError(f"{where}: dtype {dtype} is not numeric; expected integers or floats",
                               source=source)
    if any(n < 0 for n in shape):
        raise ObservationError(f"{where}: not a valid .npy array (shape {shape})", source=source)
    need = math.prod(shape) * dtype.itemsize
    have = size - fp.tell()
    if have < need:
        held = ""
        if shape and not fortran and shape[0] > 0:  # C order: whole rows first, so say how many are there
            row_bytes = need // shape[0]
            rows = max(have, 0) // row_bytes if row_bytes else 0
            missing = f"row {rows}" if rows == shape[0] - 1 else f"rows {rows} to {shape[0] - 1}"
            held = (f": {rows} whole row{'' if rows == 1 else 's'} of the {shape[0]} its header declares "
                    f"({missing} missing)")
        raise ObservationError(f"{where}: cut short: shape {shape} of {dtype} needs {need} bytes of data, "
                               f"the file holds {max(have, 0)}{held}", source=source)
    return _Header(shape, fortran, dtype, need)


def _check_shape(header: _Header, where: str, source: str, columns: bool = True):
    shape = header.shape
    if columns:
        if len(shape) not in (1, 2):
            raise ObservationError(f"{where}: shape {shape}, expected (T, m) or (T,)", source=source)
    elif not (len(shape) == 1 or (len(shape) == 2 and shape[1] == 1)):
        raise ObservationError(f"{where}: shape {shape}, expected (T,)", source=source)
    if shape[0] == 0:
        raise ObservationError(f"{where}: no rows (shape {shape})", source=source)
    if len(shape) == 2 and shape[1] == 0:
        raise ObservationError(f"{where}: no columns (shape {shape})", source=source)


def _npy_data(fp, header: _Header, rows: int) -> np.ndarray:
    """The first ``rows`` rows of the array whose data ``fp`` is at, as (rows, m) float64."""
    shape = header.shape
    m = shape[1] if len(shape) == 2 else 1
    if header.fortran and len(shape) == 2 and m > 1:
        raw = fp.read(header.data_bytes)
        a = np.frombuffer(raw, dtype=header.dtype).reshape(shape, order="F")[:rows]
    else:
        raw = fp.read(rows * m * header.dtype.itemsize)
        a = np.frombuffer(raw, dtype=header.dtype).reshape(rows, m)
    out = np.array(a, dtype=np.float64, order="C", copy=True)
    out.flags.writeable = False
    return out


def _check_finite(a: np.ndarray, where: str, source: str, role: str):
    finite = np.isfinite(a)
    if not finite.all():
        r, c = divmod(int(np.argmin(finite.ravel())), a.shape[1])
        raise ObservationError(f"{where} row {r}, column {c}: {float(a[r, c])!r} ({role} must be finite)",
                               source=source, row=r, column=c)


def _check_times(times: np.ndarray, where: str, source: str):
    back = np.flatnonzero(times[1:] < times[:-1])
    if back.size:
        r = int(back[0]) + 1
        raise ObservationError(f"{where} row {r}: {float(times[r])!r} is before {float(times[r - 1])!r} "
                               f"in row {r - 1}", source=source, row=r)


def _read_npy(source, name, steps, *, obs_dim):
    try:
        with open(source, "rb") as fp:
            header = _npy_header(fp, name, source, os.fstat(fp.fileno()).st_size)
            _check_shape(header, name, source)
            m = header.shape[1] if len(header.shape) == 2 else 1
            columns = tuple(f"z{j}" for j in range(m))
            _check_model(name, source, columns, (), obs_dim, None)
            rows = header.shape[0] if steps is None else min(steps, header.shape[0])
            z = _npy_data(fp, header, rows)
    except OSError as exc:
        raise ObservationError(f"{name}: cannot read ({exc.strerror or exc})", source=source) from None
    _check_finite(z, name, source, "observations")
    return ObservationTable(observations=z, truth=None, times=None, columns=columns, truth_columns=(),
                            source=source)


def _read_npz(source, name, steps, *, obs_dim, state_dim):
    try:
        with zipfile.ZipFile(source) as archive:
            return _read_archive(archive, source, name, steps, obs_dim=obs_dim, state_dim=state_dim)
    except zipfile.BadZipFile as exc:
        raise ObservationError(f"{name}: not a valid .npz archive ({exc})", source=source) from None
    except (OSError, EOFError, RuntimeError, NotImplementedError, zlib.error) as exc:
        raise ObservationError(f"{name}: cannot read the archive ({type(exc).__name__}: {exc})",
                               source=source) from None


def _read_archive(archive: zipfile.ZipFile, source, name, steps, *, obs_dim, state_dim):
    members: dict[str, zipfile.ZipInfo] = {}
    for info in archive.infolist():
        if info.is_dir():
            continue
        key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
        members.setdefault(key, info)
    total = sum(info.file_size for info in members.values())
    if total > MAX_FILE_BYTES:
        raise ObservationError(f"{name}: its arrays unpack to {_bytes(total)}, more than the limit of "
                               f"{_bytes(MAX_FILE_BYTES)} (MAX_FILE_BYTES)", source=source)
    held = f"it holds: {_names(list(members))}" if members else "it holds no arrays"

    def find(role):
        present = [n for n in NPZ_NAMES[role] if n in members]
        if len(present) > 1:
            raise ObservationError(f"{name}: both {present[0]!r} and {present[1]!r}; keep one {role} array",
                                   source=source)
        return present[0] if present else None

    keys = {role: find(role) for role in NPZ_NAMES}
    if keys["observations"] is None:
        other = [k for k in members if k not in NPZ_NAMES["truth"] + NPZ_NAMES["time"]]
        if len(members) == 1 and other:
            keys["observations"] = other[0]
        else:
            raise ObservationError(f"{name}: no array 'observations' (or 'z'); {held}", source=source)

    headers: dict[str, _Header] = {}
    for role, key in keys.items():
        if key is None:
            continue
        where = f"{name} array {key!r}"
        info = members[key]
        with archive.open(info) as fp:
            header = _npy_header(fp, where, source, info.file_size)
        _check_shape(header, where, source, columns=(role != "time"))
        headers[role] = header
    lengths = {keys[role]: h.shape[0] for role, h in headers.items()}
    if len(set(lengths.values())) > 1:
        listed = ", ".join(f"{k!r} {n}" for k, n in lengths.items())
        raise ObservationError(f"{name}: arrays differ in length (rows): {listed}", source=source)

    def width(role):
        shape = headers[role].shape
        return shape[1] if len(shape) == 2 else 1

    columns = tuple(f"z{j}" for j in range(width("observations")))
    truth_columns = tuple(f"x{j}" for j in range(width("truth"))) if "truth" in headers else ()
    components = _check_model(name, source, columns, truth_columns, obs_dim, state_dim)

    T = headers["observations"].shape[0]
    rows = T if steps is None else min(steps, T)
    data = {}
    for role, header in headers.items():
        key = keys[role]
        where = f"{name} array {key!r}"
        with archive.open(members[key]) as fp:
            _npy_header(fp, where, source, members[key].file_size)
            data[role] = _npy_data(fp, header, rows)
            while fp.read(1 << 20):  # to the member's end, where zipfile checks its CRC: rows read are intact
                pass
        _check_finite(data[role], where, source, "times" if role == "time" else role)
    times = None
    if "time" in data:
        times = data["time"][:, 0]
        _check_times(times, f"{name} array {keys['time']!r}", source)
    return ObservationTable(observations=data["observations"], truth=data.get("truth"), times=times,
                            columns=columns, truth_columns=truth_columns, source=source,
                            truth_components=components)
