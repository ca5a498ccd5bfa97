"""The plan of ``dtpf compare``: which runs it makes, checked before any of them starts.

A plan is one cell of the comparison: the variants, each one's run of seed 0 (checked: its model
loaded and probed, its filter built on the first observation), the seeds, the baseline and the metric.
A grid (``--grid particles=100,1000 --grid scenario=ungm,drift``) is one plan per cell, each cell the
run options with one value of every gridded field, in the order given (the first field outermost)::

    cells = parse_grid(["particles=100,1000"])            # [Cell("particles=100", ...), ...]
    plans = [make_plan(base, variants, seeds, "plain", None, None, steps_given=True, cell=c) for c in cells]
    tasks = tasks_of(plans, done=set())                   # seed by seed, every cell and variant of a seed
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

from dtpf.messages.config import RunConfig, RunInputError
from dtpf.messages.errors import DtpfError
from dtpf.scripts.compare_metrics import Metric, parse_metric
from dtpf.scripts.compare_runs import Task, WARM_PARTICLES, WARM_STEPS
from dtpf.scripts.compare_variants import Variant, settings_of

__all__ = ["Cell", "Plan", "parse_grid", "parse_seeds", "make_plan", "tasks_of", "warm_configs"]


@dataclass(frozen=True)
class Cell:
    """A cell of a grid: its name (``particles=100, scenario=drift``; "" without a grid) and the run fields it
    sets over the run options (as text, as a variant's)."""

    name: str = ""
    fields: dict[str, str] = field(default_factory=dict)


class Plan:
    """What a compare does in one cell: the variants, each one's run of seed 0, the seeds, the baseline, the
    metric."""

    def __init__(self, variants: list[Variant], configs: dict[str, RunConfig], seeds: list[int], baseline: str,
                 metric: Metric, cell: str = ""):
        self.variants, self.configs, self.seeds, self.baseline = variants, configs, seeds, baseline
        self.metric, self.cell = metric, cell

    @property
    def labels(self) -> list[str]:
        return [variant.label for variant in self.variants]

    def settings(self) -> dict[tuple[str, str], str]:
        """Each (cell, label)'s settings (its run but the seed), as the CSV keeps them."""
        return {(self.cell, label): settings_of(config) for label, config in self.configs.items()}

    def tasks(self, done: set[tuple[str, str, int]], seeds: list[int] | None = None) -> list[Task]:
        """The runs not in ``done`` (cell, label, seed), seed by seed (every variant of a seed before the next)."""
        settings = self.settings()
        return [Task(variant.label, variant.spec, settings[(self.cell, variant.label)],
                     self.configs[variant.label].model_copy(update={"seed": seed}), self.metric, self.cell)
                for seed in (self.seeds if seeds is None else seeds) for variant in self.variants
                if (self.cell, variant.label, seed) not in done]


def parse_seeds(count: int | None, listed: str | None) -> list[int]:
    """The seeds: ``listed`` ('0,5,9' or ranges '100-199', comma-separated) or 0 .. count-1."""
    if listed is None:
        if count is None or count < 1:
            raise RunInputError(f"--seeds: at least 1, got {count}")
        return list(range(count))
    seeds: list[int] = []
    for part in listed.split(","):
        first, dash, last = part.strip().partition("-")
        try:
            seeds += list(range(int(first), int(last) + 1)) if dash else [int(first)]
        except ValueError:
            raise RunInputError(f"--seed-list: {part.strip()!r} is not a seed or a range FIRST-LAST") from None
    if not seeds or min(seeds) < 0:
        raise RunInputError(f"--seed-list: seeds are integers >= 0, got {listed!r}")
    return list(dict.fromkeys(seeds))


def parse_grid(texts: list[str] | None) -> list[Cell]:
    """The cells of ``--grid FIELD=VALUE[,VALUE...]`` given once per field: every combination, the first field
    outermost; one unnamed cell without a grid."""
    if not texts:
        return [Cell()]
    axes: list[tuple[str, list[str]]] = []
    for text in texts:
        name, equals, values = text.partition("=")
        name = name.strip().replace("-", "_")
        listed = [value.strip() for value in values.split(",")] if equals else []
        if not equals or not name or not all(listed):
            raise RunInputError(f"--grid: FIELD=VALUE[,VALUE...], e.g. particles=100,1000, got {text!r}")
        if name == "seed":
            raise RunInputError("--grid: the seed is each run's own (--seeds or --seed-list)")
        if name not in RunConfig.model_fields:
            raise RunInputError(f"--grid: unknown field {name!r} (the run settings: "
                                f"{', '.join(f for f in RunConfig.model_fields if f != 'seed')})")
        if name in (axis for axis, _ in axes):
            raise RunInputError(f"--grid: {name} is given twice")
        if len(set(listed)) != len(listed):
            raise RunInputError(f"--grid: {name} lists a value twice ({values.strip()})")
        axes.append((name, listed))
    return [Cell(", ".join(f"{name}={value}" for (name, _), value in zip(axes, combination)),
                 {name: value for (name, _), value in zip(axes, combination)})
            for combination in itertools.product(*(values for _, values in axes))]


def make_plan(base: RunConfig, variants: list[Variant], seeds: list[int], baseline: str | None,
              metric: str | None, components: str | None, steps_given: bool, cell: Cell = Cell()) -> Plan:
    """The plan of one cell, checked: RunInputError (one line, naming the variant and the cell) for anything
    wrong. ``base``: the run options; ``metric``, ``components``: as given (None: the default);
    ``steps_given``: whether the options set the steps (else a simulation is held to the model's most)."""
    labels = [variant.label for variant in variants]
    repeated = sorted({label for label in labels if labels.count(label) > 1})
    if repeated:
        raise RunInputError(f"--variant: label {repeated[0]!r} is given twice")
    baseline = labels[0] if baseline is None else baseline
    if baseline not in labels:
        raise RunInputError(f"--baseline {baseline!r} is none of the variants ({', '.join(labels)})")
    where = f" of cell {cell.name!r}" if cell.name else ""
    cell_base = _cell_base(base, cell)
    configs, truths, metrics = {}, {}, {}
    for variant in variants:
        both = set(variant.fields) & set(cell.fields)
        if both:
            raise RunInputError(f"variant {variant.label!r} sets {', '.join(sorted(both))}, which --grid varies")
        config = variant.config(cell_base, seed=0)
        try:
            config, truths[variant.label] = _checked(config, steps_given or "steps" in variant.fields
                                                     or "steps" in cell.fields)
            chosen = parse_metric(metric, components, truths[variant.label] is not None)
            chosen.check(truths[variant.label][0] if truths[variant.label] else 0,
                         truths[variant.label][1] if truths[variant.label] else None)
        except RunInputError as error:
            text = str(error)
            raise RunInputError(text if text.startswith("--") else f"variant {variant.label!r}{where}: {text}") \
                from None
        except (DtpfError, ValueError) as error:
            raise RunInputError(f"variant {variant.label!r}{where}: {error}") from None
        configs[variant.label], metrics[variant.label] = config, chosen
    if len(set(metrics.values())) > 1:
        kinds = "; ".join(f"{label}: {'the truth' if truths[label] else 'no truth'}" for label in labels)
        raise RunInputError(f"the variants{where} are judged by different metrics ({kinds}): give them all truth or "
                            f"none, or name one with --metric")
    return Plan(variants, configs, seeds, baseline, metrics[baseline], cell.name)


def _cell_base(base: RunConfig, cell: Cell) -> RunConfig:
    """The run options with the cell's fields; RunInputError names the cell."""
    if not cell.fields:
        return base
    values = base.model_dump()
    values.update({name: None if text.lower() == "none" else text for name, text in cell.fields.items()})
    try:
        return RunConfig(**values)
    except RunInputError as error:
        raise RunInputError(f"--grid: cell {cell.name!r}: {error}") from None


def _checked(config: RunConfig, steps_given: bool) -> tuple[RunConfig, tuple[int, tuple[int, ...]] | None]:
    """The run of seed 0 with its model loaded and checked and its filter built on the first observation (so
    a user's resampler, move or policy is loaded), simulated steps held to the model's most; and what truth it
    has: (the state's dimension, the components the truth covers), or None."""
    from dtpf.entity import sources
    from dtpf.scripts.inprocess import build

    if config.live:
        raise RunInputError("live observations need dtpf launch; compare filters a file or a simulation")
    model = sources.load_model(config)
    first = sources.observations_of(config.model_copy(update={"steps": 1}), model)
    build(config, first.observations, model)
    if config.simulated:
        most = getattr(model, "max_steps", None)
        if most is not None and config.steps > most:
            if steps_given:
                raise RunInputError(f"steps: the {config.model_ref} scenario can simulate at most {most} steps, "
                                    f"got {config.steps}")
            config = config.model_copy(update={"steps": most})
    if first.known_truth is None:
        return config, None
    return config, (int(model.dim), tuple(first.truth_components))


def tasks_of(plans: list[Plan], done: set[tuple[str, str, int]]) -> list[Task]:
    """Every plan's runs not in ``done``, seed by seed: all cells and variants of a seed before the next, so that
    a compare cut short holds whole seeds."""
    seeds = list(dict.fromkeys(seed for plan in plans for seed in plan.seeds))
    held = [set(plan.seeds) for plan in plans]
    return [task for seed in seeds for plan, own in zip(plans, held) if seed in own for task in plan.tasks(done, [seed])]


def warm_configs(plans: list[Plan]) -> list[RunConfig]:
    """The configurations a worker warms up on: each distinct run of the plans on the warm-up's few particles
    and steps (cells that differ only in N or T warm up once)."""
    found: dict[str, RunConfig] = {}
    for plan in plans:
        for config in plan.configs.values():
            small = config.model_copy(update=dict(particles=min(config.particles, WARM_PARTICLES),
                                                  steps=min(config.steps or WARM_STEPS, WARM_STEPS)))
            found.setdefault(settings_of(small), config)
    return list(found.values())
