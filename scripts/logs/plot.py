"""``dtpf plot``: one PNG of a recorded run, after the paper's Figs. 6-8 and 10.

::

    dtpf plot runs/demo.mcap -o demo.png
    dtpf plot runs/demo.mcap --twin ungm-1 --steps-at 10 50 90 --dpi 150
    dtpf plot runs/cv.mcap --component 1       # the state's second component, x[1]

The figure has, top to bottom:

1. the true state x_k, the estimate with its 95% interval and the observation
   z_k (Figs. 6 and 7); for the growth model (z = x^2/20 + v) the observation
   is drawn in state units as +-sqrt(20 z_k), since z cannot tell the sign;
2. the error of the estimate against the truth, inside the band of the 95%
   half-width 1.96 sd, with the observation's own error where it means
   something (Fig. 8);
3. ESS/N and PS per step, degraded steps (no preprocessed set in time) marked;
4. the particles (value against weight) before preprocessing (entity/particles)
   and after it (information/preprocessed) at a few steps, the processed
   particles in red (Fig. 10).

Reading and drawing are separate: :func:`read_log` turns an MCAP file into a
:class:`RunLog`, :func:`plot_run` turns a RunLog into a matplotlib Figure, so
the figure can be built from data made in memory::

    from dtpf.scripts.logs.plot import read_log, plot_run, save
    run = read_log("runs/demo.mcap", steps_at=[10, 50])
    figure = plot_run(run, steps_at=[10, 50])
    save(figure, "demo.png", dpi=100)
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from dtpf.messages.errors import DtpfError

__all__ = ["RunLog", "PlotError", "read_log", "default_steps", "plot_run", "save", "register", "cmd_plot",
           "main", "FIGSIZE"]

#: Figure size in inches; the PNG is FIGSIZE * dpi pixels.
FIGSIZE = (12.0, 15.0)
DEFAULT_DPI = 100
#: How many steps the particle panels show by default.
DEFAULT_PARTICLE_STEPS = 3
#: At most this many particle panels (columns).
MAX_PARTICLE_STEPS = 6

COLOURS = {
    "truth": "black",
    "estimate": "tab:blue",
    "band": "#9ecae1",
    "observation": "0.45",
    "outside": "tab:red",
    "ess": "tab:green",
    "ps": "tab:purple",
    "degraded": "tab:red",
    "kept": "tab:blue",
    "small": "0.6",
    "processed": "tab:red",
}


class PlotError(DtpfError, ValueError):
    """A log or an option the plot cannot use; ``code`` is the exit code (1: the file, 2: an option)."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


@dataclass
class RunLog:
    """What the plot needs of one twin's run, as read from a log (or built in memory).

    ``estimates``, ``ps_commands`` and ``weight_states`` are sorted by step.
    ``propagated`` and ``preprocessed`` hold particle sets by step, only for
    the steps that were asked for (they are large); ``propagated_count`` and
    ``preprocessed_count`` say how many sets of each kind the log holds.
    ``set_steps`` are the steps that have a particle set in the log.
    ``config`` is the run configuration the services reported (the fields of
    :class:`dtpf.messages.config.RunConfig`), empty when the log does not say.
    """

    twin: str
    estimates: list
    run_id: str | None = None
    config: dict = field(default_factory=dict)
    ps_commands: list = field(default_factory=list)
    weight_states: list = field(default_factory=list)
    propagated: dict = field(default_factory=dict)
    preprocessed: dict = field(default_factory=dict)
    propagated_count: int = 0
    preprocessed_count: int = 0
    set_steps: list = field(default_factory=list)
    skipped: int = 0
    path: str | None = None

    @property
    def steps(self) -> np.ndarray:
        return np.array([e.step for e in self.estimates], dtype=int)

    @property
    def n_particles(self) -> int | None:
        """N: from the configuration, else a particle set, else ESS / (ESS/N)."""
        if self.config.get("particles"):
            return int(self.config["particles"])
        for sets in (self.propagated, self.preprocessed):
            for particle_set in sets.values():
                return int(particle_set.weights.shape[0])
        for e in self.estimates:
            if e.ess_ratio > 0:
                return int(round(e.ess / e.ess_ratio))
        return None

    @property
    def rmse(self) -> float:
        errors = [np.subtract(e.mean, e.truth) for e in self.estimates if e.truth is not None]
        return float(np.sqrt(np.mean(np.square(errors)))) if errors else float("nan")


# --- reading ---------------------------------------------------------------

_SMALL_TOPICS = ("entity/estimate", "system/ps", "information/weight_state")
_PARTICLE_TOPICS = {"entity/particles": "propagated", "information/preprocessed": "preprocessed"}


