"""The CSV of ``dtpf compare``: one row per (variant, seed), appended as each run ends, read back to resume.

Each row holds the variant's label, its spec as given, the settings the run had but its seed (JSON,
:func:`~dtpf.scripts.compare_variants.settings_of`), the seed, the metric's name and value, the mean
ESS, the steps and the milliseconds per step. Numbers are written in full (``repr``), so a table made
from the file equals the one made from the runs. A file with another header is not ours; a label whose
rows were run with other settings would mix two experiments: both are one-line errors.
"""
from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

from dtpf.messages.config import RunInputError

__all__ = ["HEADER", "RunRow", "CompareCsv"]

HEADER = ("variant", "spec", "settings", "seed", "metric", "value", "mean_ess", "steps", "ms_per_step")


@dataclass(frozen=True)
class RunRow:
    """The figures of one run of one variant."""

    variant: str
    spec: str
    settings: str
    seed: int
    metric: str
    value: float
    mean_ess: float
    steps: int
    ms_per_step: float

    def cells(self) -> list[str]:
        return [self.variant, self.spec, self.settings, str(self.seed), self.metric, repr(self.value),
                repr(self.mean_ess), str(self.steps), repr(self.ms_per_step)]


class CompareCsv:
    """A compare CSV: :meth:`read` what it holds (checked), :meth:`append` a run as soon as it ends."""

    def __init__(self, path: Path):
        self.path = Path(path)

    def read(self) -> tuple[dict[tuple[str, int], RunRow], str | None]:
        """The rows by (label, seed) (the first of a repeated pair) and a note when an incomplete last line
        (a run cut off while it was written) was dropped; an empty or missing file holds none."""
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
        if not lines or tuple(lines[0]) != HEADER:
            found = ",".join(lines[0]) if lines else "nothing"
            raise RunInputError(f"--csv {self.path}: not a dtpf compare CSV (its header is {found[:80]!r}); "
                                f"give another file")
        rows: dict[tuple[str, int], RunRow] = {}
        for number, cells in enumerate(lines[1:], 2):
            if not cells:
                continue
            try:
                row = RunRow(cells[0], cells[1], cells[2], int(cells[3]), cells[4], float(cells[5]), float(cells[6]),
                             int(cells[7]), float(cells[8]))
                if len(cells) != len(HEADER):
                    raise ValueError
            except (ValueError, IndexError):
                raise RunInputError(f"--csv {self.path}: line {number} is not a compare row") from None
            rows.setdefault((row.variant, row.seed), row)
        return rows, note

    def check(self, rows: dict[tuple[str, int], RunRow], settings: dict[str, str]) -> None:
        """RunInputError when a label of ``settings`` (label: its settings now) has rows run with others."""
        for (label, seed), row in rows.items():
            now = settings.get(label)
            if now is not None and row.settings != now:
                raise RunInputError(f"--csv {self.path}: variant {label!r} was run there with "
                                    f"{_difference(row.settings, now)}; give another --csv or another label")

    def start(self) -> None:
        """Write the header to a new or empty file."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "w", newline="") as handle:
                csv.writer(handle, lineterminator="\n").writerow(HEADER)

    def append(self, row: RunRow) -> None:
        """Add one run's row, flushed at once (an interrupted compare keeps every finished run)."""
        with open(self.path, "a", newline="") as handle:
            csv.writer(handle, lineterminator="\n").writerow(row.cells())


def _difference(before: str, now: str) -> str:
    """What differs between two settings texts, ``field a (now b)``."""
    try:
        old, new = json.loads(before), json.loads(now)
    except ValueError:
        return f"other settings ({before})"
    changed = [f"{name} {old.get(name, 'default')} (now {new.get(name, 'default')})"
               for name in dict.fromkeys([*old, *new]) if old.get(name) != new.get(name)]
    return ", ".join(changed) or f"other settings ({before})"
