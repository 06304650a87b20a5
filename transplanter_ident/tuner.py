"""The `tuner` command: IPSO/PSO tuning of the EKF's Q and R on a bag (paper eqs. 15-22, Table 2).

``tuner BAG -o OUT.yaml [--params-file P.yaml ...] [--algorithm ipso|pso] [--objective mae|nll]
[--particles N] [--iterations N] [--seed N] [--report DIR] [--debug]``

1. reads the bag's epochs (``bag_io.read_epochs``) with the layered parameters;
2. searches the log10 diagonal of Q and R (eq. 22, :mod:`tuning`) with IPSO (eqs. 17-20) or
   standard PSO (eqs. 15-16), minimising eq. (21) (``mae``) or the innovation NLL (``nll``),
   the starting Q/R being one of the initial particles; one progress line per iteration;
3. writes OUT.yaml atomically: ``ekf.process_noise``, ``ekf.measurement_noise`` (and the heading
   Q they were tuned with) plus the ``ekf`` options they are valid for, under a comment header;
   it layers over the defaults (``--params-file config/estimator.yaml --params-file OUT.yaml``);
4. prints the paper's Table 2 for the starting and the tuned Q/R on the same bag, and the
   tuned/start ratios of the mean errors; ``--report DIR`` adds the plots of Figs. 4-7.

Every failure (unreadable bag, too few epochs, unwritable output, bad flag) is one line on
stderr and a non-zero exit; a half-written YAML is never left behind.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from .cli_util import CliError, cli_main
from .ekf import run_sequence
from .measurements import EpochArrays
from .metrics import Table2Row, format_table2, table2_row
from .optimize import ALGORITHMS, IterationRecord, OptimizeResult, minimize, settings_for
from .parameters import EstimatorConfig
from .params_file import EstimatorParams, load_params, write_params_yaml
from .tuning import NAMES, OBJECTIVES, TuningProblem

MIN_EPOCHS = 50
START_LABEL = "EKF (start Q/R)"


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (``tuner: error: ...``) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} -h)\n")


def _int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {text!r}")
        return value

    return parse


_count = _int_at_least(1)
_seed = _int_at_least(0)


def build_parser() -> argparse.ArgumentParser:
    """Command line pinned in DESIGN.md section 3."""
    parser = _Parser(prog="tuner", description="Tune the EKF's Q and R on a recorded bag (IPSO or PSO).")
    parser.add_argument("bag", metavar="BAG", help="rosbag2 directory (with metadata.yaml) or a .mcap file")
    parser.add_argument("-o", "--output", metavar="OUT.yaml", required=True, help="params YAML to write")
    parser.add_argument("--params-file", metavar="P.yaml", action="append", default=[],
                        help="base parameters (repeatable, layered; default: built-in = config/estimator.yaml)")
    parser.add_argument("--algorithm", choices=ALGORITHMS, default="ipso", help="optimiser (default ipso)")
    parser.add_argument("--objective", choices=tuple(OBJECTIVES), default="nll",
                        help="nll: innovation negative log-likelihood (default; more robust, see README); "
                             "mae: the paper's eq. 21 mean |innovation|")
    parser.add_argument("--particles", metavar="N", type=_count, default=20, help="swarm size F (default 20)")
    parser.add_argument("--iterations", metavar="N", type=_count, default=40, help="iterations k_max (default 40)")
    parser.add_argument("--seed", metavar="N", type=_seed, help="random seed (default: drawn, and recorded in OUT)")
    parser.add_argument("--report", metavar="DIR", help="write plots (Figs. 4-7) and the metrics to DIR")
    parser.add_argument("--debug", action="store_true", help="print tracebacks on errors")
    return parser


# --------------------------------------------------------------------------- building blocks


@dataclass(frozen=True)
class TuningOutcome:
    """What one tuning run produced."""

    problem: TuningProblem
    result: OptimizeResult
    start_fitness: float
    seed: int
    seconds: float

    @property
    def start_config(self) -> EstimatorConfig:
        """The configuration tuning started from (hand-tuned Q/R)."""
        return self.problem.config

    @property
    def tuned_config(self) -> EstimatorConfig:
        """The configuration with the tuned Q/R."""
        return self.problem.tuned_config(self.result.position)


@dataclass(frozen=True)
class Comparison:
    """Table 2 for the starting and the tuned Q/R over the same epochs."""

    start: Table2Row
    tuned: Table2Row
    start_outputs: np.ndarray
    tuned_outputs: np.ndarray

    def ratio(self, name: str) -> float:
        """Ratio tuned / start of a Table2Row field (NaN if the start is 0 or not finite)."""
        before, after = getattr(self.start, name), getattr(self.tuned, name)
        return after / before if math.isfinite(before) and before > 0.0 else math.nan

    def format(self, title: str = "") -> str:
        """Table 2's layout, plus the tuned/start ratios of the mean errors."""
        table = format_table2([self.start, self.tuned], title)
        return (f"{table}\nratio tuned/start: mean err vy {self.ratio('mean_error_vy'):.3g}, "
                f"mean err r {self.ratio('mean_error_r'):.3g} (max err vy {self.ratio('max_error_vy'):.3g}, "
                f"max err r {self.ratio('max_error_r'):.3g})")