#: The 8 bytes every MCAP file starts with.
MCAP_MAGIC = b"\x89MCAP0\r\n"


def _open_reader(stream, path):
    from mcap.reader import make_reader

    head = stream.read(len(MCAP_MAGIC))
    if not head:
        raise PlotError(f"{path} is empty, not an MCAP log")
    if head != MCAP_MAGIC:
        raise PlotError(f"{path} is not an MCAP file (it starts with {head!r}, an MCAP file with {MCAP_MAGIC!r})")
    stream.seek(0)
    reader = make_reader(stream)
    return reader, reader.get_summary()


def _topics(reader, summary) -> list[str]:
    if summary is not None:
        return sorted({channel.topic for channel in summary.channels.values()})
    return sorted({channel.topic for _, channel, _ in reader.iter_messages()})


def _twins(topics: Iterable[str]) -> dict[str, set[str]]:
    """{twin: {'layer/topic', ...}} for every dtpf key expression among ``topics``."""
    twins: dict[str, set[str]] = {}
    for topic in topics:
        chunks = topic.split("/")
        if len(chunks) == 4 and chunks[0] == "dtpf":
            twins.setdefault(chunks[1], set()).add(f"{chunks[2]}/{chunks[3]}")
    return twins


def _messages(reader, topics: list[str], on_error):
    """Decoded (topic, message) pairs of ``topics``; undecodable messages go to ``on_error``."""
    from dtpf.messages.codec import MessageError, decode_for_key

    for _, channel, message in reader.iter_messages(topics=topics):
        try:
            yield channel.topic, decode_for_key(channel.topic, message.data)
        except MessageError as error:
            on_error(channel.topic, error)


def read_log(path, *, twin: str | None = None, steps_at: Sequence[int] | None = None) -> RunLog:
    """Read the messages of one twin from a complete MCAP log.

    Parameters
    ----------
    path : str or Path
        The MCAP file ``dtpf launch`` (or the recorder) wrote.
    twin : str, optional
        The twin to read; default the only twin in the log.
    steps_at : sequence of int, optional
        Steps whose particle sets are kept (default: :func:`default_steps`).

    Raises
    ------
    PlotError
        Missing file, not an MCAP file, no or unknown twin, no estimates,
        or a step outside the run; the message says which.
    """
    path = Path(path)
    if not path.exists():
        raise PlotError(f"no such file: {path}")
    if path.is_dir():
        raise PlotError(f"{path} is a directory, not an MCAP log")
    skipped = {"count": 0, "first": None}

    def on_error(topic, error):
        skipped["count"] += 1
        skipped["first"] = skipped["first"] or f"{topic}: {error}"

    try:
        with open(path, "rb") as stream:
            reader, summary = _open_reader(stream, path)
            twins = _twins(_topics(reader, summary))
            twin = _choose_twin(twins, twin, path)
            keys = {name: f"dtpf/{twin}/{name}" for name in (*_SMALL_TOPICS, *_PARTICLE_TOPICS)}
            status_keys = [f"dtpf/{twin}/{t}" for t in sorted(twins[twin]) if t.endswith("/status")]
            run = RunLog(twin=twin, estimates=[], path=str(path))
            by_step: dict[int, object] = {}
            for topic, message in _messages(reader, [keys[t] for t in _SMALL_TOPICS] + status_keys, on_error):
                name = topic.split("/", 2)[2]
                if name == "entity/estimate":
                    by_step[message.step] = message  # a repeated step: the last one counts
                    run.run_id = run.run_id or message.run_id
                elif name == "system/ps":
                    run.ps_commands.append(message)
                elif name == "information/weight_state":
                    run.weight_states.append(message)
                elif not run.config and getattr(message, "config_json", None):
                    try:
                        run.config = json.loads(message.config_json)
                    except ValueError:
                        pass
            run.estimates = [by_step[k] for k in sorted(by_step)]
            run.ps_commands.sort(key=lambda m: m.step)
            run.weight_states.sort(key=lambda m: m.step)
            if not run.estimates:
                found = ", ".join(sorted(twins[twin])) or "nothing"
                raise PlotError(f"{path} holds no estimates (dtpf/{twin}/entity/estimate) for twin {twin!r}; "
                                f"it has: {found}")
            particle_keys = [keys[t] for t in _PARTICLE_TOPICS]
            if steps_at is not None:
                _read_sets(reader, particle_keys, run, set(_check_steps(run, steps_at)), on_error)
            else:
                # First guess: the resampled steps (the entity sends its set only when it resamples).
                resampled = [e.step for e in run.estimates if e.resampled]
                wanted = set(_evenly_spaced(resampled or run.steps))
                present = _read_sets(reader, particle_keys, run, wanted, on_error)
                better = set(_evenly_spaced(sorted(present)))
                if present and not wanted <= present and better != wanted:
                    _read_sets(reader, particle_keys, run, better, lambda *_: None)
    except PlotError:
        raise
    except OSError as error:
        raise PlotError(f"cannot read {path}: {error}") from None
    except Exception as error:  # mcap, struct, lz4, zstd: whatever a damaged file makes them raise
        from dtpf.recording.logfile import LogError
        from dtpf.recording.logfile import read_log as read_damaged

        try:
            problem = read_damaged(path).problem
        except LogError as second:
            problem = str(second)
        raise PlotError(f"cannot plot {path}: {problem or f'{type(error).__name__}: {error}'}; "
                        f"`dtpf recover {path} -o fixed.mcap` writes what it holds as a complete log to plot"
                        ) from None
    run.skipped = skipped["count"]
    if skipped["count"]:
        print(f"dtpf plot: warning: skipped {skipped['count']} message(s) that did not decode, "
              f"first: {skipped['first']}", file=sys.stderr)
    return run


