"""The metrics of ``dtpf compare``: the one figure a run is judged by, and which way is better.

With the truth known (a simulation, or an observation file with truth columns), over the state
components chosen (all those the truth covers by default), e_k being the estimate minus the truth
at step k over those components:

=====================  ========================================================  ==============
``mse``                mean over steps and components of e^2                     lower is better
``rmse``               the square root of the mse                                lower is better
``squared-distance``   mean over steps of |e_k|^2 (summed over the components)   lower is better
``distance``           mean over steps of |e_k| (the Euclidean error)            lower is better
``log-predictive``     mean over steps of log p(z_k | z_1:k-1) (no truth needed) higher is better
=====================  ========================================================  ==============

``squared-distance`` and ``distance`` over a tracker's position (``--components 0,1``) are the
squared and plain distance of the estimated to the true position; ``mse`` over the same two is half
the squared distance. ::

    metric = parse_metric("squared-distance", "0,1")
    metric.of(result)          # a RunResult of dtpf.scripts.inprocess.run
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dtpf.messages.config import RunInputError

__all__ = ["MSE", "RMSE", "SQUARED_DISTANCE", "DISTANCE", "LOG_PREDICTIVE", "METRICS", "Metric", "parse_metric",
           "parse_components", "figures_of"]

MSE, RMSE, SQUARED_DISTANCE, DISTANCE, LOG_PREDICTIVE = "mse", "rmse", "squared-distance", "distance", "log-predictive"
#: Each metric: (its name in the table, what it is, whether higher is better).
METRICS = {
    MSE: ("MSE", "the mean squared error of the posterior mean against the truth", False),
    RMSE: ("RMSE", "the root mean squared error of the posterior mean against the truth", False),
    SQUARED_DISTANCE: ("squared distance", "the mean over steps of the squared distance of the posterior mean "
                                           "to the truth", False),
    DISTANCE: ("distance", "the mean over steps of the distance of the posterior mean to the truth", False),
    LOG_PREDICTIVE: ("log predictive", "the mean log predictive likelihood per step, log p(z_k | z_1:k-1)", True),
}


@dataclass(frozen=True)
class Metric:
    """A metric's name and the state components it is over (None: all that the truth covers)."""

    name: str
    components: tuple[int, ...] | None = None

    @property
    def needs_truth(self) -> bool:
        return self.name != LOG_PREDICTIVE

    @property
    def higher_is_better(self) -> bool:
        return METRICS[self.name][2]

    @property
    def key(self) -> str:
        """As the CSV keeps it: ``mse``, ``squared-distance[0,1]``, ``log_predictive`` (the older files' name)."""
        if self.name == LOG_PREDICTIVE:
            return "log_predictive"
        return self.name + ("" if self.components is None else f"[{','.join(map(str, self.components))}]")

    @property
    def title(self) -> str:
        """The table's column: ``MSE of components 0, 1 (lower is better)``."""
        return f"{METRICS[self.name][0]}{self._over()} ({'higher' if self.higher_is_better else 'lower'} is better)"

    @property
    def meaning(self) -> str:
        """The line above the table's words for it."""
        extra = " (no truth known)" if self.name == LOG_PREDICTIVE else ""
        return f"{METRICS[self.name][1]}{self._over()}{extra}, {'higher' if self.higher_is_better else 'lower'} is better"

    def _over(self) -> str:
        if self.components is None:
            return ""
        return f" of component{'s' if len(self.components) > 1 else ''} {', '.join(map(str, self.components))}"

    def check(self, state_dim: int, truth_components: tuple[int, ...] | None) -> None:
        """RunInputError when the run cannot give this metric: no truth, or a component that is not in the state
        (``state_dim``) or that the truth does not cover (``truth_components``; None: no truth)."""
        if not self.needs_truth:
            return
        if truth_components is None:
            raise RunInputError(f"--metric {self.name} needs the truth, which this run does not have (a file "
                                f"without truth columns): use --metric log-predictive")
        for component in self.components or ():
            if component >= state_dim:
                raise RunInputError(f"--components: the state has components 0 .. {state_dim - 1}, got {component}")
            if component not in truth_components:
                raise RunInputError(f"--components: the truth covers components "
                                    f"{', '.join(map(str, truth_components))}, not {component}")

    def of(self, result) -> float:
        """The metric of a :class:`~dtpf.scripts.inprocess.RunResult`."""
        if self.name == LOG_PREDICTIVE:
            return float(np.mean(result.log_predictive))
        errors = result.errors
        if self.components is not None:
            errors = errors[:, [result.components.index(c) for c in self.components]]
        squared = errors ** 2
        if self.name == MSE:
            return float(np.mean(squared))
        if self.name == RMSE:
            return math.sqrt(float(np.mean(squared)))
        distance2 = np.sum(squared, axis=1)
        return float(np.mean(distance2)) if self.name == SQUARED_DISTANCE else float(np.mean(np.sqrt(distance2)))


def parse_components(text: str | None) -> tuple[int, ...] | None:
    """``0,1`` as (0, 1); None for None; RunInputError for anything but distinct integers >= 0."""
    if text is None:
        return None
    try:
        components = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise RunInputError(f"--components: state components are integers from 0, comma-separated (0,1), "
                            f"got {text!r}") from None
    if min(components) < 0 or len(set(components)) != len(components):
        raise RunInputError(f"--components: distinct components from 0, got {text!r}")
    return components


def parse_metric(name: str | None, components: str | None, has_truth: bool) -> Metric:
    """The metric ``name`` (None: ``mse`` when the run has the truth, else ``log-predictive``) over
    ``components`` (``0,1``; None: every component the truth covers)."""
    if name is None:
        name = MSE if has_truth or components is not None else LOG_PREDICTIVE
    if name not in METRICS:
        raise RunInputError(f"--metric: one of {', '.join(METRICS)}, got {name!r}")
    chosen = parse_components(components)
    if chosen is not None and name == LOG_PREDICTIVE:
        raise RunInputError("--components: the log predictive is of the whole observation, not of state components")
    return Metric(name, chosen)


def figures_of(result) -> dict[str, float]:
    """What every row keeps besides its metric: the mean ESS, the mean distinct ancestors of a resampling / N
    (NaN where no step resampled), the share of steps whose set the DT preprocessing changed, and the mean log
    predictive per step."""
    n = result.config.particles
    distinct = [1 + int(np.count_nonzero(s.ancestors[1:] != s.ancestors[:-1])) for s in result.steps if s.resampled]
    processed = [s.report is not None and s.report.n_processed > 0 for s in result.steps]
    return dict(mean_ess=result.mean_ess, distinct=float(np.mean(distinct)) / n if distinct else math.nan,
                preprocessed=float(np.mean(processed)) if processed else math.nan,
                log_predictive=float(np.mean(result.log_predictive)))
