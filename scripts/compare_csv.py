"""The CSV of ``dtpf compare``: one row per (variant, seed), appended as each run ends, read back to resume.

Each row holds the cell (``--grid``; empty without one), the variant's label, its spec as given, the
settings the run had but its seed (JSON, :func:`~dtpf.scripts.compare_variants.settings_of`), the seed,
the metric's name and value, the mean ESS, the mean distinct ancestors of a resampling / N, the share
of steps preprocessed, the mean log predictive per step, the steps and the milliseconds per step.
Numbers are written in full (``repr``), so a table made from the file equals the one made from the runs.
A file of the first layout (no cell, no distinct, preprocessed or log predictive) is read, its missing
figures NaN, and appended to in its own layout. A file with another header is not ours; a label whose
rows were run with other settings, or judged by another metric, would mix two experiments: each is a
one-line error.
"""
from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

from dtpf.messages.config import RunInputError

__all__ = ["HEADER", "FIRST_HEADER", "RunRow", "CompareCsv"]

HEADER = ("cell", "variant", "spec", "settings", "seed", "metric", "value", "mean_ess", "distinct", "preprocessed",
          "log_predictive", "steps", "ms_per_step")
#: The layout of the files of dtpf compare's first form, still read and appended to.
FIRST_HEADER = ("variant", "spec", "settings", "seed", "metric", "value", "mean_ess", "steps", "ms_per_step")
_NAN = float("nan")


@dataclass(frozen=True)
class RunRow:
    """The figures of one run of one variant (in one cell of a grid)."""

    variant: str
    spec: str
    settings: str
    seed: int
    metric: str
    value: float
    mean_ess: float
    steps: int
    ms_per_step: float
    cell: str = ""
    distinct: float = _NAN
    preprocessed: float = _NAN
    log_predictive: float = _NAN

    @property
    def key(self) -> tuple[str, str, int]:
        """(cell, label, seed): what a compare runs once."""
        return self.cell, self.variant, self.seed

    def cells(self, header: tuple[str, ...] = HEADER) -> list[str]:
        """The row's cells under ``header`` (:data:`HEADER` or :data:`FIRST_HEADER`)."""
        text = {name: repr(value) if isinstance(value, float) else str(value) for name, value in vars(self).items()}
        return [text[name] for name in header]

    @classmethod
    def of_cells(cls, header: tuple[str, ...], cells: list[str]) -> "RunRow":
        """The row of a file's line under ``header``; ValueError for a line that is not one."""
        if len(cells) != len(header):
            raise ValueError
        named = dict(zip(header, cells))
        return cls(**{name: kind(named[name]) if name in named else default
                      for name, (kind, default) in _FIELDS.items()})


#: Each field of a row: how its text is read, and its value in a file that lacks it.
_FIELDS = {"variant": (str, None), "spec": (str, None), "settings": (str, None), "seed": (int, None),
           "metric": (str, None), "value": (float, None), "mean_ess": (float, None), "steps": (int, None),
           "ms_per_step": (float, None), "cell": (str, ""), "distinct": (float, _NAN),
           "preprocessed": (float, _NAN), "log_predictive": (float, _NAN)}


class CompareCsv:
    """A compare CSV: :meth:`read` what it holds (checked), :meth:`append` a run as soon as it ends."""

    def __init__(self, path: Path):
        self.path = Path(path)
        #: The layout rows are written in: the file's own, once read.
        self.header = HEADER

    def read(self) -> tuple[dict[tuple[str, str, int], RunRow], str | None]:
        """The rows by (cell, label, seed) (the first of a repeated one) and a note when an incomplete last
        line (a run cut off while it was written) was dropped; an empty or missing file holds none."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            return {}, None
        with open(self.path, newline="") as handle:
            text = handle.read()
        note = None
        if not text.endswith("\n"):
            kept = text[: text.rfind("\n") + 1]
            note = f"{self.path}: dropped an incomplete last line ({len(text) - len(kept)} bytes)"
            text = kept
            with open(self.path, "w", newline="") as handle:
                handle.write(text)
        lines = list(csv.reader(io.StringIO(text, newline="")))
        if not lines or tuple(lines[0]) not in (HEADER, FIRST_HEADER):
            found = ",".join(lines[0]) if lines else "nothing"
            raise RunInputError(f"--csv {self.path}: not a dtpf compare CSV (its header is {found[:80]!r}); "
                                f"give another file")
        self.header = tuple(lines[0])
        rows: dict[tuple[str, str, int], RunRow] = {}
        for number, cells in enumerate(lines[1:], 2):
            if not cells:
                continue
            try:
                row = RunRow.of_cells(self.header, cells)
            except (ValueError, TypeError):
                raise RunInputError(f"--csv {self.path}: line {number} is not a compare row") from None
            rows.setdefault(row.key, row)
        return rows, note

    def check(self, rows: dict[tuple[str, str, int], RunRow], settings: dict[tuple[str, str], str],
              metric: str | None = None) -> None:
        """RunInputError when a (cell, label) of ``settings`` (its settings now) has rows run with other settings,
        or judged by another metric than ``metric`` (its CSV name)."""
        if any(cell for cell, _ in settings) and self.header == FIRST_HEADER:
            raise RunInputError(f"--csv {self.path}: a file of dtpf compare's first layout holds no cells; give "
                                f"another --csv for a --grid")
        for (cell, label, seed), row in rows.items():
            now = settings.get((cell, label))
            if now is None:
                continue
            where = f"variant {label!r}" + (f" of cell {cell!r}" if cell else "")
            if row.settings != now:
                raise RunInputError(f"--csv {self.path}: {where} was run there with "
                                    f"{_difference(row.settings, now)}; give another --csv or another label")
            if metric is not None and row.metric != metric:
                raise RunInputError(f"--csv {self.path}: {where} was judged there by the metric {row.metric} (now "
                                    f"{metric}); give another --csv")

    def start(self) -> None:
        """Write the header to a new or empty file."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "w", newline="") as handle:
                csv.writer(handle, lineterminator="\n").writerow(self.header)

    def append(self, row: RunRow) -> None:
        """Add one run's row, flushed at once (an interrupted compare keeps every finished run)."""
        with open(self.path, "a", newline="") as handle:
            csv.writer(handle, lineterminator="\n").writerow(row.cells(self.header))


def _difference(before: str, now: str) -> str:
    """What differs between two settings texts, ``field a (now b)``."""
    try:
        old, new = json.loads(before), json.loads(now)
    except ValueError:
        return f"other settings ({before})"
    changed = [f"{name} {old.get(name, 'default')} (now {new.get(name, 'default')})"
               for name in dict.fromkeys([*old, *new]) if old.get(name) != new.get(name)]
    return ", ".join(changed) or f"other settings ({before})"