def load_parameters(files: Sequence[str]) -> EstimatorParams:
    """Layered parameter files, or the built-in defaults (those of config/estimator.yaml)."""
    return load_params(list(files)) if files else EstimatorParams()


def load_bag(bag: str, params: EstimatorParams, *, truth: bool = False,
             min_epochs: int = MIN_EPOCHS) -> tuple[EpochArrays, Any]:
    """The bag's epochs (and its ground truth, or None); too few epochs to tune is an error."""
    from .bag_io import read_bag  # rosbags only where bags are read

    data = read_bag(bag, params, truth=truth)
    if len(data.epochs) < min_epochs:
        raise CliError(f"{bag}: only {len(data.epochs)} epochs, too short to tune (need at least {min_epochs})")
    return data.epochs, data.truth


def tune(config: EstimatorConfig, epochs: EpochArrays, *, algorithm: str = "ipso", objective: str = "nll",
         particles: int = 20, iterations: int = 40, seed: int | None = None,
         max_evaluations: int | None = None,
         on_iteration: Callable[[IterationRecord], None] | None = None) -> TuningOutcome:
    """Search Q/R on ``epochs``; ``config``'s own Q/R (clipped to the box) is one of the initial particles.

    So the result is never worse than the starting Q/R when that lies inside the search box.
    ``seed`` None draws one (recorded in the outcome, so the run can be repeated).
    """
    seed = int(np.random.SeedSequence().entropy % 2**32) if seed is None else seed
    problem = TuningProblem.from_epochs(config, epochs, objective)
    settings = settings_for(algorithm, particles=particles, iterations=iterations)
    begin = time.perf_counter()
    result = minimize(problem, problem.box, settings, seed, initial=problem.start[None, :],
                      max_evaluations=max_evaluations, on_iteration=on_iteration)
    seconds = time.perf_counter() - begin
    return TuningOutcome(problem, result, problem.evaluate_noise(config.noise), seed, seconds)


def compare(outcome: TuningOutcome, epochs: EpochArrays, tuned_label: str | None = None) -> Comparison:
    """Table 2 rows of the starting and the tuned Q/R over ``epochs``."""
    label = tuned_label or f"{outcome.result.algorithm.upper()}-EKF (tuned)"
    return compare_configs(outcome.start_config, outcome.tuned_config, epochs, label)


def compare_configs(start: EstimatorConfig, tuned: EstimatorConfig, epochs: EpochArrays,
                    tuned_label: str = "IPSO-EKF (tuned)") -> Comparison:
    """Table 2 rows of two configurations over the same epochs."""
    start_out, tuned_out = run_sequence(start, epochs), run_sequence(tuned, epochs)
    return Comparison(table2_row(START_LABEL, epochs, start_out), table2_row(tuned_label, epochs, tuned_out),
                      start_out, tuned_out)