def _read_sets(reader, topics, run: RunLog, wanted: set[int], on_error) -> set[int]:
    """Keep the particle sets of the ``wanted`` steps in ``run``; returns every step that has a set."""
    run.propagated, run.preprocessed = {}, {}
    run.propagated_count = run.preprocessed_count = 0
    present = set()
    for topic, message in _messages(reader, topics, on_error):
        kind = _PARTICLE_TOPICS[topic.split("/", 2)[2]]
        setattr(run, f"{kind}_count", getattr(run, f"{kind}_count") + 1)
        present.add(message.step)
        if message.step in wanted:
            getattr(run, kind)[message.step] = message
    run.set_steps = sorted(present)
    return present


def _choose_twin(twins: dict[str, set[str]], twin: str | None, path) -> str:
    if not twins:
        raise PlotError(f"{path} holds no dtpf messages (no topic dtpf/<twin>/<layer>/<topic>)")
    if twin is None:
        if len(twins) > 1:
            raise PlotError(f"{path} holds {len(twins)} twins: {', '.join(sorted(twins))}; choose one with --twin",
                            code=2)
        return next(iter(twins))
    if twin not in twins:
        raise PlotError(f"twin {twin!r} is not in {path}; it holds: {', '.join(sorted(twins))}", code=2)
    return twin


def default_steps(run: RunLog, count: int = DEFAULT_PARTICLE_STEPS) -> list[int]:
    """``count`` evenly spaced interior steps among those with particle sets in ``run``, else among all steps."""
    with_sets = sorted(set(run.propagated) | set(run.preprocessed))
    return _evenly_spaced(with_sets or run.steps.tolist(), count)


def _evenly_spaced(steps, count: int = DEFAULT_PARTICLE_STEPS) -> list[int]:
    """``count`` of ``steps``, evenly spaced over their range, without the ends when there are enough."""
    steps = np.unique(np.asarray(steps, dtype=int))
    if steps.size <= count:
        return steps.tolist()
    targets = np.linspace(steps[0], steps[-1], count + 2)[1:-1]
    chosen = {int(steps[np.argmin(np.abs(steps - target))]) for target in targets}
    return sorted(chosen)


def _check_steps(run: RunLog, steps_at: Sequence[int]) -> list[int]:
    steps = sorted({int(k) for k in steps_at})
    if not steps:
        raise PlotError("--steps-at needs at least one step", code=2)
    if len(steps) > MAX_PARTICLE_STEPS:
        raise PlotError(f"--steps-at takes at most {MAX_PARTICLE_STEPS} steps, got {len(steps)}", code=2)
    known = set(run.steps.tolist())
    missing = [k for k in steps if k not in known]
    if missing:
        raise PlotError(f"--steps-at: no estimate at step {', '.join(map(str, missing))}; the log has steps "
                        f"{min(known)} .. {max(known)}", code=2)
    return steps


# --- drawing ---------------------------------------------------------------

def _series(estimates, name, index=0) -> np.ndarray:
    return np.array([np.nan if getattr(e, name) is None else getattr(e, name)[index] for e in estimates])


def _growth_model(config: dict):
    """The GrowthModel of the run's scenario (z = x^2/20 + v), or None if the log does not say."""
    scenario = config.get("scenario")
    if not scenario or config.get("model"):  # a user model of its own, whatever the scenario field says
        return None
    from dtpf.entity import models

    try:
        model = models.get(scenario)
    except ValueError:
        return None
    return model if isinstance(model, models.GrowthModel) else None


