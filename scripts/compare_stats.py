"""The statistics of ``dtpf compare``: means, paired differences and relative changes with 95% intervals.

Plain functions of arrays, no runs and no files::

    from dtpf.scripts.compare_stats import compare
    row = compare(values, baseline, higher_is_better=False)   # values[i], baseline[i]: the same seed
    row.difference, row.difference_half, row.verdict           # e.g. 2.99, 1.67, "worse"

Every interval is the normal one, mean +- z s / sqrt(S) with z = 1.96 and s the sample standard
deviation (ddof 1) over the S seeds; a difference is paired by seed. The relative change is the ratio
of the means minus one, in percent of the baseline's mean, with the delta method's interval: the
half-width is z sd(a - R b) / (sqrt(S) |mean b|), R = mean a / mean b (the method of the paper's
reports). With fewer than two seeds a half-width is NaN and no verdict is given. Every function takes
``z=`` for another quantile (the research reports use the exact 1.959963984540054).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Z95", "Comparison", "mean_interval", "paired_difference", "relative_change", "verdict", "compare",
           "format_interval", "format_change", "BETTER", "WORSE", "SAME", "BASELINE"]

#: The 97.5% quantile of the standard normal distribution, as every table of this project rounds it.
Z95 = 1.96

BETTER, WORSE, SAME, BASELINE = "better", "worse", "not significantly different", "baseline"


def mean_interval(values, z: float = Z95) -> tuple[float, float]:
    """The mean of ``values`` and the half-width of its 95% normal interval (NaN for fewer than two)."""
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return math.nan, math.nan
    if values.size < 2:
        return float(values.mean()), math.nan
    return float(values.mean()), z * float(values.std(ddof=1)) / math.sqrt(values.size)


def paired_difference(values, baseline, z: float = Z95) -> tuple[float, float]:
    """The mean of ``values - baseline`` (paired element by element) and its 95% half-width."""
    values, baseline = _paired(values, baseline)
    return mean_interval(values - baseline, z)


def relative_change(values, baseline, z: float = Z95) -> tuple[float, float]:
    """The change of mean(values) against mean(baseline) in percent of |mean(baseline)|, paired by element,
    with its 95% delta-method half-width (NaN where the baseline's mean is 0, or for fewer than two)."""
    values, baseline = _paired(values, baseline)
    base = float(baseline.mean()) if baseline.size else math.nan
    if not base or not math.isfinite(base):
        return math.nan, math.nan
    ratio = float(values.mean()) / base
    change = 100.0 * (float(values.mean()) - base) / abs(base)
    if values.size < 2:
        return change, math.nan
    spread = float(np.std(values - ratio * baseline, ddof=1)) / (math.sqrt(values.size) * abs(base))
    return change, 100.0 * z * spread


def verdict(difference: float, half: float, higher_is_better: bool) -> str:
    """"better" or "worse" when the difference's interval excludes 0 (which way is better: ``higher_is_better``),
    else "not significantly different" (also when the interval is unknown)."""
    if not (math.isfinite(difference) and math.isfinite(half)) or abs(difference) <= half:
        return SAME
    return BETTER if (difference > 0) == higher_is_better else WORSE


@dataclass(frozen=True)
class Comparison:
    """One variant against the baseline over the same seeds: its mean, the paired difference, the change."""

    runs: int
    mean: float
    mean_half: float
    difference: float
    difference_half: float
    change: float
    change_half: float
    verdict: str


def compare(values, baseline, higher_is_better: bool, is_baseline: bool = False, z: float = Z95) -> Comparison:
    """``values`` against ``baseline`` (the same seeds, in the same order); ``is_baseline``: the baseline itself
    (its difference is 0 by construction, its verdict ``"baseline"``)."""
    values, baseline = _paired(values, baseline)
    mean, mean_half = mean_interval(values, z)
    if is_baseline:
        return Comparison(values.size, mean, mean_half, 0.0, 0.0, 0.0, 0.0, BASELINE)
    difference, difference_half = paired_difference(values, baseline, z)
    change, change_half = relative_change(values, baseline, z)
    return Comparison(values.size, mean, mean_half, difference, difference_half, change, change_half,
                      verdict(difference, difference_half, higher_is_better))


def _decimals(half: float) -> int:
    """Decimals that show three significant digits of a half-width (at least 0)."""
    if not math.isfinite(half) or half <= 0:
        return 4
    return max(0, 2 - math.floor(math.log10(half)))


def format_interval(value: float, half: float) -> str:
    """``value ± half`` with three significant digits of the half-width and the value to the same decimals
    (``25.08 ± 1.53``, ``4.369 ± 0.152``); ``0 ± 0`` when every value is the same; the value alone (4 significant
    digits) when the half is unknown."""
    if not math.isfinite(value):
        return "-"
    if not math.isfinite(half):
        return f"{value:.4g}"
    if half == 0:  # every value the same (a variant identical to the baseline)
        return f"{value:.4g} ± 0"
    digits = _decimals(half)
    return f"{value:.{digits}f} ± {half:.{digits}f}"


def format_change(change: float, half: float) -> str:
    """A relative change in percent with its interval, signed: ``+11.9% ± 6.6%``."""
    if not math.isfinite(change):
        return "-"
    if not math.isfinite(half):
        return f"{change:+.3g}%"
    if half == 0:
        return f"{change:+.3g}% ± 0%"
    digits = max(0, _decimals(half) - 1)  # two significant digits of a percentage's half-width
    return f"{change:+.{digits}f}% ± {half:.{digits}f}%"


def _paired(values, baseline) -> tuple[np.ndarray, np.ndarray]:
    values, baseline = np.asarray(values, dtype=np.float64), np.asarray(baseline, dtype=np.float64)
    if values.shape != baseline.shape:
        raise ValueError(f"paired values need the same seeds: {values.size} values against {baseline.size}")
    return values, baseline
