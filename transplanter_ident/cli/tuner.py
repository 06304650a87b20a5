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
stderr and a non-zero exit; a half-written YAML is never left behind. When no candidate
produced a finite objective (every one diverged, or never updated: ``ekf.DIVERGENCE_PENALTY``),
nothing is written. The ``--report`` folder appears whole, together with OUT.yaml, or not at all.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from transplanter_ident.cli.util import CliError, cli_main
from transplanter_ident.config.params_file import EstimatorParams, load_params
from transplanter_ident.config.params_writer import write_params_yaml
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.files import atomic_output_dir
from transplanter_ident.tuning.problem import OBJECTIVES
from transplanter_ident.tuning.pso import ALGORITHMS, IterationRecord
from transplanter_ident.tuning.tune import compare, header_comment, tune, tuned_parameters

MIN_EPOCHS = 50
#: what ``--report`` writes (cli/plots.write_report): an existing folder holding only these may be replaced
REPORT_FILES = frozenset({"fig4_objective.png", "fig5_stiffness_tuned.png", "fig5_stiffness_start.png",
                          "fig6_model_output_tuned.png", "fig7_model_output_start.png", "report.txt"})


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
    parser.add_argument("--allow-partial", action="store_true",
                        help="go on when fewer messages can be read than the bag's metadata counts (a corrupt chunk)")
    parser.add_argument("--debug", action="store_true", help="print tracebacks on errors")
    return parser


# --------------------------------------------------------------------------- building blocks


def load_parameters(files: Sequence[str]) -> EstimatorParams:
    """Layered parameter files, or the built-in defaults (those of config/estimator.yaml)."""
    return load_params(list(files)) if files else EstimatorParams()


def load_bag(bag: str, params: EstimatorParams, *, truth: bool = False, min_epochs: int = MIN_EPOCHS,
             allow_partial: bool = False) -> tuple[EpochArrays, Any]:
    """The bag's epochs (and its ground truth, or None); too few epochs to tune is an error."""
    from transplanter_ident.bags import read_bag  # rosbags only where bags are read

    data = read_bag(bag, params, truth=truth, allow_partial=allow_partial)
    for note in data.notes:
        print(f"tuner: note: {note}", file=sys.stderr)
    if len(data.epochs) < min_epochs:
        raise CliError(f"{bag}: only {len(data.epochs)} epochs, too short to tune (need at least {min_epochs})")
    return data.epochs, data.truth


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
        from transplanter_ident.cli.plots import require_pyplot

        require_pyplot()  # fail before the search, not after it
        check_report_path(args.report)
    params = load_parameters(args.params_file)
    epochs, truth = load_bag(args.bag, params, truth=bool(args.report), allow_partial=args.allow_partial)
    config = params.config
    print(f"tuner: {len(epochs)} epochs from {args.bag}; {args.algorithm} on {args.objective}, "
          f"F = {args.particles}, k_max = {args.iterations}, model {config.options.discretization}/"
          f"{config.options.stiffness_state}/{config.options.measurement}", file=sys.stderr)
    outcome = tune(config, epochs, algorithm=args.algorithm, objective=args.objective, particles=args.particles,
                   iterations=args.iterations, seed=args.seed, on_iteration=progress_printer(args.iterations))
    check_finite(outcome.result.fitness, outcome.result.evaluations, args.bag)
    result = outcome.result
    comparison = compare(outcome, epochs)
    with report_folder(args.report) as staged:  # renamed into place after OUT.yaml is written
        if staged is not None:
            from transplanter_ident.cli.plots import write_report

            written = write_report(staged, outcome, epochs, comparison, bag=args.bag, truth=truth)
        write_params_yaml(args.output, tuned_parameters(outcome.tuned_config),
                          header_comment(outcome, args.bag, len(epochs)))
    print(f"{args.algorithm}: {args.objective} {outcome.start_fitness:.6g} -> {result.fitness:.6g} "
          f"({result.evaluations} evaluations, {outcome.seconds:.1f} s, seed {outcome.seed}); wrote {args.output}")
    print(comparison.format(f"Table 2 on {args.bag}"))
    if args.report:
        print(f"report: {len(written)} files in {args.report}")
    return 0


def check_finite(fitness: float, evaluations: int, bag: str) -> None:
    """CliError when the best objective is not finite: every candidate diverged (DIVERGENCE_PENALTY)."""
    from transplanter_ident.ekf.layout import DIVERGENCE_PENALTY

    if not (math.isfinite(fitness) and fitness < DIVERGENCE_PENALTY):
        raise CliError(f"{bag}: none of the {evaluations} candidate Q/R gave a finite objective (each filter "
                       "diverged or never updated: too slow, below ekf.min_speed, or the base parameters do not fit "
                       "the bag); nothing written")


@contextlib.contextmanager
def report_folder(path: str | None) -> Iterator[Path | None]:
    """A staging folder for ``--report DIR``, moved to DIR on success; None without ``--report``.

    An existing DIR is replaced only if it is empty or an earlier report (its files only): never a
    folder of other files (``--report .``).
    """
    if path is None:
        yield None
        return
    check_report_path(path)
    with atomic_output_dir(path, overwrite=True) as staged:
        yield staged


def check_report_path(path: str) -> None:
    """CliError if ``--report DIR`` cannot be written, or would replace something that is not a report."""
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    if target.exists() and (not target.is_dir() or any(p.name not in REPORT_FILES for p in target.iterdir())):
        raise CliError(f"{target}: exists and is not an earlier report; choose a new folder for --report")
    if not parent.is_dir():
        raise CliError(f"{target}: directory {parent} does not exist")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``tuner`` executable."""
    return cli_main(build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