def _describe(run: RunLog) -> tuple[str, str]:
    """The two title lines: what ran, and how it went."""
    c = run.config
    e = run.estimates
    n = run.n_particles
    model = _growth_model(c)
    if model is not None:
        scenario = f"{model.name}: growth model with {model.growth:g} x/(1+x²), z = x²/20 + v"
    elif c.get("model"):
        scenario = f"model {c['model']}"
    else:
        scenario = c.get("scenario", "scenario not recorded")
    if any(x.truth is not None for x in e):
        judged = f"RMSE {run.rmse:.3f}"
    else:
        lp = [x.log_predictive for x in e if x.log_predictive is not None]
        judged = f"no truth; log predictive {np.mean(lp):.3f} per step" if lp else "no truth"
    preprocess = c.get("preprocess", run.preprocessed_count > 0 or any(x.ps is not None for x in e))
    ps_values = [x.ps for x in e if x.ps is not None]
    if preprocess:
        ps_text = (f"PS {min(ps_values):g}" if ps_values and min(ps_values) == max(ps_values)
                   else f"PS {min(ps_values):g}..{max(ps_values):g}" if ps_values else "PS -")
        if c.get("policy"):
            ps_text += f" ({c['policy']} policy)"
        method = f"DT preprocessing (Eq. 28-30, {ps_text}) + {c.get('resampler', 'traditional')} resampling"
    else:
        method = f"no preprocessing: plain {c.get('resampler', 'traditional')} resampling"
    line1 = (f"twin {run.twin}" + (f", run id {run.run_id!r}" if run.run_id else "")
             + f"  |  {scenario}  |  N = {n if n is not None else '?'}, {len(e)} steps"
             + f"  |  {judged}")
    degraded = sum(x.degraded for x in e)
    extras = [method]
    if "seed" in c:
        extras.append(f"seed {c['seed']}")
    extras.append(f"mean ESS/N {np.mean([x.ess_ratio for x in e]):.2f}")
    extras.append(f"resampled at {sum(x.resampled for x in e)} of {len(e)} steps")
    extras.append(f"{degraded} degraded step{'s' if degraded != 1 else ''}")
    steps = run.steps
    gaps = int(steps.max() - steps.min() + 1 - steps.size)
    if gaps:
        extras.append(f"{gaps} step(s) missing")
    return line1, "; ".join(extras)


def _mark_degraded(ax, steps, degraded):
    for k in steps[degraded]:
        ax.axvspan(k - 0.5, k + 0.5, color=COLOURS["degraded"], alpha=0.12, lw=0)


def _mark_particle_steps(ax, steps_at):
    for k in steps_at:
        ax.axvline(k, color="0.5", lw=0.8, ls=":", zorder=0)


def _plot_state(ax, run: RunLog, steps, model, steps_at, component: int = 0):
    e = run.estimates
    mean, lower, upper = (_series(e, name, component) for name in ("mean", "lower", "upper"))
    truth, z = _series(e, "truth", component), _observed(e, component)
    ax.fill_between(steps, lower, upper, color=COLOURS["band"], alpha=0.6, lw=0, label="95% interval")
    if np.isfinite(truth).any():
        ax.plot(steps, truth, color=COLOURS["truth"], lw=1.4, label="state $x_k$ (truth)")
    ax.plot(steps, mean, color=COLOURS["estimate"], lw=1.4, marker="o", ms=2.5, label=r"estimate $\hat{x}_k$")
    if np.isfinite(z).any():
        if model is not None:
            root = np.sqrt(20.0 * np.clip(z, 0.0, None))
            ax.plot(np.r_[steps, steps], np.r_[root, -root], ls="none", marker="_", ms=6, mew=1.2,
                    color=COLOURS["observation"], label=r"observation as $\pm\sqrt{20\,z_k}$")
        else:
            ax.plot(steps, z, ls="none", marker=".", ms=4, color=COLOURS["observation"],
                    label="observation $z_k$ (its own units)")
    _mark_degraded(ax, steps, np.array([x.degraded for x in e]))
    _mark_particle_steps(ax, steps_at)
    dim = len(e[0].mean)
    shown = "" if dim == 1 else f" (component x[{component}] of d = {dim})"
    inside = _inside(e, component)
    title = "State, observation and estimate with 95% interval (Figs. 6, 7)" + shown
    if inside is not None:
        title += f": truth inside the interval at {inside[0]} of {inside[1]} steps"
    ax.set_title(title, loc="left", fontsize=10)
    if steps_at:
        ax.plot([], [], color="0.5", lw=0.8, ls=":", label="steps of the particle panels")
    ax.set_ylabel("state x")
    ax.set_xlabel("time step k")
    _headroom(ax, 0.12)
    ax.legend(loc="upper left", fontsize=8, ncol=5, framealpha=0.9)
    ax.margins(x=0.01)