def tuned_parameters(config: EstimatorConfig) -> dict[str, Any]:
    """The flat keys the tuner writes: Q, R and the ekf options they are valid for."""
    options, noise = config.options, config.noise
    flat: dict[str, Any] = {
        "ekf.discretization": options.discretization,
        "ekf.stiffness_state": options.stiffness_state,
        "ekf.measurement": options.measurement,
        "ekf.process_noise": [float(v) for v in noise.process_noise],
        "ekf.measurement_noise": [float(v) for v in noise.measurement_noise],
    }
    if options.measurement == "heading":
        flat["ekf.heading_process_noise"] = float(noise.heading_process_noise)
    return flat


def header_comment(outcome: TuningOutcome, bag: str, epochs: int) -> str:
    """The YAML's comment header: provenance of the numbers."""
    result = outcome.result
    names = ", ".join(f"{n}={10.0**v:.3g}" for n, v in zip(NAMES, result.position, strict=True))
    return "\n".join([
        "Q and R tuned by transplanter_ident tuner (paper eqs. 15-22).",
        f"bag: {Path(bag).resolve()} ({epochs} epochs)",
        f"algorithm: {result.algorithm}, objective: {outcome.problem.objective}, seed: {outcome.seed}",
        f"fitness: {result.fitness:.6g} (start {outcome.start_fitness:.6g}), evaluations: {result.evaluations}, "
        f"iterations: {result.iterations}",
        f"tuned: {names}",
        "Layer over the defaults: --params-file config/estimator.yaml --params-file <this file>",
    ])


def check_output_path(path: str) -> None:
    """Fail early (before a long search) if OUT.yaml cannot be written."""
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    if target.is_dir():
        raise CliError(f"{target}: is a directory, cannot write the params YAML there")
    if not parent.is_dir():
        raise CliError(f"{target}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CliError(f"{target}: directory {parent} is not writable")


def progress_printer(total: int, stream: Any = None) -> Callable[[IterationRecord], None]:
    """One line per iteration with the best fitness (stderr)."""
    out = stream if stream is not None else sys.stderr

    def show(record: IterationRecord) -> None:
        chaos = f", chaotic search: {record.chaotic_particles}" if record.chaotic_particles else ""
        print(f"iteration {record.iteration:3d}/{total}: best {record.best_fitness:.6g}, "
              f"swarm median {record.median_fitness:.6g}, evaluations {record.evaluations}{chaos}",
              file=out, flush=True)

    return show


# --------------------------------------------------------------------------- command


def _run(args: argparse.Namespace) -> int:
    check_output_path(args.output)
    if args.report:
        from .plots import require_pyplot

        require_pyplot()  # fail before the search, not after it
    params = load_parameters(args.params_file)
    epochs, truth = load_bag(args.bag, params, truth=bool(args.report))
    config = params.config
    print(f"tuner: {len(epochs)} epochs from {args.bag}; {args.algorithm} on {args.objective}, "
          f"F = {args.particles}, k_max = {args.iterations}, model {config.options.discretization}/"
          f"{config.options.stiffness_state}/{config.options.measurement}", file=sys.stderr)
    outcome = tune(config, epochs, algorithm=args.algorithm, objective=args.objective, particles=args.particles,
                   iterations=args.iterations, seed=args.seed, on_iteration=progress_printer(args.iterations))
    write_params_yaml(args.output, tuned_parameters(outcome.tuned_config),
                      header_comment(outcome, args.bag, len(epochs)))
    result = outcome.result
    print(f"{args.algorithm}: {args.objective} {outcome.start_fitness:.6g} -> {result.fitness:.6g} "
          f"({result.evaluations} evaluations, {outcome.seconds:.1f} s, seed {outcome.seed}); wrote {args.output}")
    comparison = compare(outcome, epochs)
    print(comparison.format(f"Table 2 on {args.bag}"))
    if args.report:
        from .plots import write_report

        written = write_report(args.report, outcome, epochs, comparison, bag=args.bag, truth=truth)
        print(f"report: {len(written)} files in {args.report}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``tuner`` executable."""
    return cli_main(build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
