"""The ``dtpf`` command.

``dtpf run`` runs the three layers in one process on a scenario and prints a
summary. ``dtpf --help`` and ``dtpf run --help`` explain every option.
"""
from __future__ import annotations

import argparse
import sys

from pydantic import ValidationError

from entity import models, resampling
from information.rules import WEIGHT_RULES
from messages.config import RunConfig
from system import policy

__all__ = ["main", "add_run_arguments", "config_from_args"]


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of one run, shared by every command that starts a run."""
    defaults = RunConfig()
    group = parser.add_argument_group("scenario and filter")
    group.add_argument("--scenario", default=defaults.scenario, choices=sorted(models.MODELS),
                       help="state-space model: 'ungm' is Eq. 35 with 25 (the standard benchmark), "
                            "'ungm-printed' Eq. 35 as printed with 0.25 (default: %(default)s)")
    group.add_argument("--particles", "-n", type=int, default=defaults.particles,
                       help="number of particles N (default: %(default)s)")
    group.add_argument("--steps", "-T", type=int, default=defaults.steps,
                       help="number of time points (default: %(default)s)")
    group.add_argument("--resampler", default=defaults.resampler, choices=sorted(resampling.RESAMPLERS),
                       help="traditional resampling run after preprocessing (default: %(default)s)")
    group.add_argument("--resample-below", type=float, default=None, metavar="FRACTION",
                       help="resample only when ESS < FRACTION * N (default: every step, as the paper)")
    group.add_argument("--seed", type=int, default=defaults.seed, help="root seed (default: %(default)s)")
    group.add_argument("--twin", default=defaults.twin, help="twin id (default: %(default)s)")
    group.add_argument("--run-id", default=defaults.run_id, help="run id (default: %(default)s)")
    group = parser.add_argument_group("digital twin")
    group.add_argument("--no-preprocess", dest="preprocess", action="store_false",
                       help="turn the DT preprocessing off: the plain traditional filter")
    group.add_argument("--threshold", default=defaults.threshold,
                       help="W of Eq. 28: 'neff', 'inverse-n' or a number (default: %(default)s)")
    group.add_argument("--weight-rule", default=defaults.weight_rule, choices=WEIGHT_RULES,
                       help="weights of processed particles (default: %(default)s)")
    group.add_argument("--policy", default=defaults.policy, choices=sorted(policy.POLICIES),
                       help="PS policy of the system layer (default: %(default)s)")
    group.add_argument("--ps", type=float, default=defaults.ps,
                       help="PS of the fixed policy, initial PS of the others (default: %(default)s)")


def config_from_args(args: argparse.Namespace) -> RunConfig:
    """The RunConfig of parsed arguments; raises ValueError naming a bad option."""
    try:
        return RunConfig(scenario=args.scenario, particles=args.particles, steps=args.steps,
                         resampler=args.resampler, resample_below=args.resample_below,
                         preprocess=args.preprocess, threshold=args.threshold, weight_rule=args.weight_rule,
                         policy=args.policy, ps=args.ps, seed=args.seed, twin=args.twin, run_id=args.run_id)
    except ValidationError as error:
        problems = "; ".join(f"--{'-'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in error.errors())
        raise ValueError(problems.replace("_", "-")) from None


class Progress:
    """A one-line progress bar on stderr, redrawn at most every 2 %."""

    def __init__(self, stream=sys.stderr, width: int = 30):
        self.stream = stream
        self.width = width
        self.shown = -1

    def __call__(self, done: int, total: int) -> None:
        percent = 100 * done // total
        if percent // 2 == self.shown // 2 and done != total:
            return
        self.shown = percent
        filled = self.width * done // total
        self.stream.write(f"\r[{'#' * filled}{'.' * (self.width - filled)}] step {done}/{total}")
        if done == total:
            self.stream.write("\n")
        self.stream.flush()


def cmd_run(args: argparse.Namespace) -> int:
    from scripts.inprocess import run

    config = config_from_args(args)
    result = run(config, progress=None if args.quiet else Progress())
    ps = result.ps
    ps_text = "off" if not config.preprocess else f"{ps.min():g} .. {ps.max():g}"
    lines = [
        f"scenario        {config.scenario} (N = {config.particles}, T = {config.steps}, seed {config.seed})",
        f"resampling      {'DT preprocessing + ' if config.preprocess else ''}{config.resampler}",
        f"RMSE            {result.rmse:.4f}",
        f"mean ESS        {result.mean_ess:.1f} ({result.mean_ess / config.particles:.1%} of N)",
        f"resamplings     {result.resamplings}",
        f"PS range        {ps_text}",
        f"degraded steps  {result.degraded}",
        f"time            {result.elapsed:.3f} s ({1e3 * result.elapsed / config.steps:.3f} ms/step)",
    ]
    print("\n".join(lines))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dtpf",
        description="Digital-twin particle filter: a particle filter (entity layer) whose small-weight "
                    "particles are moved towards large-weight ones before resampling (information layer, "
                    "Eq. 28-30) with a degree PS set by degradation prediction (system layer).")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    run = commands.add_parser("run", help="run the three layers in one process and print a summary",
                              description="Run the three layers in one process (no transport) on a "
                                          "simulated scenario and print RMSE, ESS, PS and timing.")
    add_run_arguments(run)
    run.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    run.set_defaults(handler=cmd_run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except ValueError as error:
        parser.exit(2, f"dtpf {args.command}: error: {error}\n")
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