def _headroom(ax, fraction):
    """Raise the top of the y range by ``fraction`` of it, so the legend sits above the data."""
    low, high = ax.get_ylim()
    ax.set_ylim(low, high + fraction * (high - low))


def _observed(estimates, component: int) -> np.ndarray:
    """The observation's value ``component`` per step, where the observation has one (NaN elsewhere)."""
    return np.array([e.observation[component] if e.observation is not None and len(e.observation) > component
                     else np.nan for e in estimates])


def _inside(estimates, component: int = 0):
    rows = [(e.lower[component], e.truth[component], e.upper[component]) for e in estimates if e.truth is not None]
    if not rows:
        return None
    return sum(low <= x <= high for low, x, high in rows), len(rows)


def _plot_error(ax, run: RunLog, steps, model, steps_at, component: int = 0):
    """The error of the state's ``component`` against the truth (Fig. 8); without truth, the log
    predictive likelihood of each observation, what a filter on real data is judged by."""
    e = run.estimates
    mean, truth, z = _series(e, "mean", component), _series(e, "truth", component), _observed(e, component)
    lp = _series_optional(e, "log_predictive")
    ylabel = "error (state units)"
    predictive = not np.isfinite(truth).any() and np.isfinite(lp).any()
    if predictive:
        ax.plot(steps, lp, color=COLOURS["estimate"], lw=1.3, marker="o", ms=2.5,
                label=r"$\log p(z_k \mid z_{1:k-1})$")
        ax.axhline(float(np.nanmean(lp)), color="0.3", lw=0.8, ls="--", label=f"mean {np.nanmean(lp):.3f}")
        ax.set_title("No truth in this log: the log predictive likelihood of each observation "
                     "(higher is better)", loc="left", fontsize=10)
        ylabel = "log predictive"
    else:
        half = 1.96 * np.sqrt(_series(e, "var", component))
        ax.fill_between(steps, -half, half, color=COLOURS["band"], alpha=0.6, lw=0,
                        label=r"$\pm$ 95% half-width $1.96\,\sigma_k$")
        ax.axhline(0.0, color="0.3", lw=0.6)
    if not np.isfinite(truth).any():
        if not predictive:
            ax.text(0.5, 0.5, "no truth in this log: the error cannot be computed", transform=ax.transAxes,
                    ha="center", va="center", fontsize=10)
    else:
        error = mean - truth
        if model is not None and np.isfinite(z).any():
            obs = np.sqrt(20.0 * np.clip(z, 0.0, None)) - np.abs(truth)
            ax.plot(steps, obs, ls="none", marker="s", ms=2.5, color=COLOURS["observation"],
                    label=r"observation: $\sqrt{20\,z_k} - |x_k|$ (magnitude only)")
        ax.plot(steps, error, color=COLOURS["estimate"], lw=1.3, marker="o", ms=2.5,
                label=r"estimate error $\hat{x}_k - x_k$")
        out = np.abs(error) > half
        if out.any():
            ax.plot(steps[out], error[out], ls="none", marker="o", ms=5, mfc="none", mew=1.2,
                    color=COLOURS["outside"], label="outside the 95% interval")
        rmse = run.rmse
        ax.set_title(f"Error against the truth (Fig. 8): RMSE {rmse:.3f}, mean |error| "
                     f"{np.nanmean(np.abs(error)):.3f}, mean half-width {np.nanmean(half):.3f}",
                     loc="left", fontsize=10)
    _mark_degraded(ax, steps, np.array([x.degraded for x in e]))
    _mark_particle_steps(ax, steps_at)
    ax.set_ylabel(ylabel)
    ax.set_xlabel("time step k")
    _headroom(ax, 0.15)
    ax.legend(loc="upper left", fontsize=8, ncol=4, framealpha=0.9)
    ax.margins(x=0.01)
    if not ax.get_title(loc="left"):
        ax.set_title("Error against the truth (Fig. 8)", loc="left", fontsize=10)


