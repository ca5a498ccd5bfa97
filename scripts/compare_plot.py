"""The figure of ``dtpf compare --plot``: each variant's paired difference against the baseline with its
95% interval, one row per variant, coloured by its verdict (matplotlib, Agg, a PNG)."""
from __future__ import annotations

from pathlib import Path

from dtpf.scripts.compare_stats import BETTER, WORSE, Comparison

__all__ = ["plot_differences"]

_COLOURS = {BETTER: "tab:green", WORSE: "tab:red"}


def plot_differences(path: Path, rows: list[tuple[str, Comparison]], baseline: str, metric: str,
                     higher_is_better: bool, seeds: int) -> None:
    """Write ``path``: the difference (variant - ``baseline``) of each (label, comparison) in ``rows`` but the
    baseline's, with its interval; ``metric`` names the figure compared (the axis says which way is better)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [(label, row) for label, row in rows if label != baseline]
    figure, axes = plt.subplots(figsize=(7.5, 1.2 + 0.45 * max(1, len(shown))))
    for y, (label, row) in enumerate(reversed(shown)):
        half = row.difference_half if row.difference_half == row.difference_half else 0.0
        axes.errorbar(row.difference, y, xerr=half, fmt="o", capsize=4,
                      color=_COLOURS.get(row.verdict, "tab:grey"))
    axes.axvline(0.0, color="black", linewidth=0.8)
    axes.set_yticks(range(len(shown)), [label for label, _ in reversed(shown)])
    axes.set_ylim(-0.7, len(shown) - 0.3)
    better = "right" if higher_is_better else "left"
    axes.set_xlabel(f"{metric}: variant - {baseline} (better to the {better}); 95% interval over {seeds} "
                    f"paired seeds")
    figure.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)
