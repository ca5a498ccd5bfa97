"""What the paper's reports share: the methods compared, their colours, statistics, CSV and figures.

Used by :mod:`dtpf.scripts.paper.experiments` (section 4) and :mod:`dtpf.scripts.paper.tracking`
(section 5), so that neither imports the other.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

TRADITIONAL = ("stratified", "multinomial", "systematic", "residual")

DT_METHODS = ("DT inherit", "DT likelihood")

#: The paper's fixed degree factor (section 4.1); pinned, whatever the library's default policy becomes.
PAPER_PS = 0.81

METHODS = TRADITIONAL + DT_METHODS

#: RunConfig fields of each method.
METHOD_CONFIG = {
    **{name: dict(preprocess=False, resampler=name) for name in TRADITIONAL},
    "DT inherit": dict(preprocess=True, resampler="systematic", weight_rule="inherit", policy="fixed", ps=PAPER_PS),
    "DT likelihood": dict(preprocess=True, resampler="systematic", weight_rule="likelihood", policy="fixed",
                          ps=PAPER_PS),
}

COLOURS = {"stratified": "tab:blue", "multinomial": "tab:orange", "systematic": "tab:green",
           "residual": "tab:purple", "DT inherit": "tab:red", "DT likelihood": "black", "DT rules only": "tab:pink"}

STYLES = {"DT likelihood": "--", "DT rules only": ":"}

Z95 = 1.959963984540054

#: Figures: small PNGs (the report links them).
DPI = 80

def report_of(out: Path) -> Path:
    """The Markdown report of the data folder ``out``: ``docs/results/<name>.md`` for a folder of ``docs/``
    (the reports are results, the data beside the guides), else ``out`` + ``.md`` beside the folder."""
    out = Path(out)
    if out.parent.name == "docs":
        return out.parent / "results" / f"{out.name}.md"
    return out.with_name(out.name + ".md")


def relative_to_report(path: Path, out: Path) -> str:
    """``path`` as a link from the report of ``out`` (forward slashes)."""
    import os

    return os.path.relpath(path, report_of(out).parent).replace(os.sep, "/")


def mean_ci(values) -> tuple[float, float]:
    """Mean and the half-width of its 95% normal interval (NaN half-width for one value)."""
    values = np.asarray(values, dtype=float)
    if values.size < 2:
        return float(values.mean()), float("nan")
    return float(values.mean()), Z95 * float(values.std(ddof=1)) / math.sqrt(values.size)

def significance(value: float, half: float) -> int:
    """-1 if the interval lies below 0, +1 above, 0 if it holds 0 (or is unknown)."""
    if not math.isfinite(half):
        return 0
    return -1 if value + half < 0 else (1 if value - half > 0 else 0)

def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)

def write_csv(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _fmt(v) for k, v in row.items()})

def _figure(rows: int, cols: int, size: tuple[float, float]):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    figure, axes = plt.subplots(rows, cols, figsize=size, squeeze=False)
    return plt, figure, axes

def _save(plt, figure, path: Path) -> None:
    """Save as a small PNG: rendered at :data:`DPI`, then reduced to a 256-colour palette."""
    import io
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, dpi=DPI, format="png")
    plt.close(figure)
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        path.write_bytes(buffer.getvalue())
        return
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(256).save(path, optimize=True)

def pm(value: float, half: float, digits: int = 3) -> str:
    if not math.isfinite(half):
        return f"{value:.{digits}g}"
    return f"{value:.{digits}g} ± {half:.2g}"