def _plot_health(ax, run: RunLog, steps, steps_at):
    e = run.estimates
    ess = np.array([x.ess_ratio for x in e])
    degraded = np.array([x.degraded for x in e])
    ax.plot(steps, ess, color=COLOURS["ess"], lw=1.3, marker="o", ms=2.5, label="ESS/N (before resampling)")
    ps = _series_optional(e, "ps")
    if np.isfinite(ps).any():
        ax.step(steps, ps, where="mid", color=COLOURS["ps"], lw=1.6, label="PS used at step k")
    commands = run.ps_commands
    changes = [c for i, c in enumerate(commands) if i == 0 or c.ps != commands[i - 1].ps]
    if len(changes) > 1:
        ax.plot([c.applies_from_step for c in changes], [c.ps for c in changes], ls="none", marker="v", ms=6,
                color=COLOURS["ps"], label="PS changed by the system layer")
    if degraded.any():
        ax.plot(steps[degraded], ess[degraded], ls="none", marker="x", ms=7, mew=1.5, color=COLOURS["degraded"],
                label="degraded: plain resampling (no preprocessed set in time)")
    not_resampled = ~np.array([x.resampled for x in e])
    if not_resampled.any():
        ax.plot(steps[not_resampled], np.zeros(not_resampled.sum()), ls="none", marker="|", ms=8,
                color="0.3", label="not resampled")
    _mark_degraded(ax, steps, degraded)
    _mark_particle_steps(ax, steps_at)
    ax.set_ylim(-0.03, 1.3)
    ax.set_ylabel("ESS/N, PS")
    ax.set_xlabel("time step k")
    if np.isfinite(ps).any():
        ps_text = f"PS {np.nanmin(ps):g}" + ("" if np.nanmin(ps) == np.nanmax(ps) else f"..{np.nanmax(ps):g}")
    elif run.config.get("preprocess") is False:
        ps_text = "no PS (run without preprocessing)"
    else:
        ps_text = "no PS (no preprocessed set was resampled)"
    marked = ", shaded red" if degraded.any() else ""
    ax.set_title(f"Effective sample size ESS/N and preprocessing degree PS: mean ESS/N {ess.mean():.2f}, "
                 f"{ps_text}, {int(degraded.sum())} degraded step{'' if degraded.sum() == 1 else 's'}{marked}",
                 loc="left", fontsize=10)
    ax.legend(loc="upper right", fontsize=8, ncol=4, framealpha=0.9)
    ax.margins(x=0.01)


def _series_optional(estimates, name) -> np.ndarray:
    return np.array([np.nan if getattr(x, name) is None else getattr(x, name) for x in estimates], dtype=float)


def _processed_mask(before, after) -> np.ndarray | None:
    """Which particles the rules moved: weight <= W in the propagated set (Eq. 28), checked against n_processed."""
    if before is None or after is None or before.weights.shape != after.weights.shape:
        return None
    if after.threshold is not None:
        mask = before.weights <= after.threshold
        if after.n_processed is None or int(mask.sum()) == after.n_processed:
            return mask
    return np.any(before.particles != after.particles, axis=1)


def _particle_panels(figure, spec, run: RunLog, steps_at, component: int = 0):
    """Two rows of panels: before preprocessing (top) and after it (bottom), one column per step."""
    estimates = {e.step: e for e in run.estimates}
    if not run.propagated_count and not run.preprocessed_count:
        ax = figure.add_subplot(spec)
        ax.set_title("Particles before / after preprocessing (Fig. 10)", loc="left", fontsize=10)
        preprocess = run.config.get("preprocess")
        why = ("the run had no DT preprocessing (--no-preprocess), and without it the entity publishes "
               "no particle sets" if preprocess is False else "the log holds no entity/particles and no "
               "information/preprocessed messages for this twin")
        ax.text(0.5, 0.5, f"No particle sets to draw: {why}.",
                transform=ax.transAxes, ha="center", va="center", fontsize=11)
        ax.set_xticks([])
        ax.set_yticks([])
        return [ax]
    axes = []
    legend: dict[str, object] = {}
    inner = spec.subgridspec(2, len(steps_at))
    for column, k in enumerate(steps_at):
        before, after = run.propagated.get(k), run.preprocessed.get(k)
        top = figure.add_subplot(inner[0, column])
        bottom = figure.add_subplot(inner[1, column], sharex=top, sharey=top)
        axes += [top, bottom]
        mask = _processed_mask(before, after)
        estimate = estimates.get(k)
        first = column == 0
        if before is None:
            top.set_title(f"k = {k}, before preprocessing", fontsize=9)
            _no_set(top, f"no propagated set at step {k}" + _why_no_set(estimate))
        else:
            x, w = before.particles[:, component], before.weights
            counts = f"N = {w.size}"
            if mask is None:
                top.scatter(x, w, s=6, color=COLOURS["kept"], lw=0, label="particle")
            else:
                top.scatter(x[~mask], w[~mask], s=6, color=COLOURS["kept"], lw=0, label="large: w > W, kept as is")
                top.scatter(x[mask], w[mask], s=6, color=COLOURS["small"], lw=0, label="small: w ≤ W, to be moved")
                counts = f"{int((~mask).sum())} large, {int(mask.sum())} small"
            if after is not None and after.threshold is not None:
                top.axhline(after.threshold, color="0.3", lw=0.8, ls="--", label="threshold W (Eq. 28)")
                counts += f", W = {after.threshold:.2g}"
            ess = f"ESS/N {estimate.ess_ratio:.2f}: " if estimate is not None else ""
            top.set_title(f"k = {k}, before preprocessing\n{ess}{counts}", fontsize=9)
        if after is None:
            if not run.preprocessed_count:
                reason = "no preprocessed sets in this log"
            elif estimate is not None and estimate.degraded:
                reason = f"no preprocessed set at step {k}:\ndegraded step (no answer in time)"
            else:
                reason = f"no preprocessed set at step {k}" + _why_no_set(estimate)
            _no_set(bottom, reason)
            bottom.set_title(f"k = {k}, after preprocessing", fontsize=9)
        else:
            x, w = after.particles[:, component], after.weights
            moved = f"{after.n_processed} moved" if after.n_processed is not None else "moved"
            detail = (f" ({after.n_mixed} by Eq. 33, {after.n_plain} by Eq. 34)"
                      if after.n_mixed is not None and after.n_plain is not None else "")
            bottom.set_title(f"k = {k}, after preprocessing with PS = {after.ps:g}\n{moved}{detail}", fontsize=9)
            if mask is None:
                bottom.scatter(x, w, s=6, color=COLOURS["processed"], lw=0, label="particle")
            else:
                bottom.scatter(x[~mask], w[~mask], s=6, color=COLOURS["kept"], lw=0, label="large: w > W, kept as is")
                bottom.scatter(x[mask], w[mask], s=8, color=COLOURS["processed"], lw=0,
                               label="processed: new position")
        for ax in (top, bottom):
            if estimate is not None:
                if estimate.truth is not None:
                    ax.axvline(estimate.truth[component], color=COLOURS["truth"], lw=1.0, ls="--",
                               label="truth $x_k$")
                ax.axvline(estimate.mean[component], color=COLOURS["estimate"], lw=1.0, label=r"estimate $\hat{x}_k$")
            ax.tick_params(labelsize=8)
            ax.yaxis.get_offset_text().set_fontsize(7)
            if first:
                source = "entity/particles" if ax is top else "information/preprocessed"
                ax.set_ylabel(f"{source}\n" + r"weight $w_k^i$", fontsize=9)
            for handle, label in zip(*ax.get_legend_handles_labels()):
                legend.setdefault(label, handle)
        shown = "" if len(run.estimates[0].mean) == 1 else f" (component {component})"
        bottom.set_xlabel(r"particle value $x_k^i$" + shown)
        top.tick_params(labelbottom=True)
    if legend:
        figure.legend(list(legend.values()), list(legend), loc="outside lower center", ncol=len(legend),
                      fontsize=8, markerscale=2.0, handlelength=1.5, frameon=False)
    return axes


def _why_no_set(estimate) -> str:
    if estimate is not None and not estimate.resampled:
        return ":\nthe filter did not resample at this step,\nand sets are sent only when it does"
    return ""


def _no_set(ax, text):
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", fontsize=9, wrap=True)


def plot_run(run: RunLog, steps_at: Sequence[int] | None = None, *, figsize=FIGSIZE, component: int = 0):
    """The figure of one run: a matplotlib Figure (not attached to pyplot, so nothing is shown).

    ``steps_at`` are the steps of the particle panels (default: the steps
    whose sets ``run`` holds, else :func:`default_steps`); ``component`` is the
    state component drawn (x[component], from 0; PlotError beyond the state).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    if not run.estimates:
        raise PlotError("no estimates to plot")
    dim = len(run.estimates[0].mean)
    if not 0 <= component < dim:
        raise PlotError(f"--component {component}: the state has {dim} component{'s' if dim != 1 else ''} "
                        f"(0 .. {dim - 1})", code=2)
    if steps_at is None:
        steps_at = sorted(set(run.propagated) | set(run.preprocessed)) or default_steps(run)
    steps_at = sorted({int(k) for k in steps_at})[:MAX_PARTICLE_STEPS]
    figure = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(figure)
    line1, line2 = _describe(run)
    figure.suptitle(f"{line1}\n{line2}", fontsize=10.5, x=0.01, ha="left")
    has_sets = bool(run.propagated_count or run.preprocessed_count)
    if not has_sets:
        steps_at = []  # nothing to point at below
    grid = figure.add_gridspec(4, 1, height_ratios=[3.0, 2.2, 1.6, 3.4 if has_sets else 0.8])
    steps = run.steps
    model = _growth_model(run.config)
    state = figure.add_subplot(grid[0])
    _plot_state(state, run, steps, model, steps_at, component)
    error = figure.add_subplot(grid[1], sharex=state)
    _plot_error(error, run, steps, model, steps_at, component)
    health = figure.add_subplot(grid[2], sharex=state)
    _plot_health(health, run, steps, steps_at)
    state.xaxis.set_major_locator(MaxNLocator(integer=True))  # steps are whole numbers (shared by all three)
    _particle_panels(figure, grid[3], run, steps_at, component)
    return figure


def save(figure, path, dpi: float = DEFAULT_DPI) -> Path:
    """Write ``figure`` to ``path`` (format from the suffix, PNG if none); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fmt = path.suffix[1:].lower() or "png"
    figure.savefig(path, dpi=dpi, format=fmt)
    return path


# --- command line ----------------------------------------------------------

DESCRIPTION = (
    "Draw one twin's run from an MCAP log as one figure: state, observation and estimate with the 95% "
    "interval (paper Figs. 6, 7); the error against the truth with the interval's half-width (Fig. 8); "
    "ESS/N and PS per step with degraded steps marked; and the particles (value against weight) before and "
    "after DT preprocessing at a few steps, the processed particles in red (Fig. 10). Exit code 1: the log "
    "cannot be used; 2: a bad option.")


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``plot`` subcommand to ``subparsers`` (of ``dtpf``); its handler is :func:`cmd_plot`."""
    parser = subparsers.add_parser("plot", help="draw a recorded run (MCAP log) as one PNG",
                                   description=DESCRIPTION)
    _add_arguments(parser)
    return parser


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", type=Path, metavar="LOG", help="MCAP log written by 'dtpf launch'")
    parser.add_argument("--output", "-o", type=Path, default=None, metavar="FILE.png",
                        help="image to write (default: LOG with the suffix .png)")
    parser.add_argument("--twin", default=None,
                        help="twin to plot (default: the only twin in the log; with several, this is required)")
    parser.add_argument("--steps-at", type=int, nargs="+", default=None, metavar="K",
                        help=f"steps of the particle panels, at most {MAX_PARTICLE_STEPS} (default: "
                             f"{DEFAULT_PARTICLE_STEPS} evenly spaced steps)")
    parser.add_argument("--component", "-c", type=_component, default=0, metavar="K",
                        help="state component to draw, x[K] counted from 0 (default: %(default)s)")
    parser.add_argument("--dpi", type=float, default=DEFAULT_DPI,
                        help=f"resolution; the image is {FIGSIZE[0]:g} x {FIGSIZE[1]:g} inches, so "
                             f"{FIGSIZE[0] * DEFAULT_DPI:.0f} x {FIGSIZE[1] * DEFAULT_DPI:.0f} pixels at the default "
                             "(default: %(default)s)")
    parser.set_defaults(handler=cmd_plot)


def _component(text: str) -> int:
    """``--component K``: a whole number >= 0 (checked against the state's dimension once the log is read)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a state component number (0, 1, ...), got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def cmd_plot(args: argparse.Namespace) -> int:
    """Handler of ``dtpf plot``: 0 on success, 1 for an unusable file, 2 for a bad option."""
    try:
        if not (math.isfinite(args.dpi) and 10 <= args.dpi <= 1000):
            raise PlotError(f"--dpi must be between 10 and 1000, got {args.dpi:g}", code=2)
        output = args.output if args.output is not None else args.log.with_suffix(".png")
        run = read_log(args.log, twin=args.twin, steps_at=args.steps_at)
        if args.steps_at and run.set_steps:
            missing = sorted(set(args.steps_at) - set(run.set_steps))
            if missing:
                shown = ", ".join(map(str, run.set_steps[:12])) + (" ..." if len(run.set_steps) > 12 else "")
                print(f"dtpf plot: note: no particle set at step {', '.join(map(str, missing))}; "
                      f"steps with sets: {shown}", file=sys.stderr)
        figure = plot_run(run, steps_at=args.steps_at, component=getattr(args, "component", 0))
        try:
            save(figure, output, dpi=args.dpi)
        except ValueError as error:  # unknown image format
            raise PlotError(f"cannot write {output}: {error}", code=2) from None
        except OSError as error:
            raise PlotError(f"cannot write {output}: {error}") from None
    except PlotError as error:
        print(f"dtpf plot: error: {error}", file=sys.stderr)
        return error.code
    print(output)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m dtpf.scripts.logs.plot LOG -o FILE.png`` (the same as ``dtpf plot``)."""
    parser = argparse.ArgumentParser(prog="dtpf plot", description=DESCRIPTION)
    _add_arguments(parser)
    args = parser.parse_args(argv)
    return args.handler(args)


if __name__ == "__main__":
    sys.exit(main())
