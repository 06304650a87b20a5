"""The `tuner` command: IPSO/PSO/CMA-ES tuning of the EKF's Q and R on bags (paper eqs. 15-22, Table 2).

``tuner BAG [BAG ...] -o OUT.yaml [--params-file P.yaml ...] [--algorithm ipso|pso|cmaes] [--objective mae|nll]
[--particles N] [--iterations N] [--seed N] [--report DIR] [--jobs N] [--dask ADDRESS] [--epoch-cache DIR |
--no-epoch-cache] [--estimate-delay [--delay-range LOW HIGH]] [--estimate-steering-play] [--estimate-steering-scale]
[--estimate-yaw-inertia]
[--estimate-relaxation-length] [--estimate-heading-offset] [--tune-stiffness-noise] [--q-span DECADES]
[--no-leave-one-out] [--debug]``

1. reads each bag's epochs with the layered parameters, decoding a bag only if the epoch cache
   (:mod:`transplanter_ident.bags.cache`) does not hold it yet; with ``--estimate-heading-offset``, first
   finds ``vehicle.heading_offset`` from the filter's measure (:mod:`transplanter_ident.tuning.heading_offset`,
   the bags decoded again at each pass); with ``--estimate-delay``, decodes each
   bag once and first searches ``gnss.delay`` over -0.2-0.3 s on the same objective at the starting Q/R,
   then ``vehicle.steering_play`` (re-assembling the decoded samples likewise), ``vehicle.steering_scale``, ``vehicle.iz`` and ``vehicle.relaxation_length`` if asked
   (:mod:`transplanter_ident.cli.delay_search`), and uses the epochs at the estimates;
2. searches the log10 diagonal of Q and R (eq. 22, :mod:`tuning`): the physical noises (vy, r, psi process
   noise and R; the stiffness and offset random walks and the change mechanism keep their designed values
   unless ``--tune-stiffness-noise``; each process noise within ``--q-span`` decades of its configured
   value) with IPSO (eqs. 17-20), standard PSO (eqs. 15-16) or CMA-ES, minimising eq. (21) (``mae``) or the
   innovation NLL (``nll``), averaged over the bags with their epoch counts as weights; the starting Q/R is
   one of the initial candidates; one progress line per iteration. The candidates run on ``--jobs``
   processes or a Dask cluster (:mod:`transplanter_ident.tuning.parallel`): the same result either way;
3. writes OUT.yaml atomically: ``ekf.process_noise``, ``ekf.measurement_noise`` (and the heading Q they
   were tuned with), the ``ekf`` options they are valid for, and the estimates of step 1, under a comment
   header; it layers over the defaults (``--params-file config/estimator.yaml --params-file OUT.yaml``);
4. prints the paper's Table 2 for the starting and the tuned Q/R on each bag, and the tuned/start ratios of
   the mean errors; with several bags, a leave-one-bag-out table (:func:`transplanter_ident.tuning.multi.leave_one_out`);
   ``--report DIR`` adds the plots of Figs. 4-7 and the tables.

Every failure (unreadable bag, too few epochs, unwritable output, bad flag) is one line on stderr and
a non-zero exit; a half-written YAML is never left behind. When no candidate produced a finite
objective (every one diverged, or never updated: ``ekf.DIVERGENCE_PENALTY``), nothing is written.
The ``--report`` folder appears whole, together with OUT.yaml, or not at all.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

from transplanter_ident.cli.report_folder import check_report_path, report_folder
from transplanter_ident.cli.tuner_args import CALIBRATIONS, build_parser
from transplanter_ident.cli.util import CliError, cli_main
from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.config.params_file import EstimatorParams, load_params
from transplanter_ident.config.params_writer import write_params_yaml
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.cramer_rao import final_bound_line
from transplanter_ident.tuning.multi import LeaveOneOut, MultiBagProblem, StiffnessTruth, leave_one_out
from transplanter_ident.tuning.parallel import (
    Backend,
    ProcessBackend,
    SerialBackend,
    default_jobs,
    open_backend,
    warm_kernels,
    warm_worker,
)
from transplanter_ident.tuning.pso import IterationRecord
from transplanter_ident.tuning.tune import (
    Comparison,
    TuningOutcome,
    compare_configs,
    edge_note,
    header_comment,
    tune_problem,
    tuned_parameters,
)
from transplanter_ident.tuning.tune import tune as tune  # one bag, in-process (tests, benchmarks)

MIN_EPOCHS = 50


# --------------------------------------------------------------------------- building blocks


def load_parameters(files: Sequence[str]) -> EstimatorParams:
    """Layered parameter files, or the built-in defaults (those of config/estimator.yaml)."""
    return load_params(list(files)) if files else EstimatorParams()


def load_bag(bag: str, params: EstimatorParams, *, truth: bool = False,
             min_epochs: int = MIN_EPOCHS) -> tuple[EpochArrays, Any]:
    """The bag's epochs (and its ground truth, or None); too few epochs to tune is an error."""
    from transplanter_ident.bags import read_bag  # rosbags only where bags are read

    data = read_bag(bag, params, truth=truth)
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


def cache_dir(args: argparse.Namespace) -> Path | None:
    """The epoch cache folder of the command line (None: no cache)."""
    if args.no_epoch_cache:
        return None
    from transplanter_ident.bags.cache import default_cache_dir

    return Path(args.epoch_cache) if args.epoch_cache else default_cache_dir()


def load_bags(bags: Sequence[str], params: EstimatorParams, backend: Backend, cache: Path | None,
              stream: Any = None, allow_partial: bool = False) -> list[Any]:
    """Each bag's ``bags.cache.DecodedBag`` (decoded in parallel on ``backend``; one line each on stderr)."""
    from transplanter_ident.bags.cache import (  # rosbags only where bags are read
        cached_bag_epochs,
        load_bag_epochs,
    )

    out = stream if stream is not None else sys.stderr
    decoded = [cached_bag_epochs(bag, params, cache) if cache is not None else None for bag in bags]
    missing = [i for i, item in enumerate(decoded) if item is None]
    for i, item in zip(missing, backend.map(load_bag_epochs, [(bags[i], params, cache, allow_partial) for i in missing]),
                       strict=True):
        decoded[i] = item
    report_decoded(decoded, cache, out)
    return decoded


def report_decoded(decoded: Sequence[Any], cache: Path | None, out: Any) -> None:
    """One line per bag on ``out``; too few epochs to tune is a CliError."""
    for item in decoded:
        count = len(item.columns)
        if count < MIN_EPOCHS:
            raise CliError(f"{item.bag}: only {count} epochs, too short to tune (need at least {MIN_EPOCHS})")
        where = "from the epoch cache" if item.source == "cache" else (
            "decoded" + (f", cached in {cache}" if cache is not None and not item.note else ""))
        print(f"tuner: {item.bag}: {count} epochs ({where}){f'; note: {item.note}' if item.note else ''}",
              file=out, flush=True)


def _run(args: argparse.Namespace) -> int:
    check_output_path(args.output)
    if args.report:
        from transplanter_ident.cli.plots import require_pyplot

        require_pyplot()  # fail before the search, not after it
    params = load_parameters(args.params_file)
    jobs = args.jobs if args.jobs is not None else default_jobs()
    local = SerialBackend() if jobs <= 1 else ProcessBackend(jobs, warm_up=partial(warm_worker, params.config),
                                                             host_warm_up=partial(warm_kernels, params.config))
    remote = open_backend(dask_address=args.dask) if args.dask else local
    try:
        if isinstance(remote, ProcessBackend):
            remote.start()  # the workers start; this process loads (or compiles) the objective, then reads the bags
        return _tune_bags(args, params, local, remote)
    finally:
        for backend in {id(local): local, id(remote): remote}.values():
            backend.close()


def _calibrate(args: argparse.Namespace, params: EstimatorParams, local: Backend
               ) -> tuple[EstimatorParams, list[Any], dict[str, tuple[float, str]]]:
    """The calibration searches asked for, ahead of Q/R.

    Returns the parameters with their estimates, the decoded bags, and the estimates (key -> (value, the
    search's line)).
    """
    estimated: dict[str, tuple[float, str]] = {}
    asked = [f"--{f.replace('_', '-')}" for f in CALIBRATIONS if getattr(args, f)]
    if asked and params.config.options.course:
        raise CliError(f"{', '.join(asked)}: not with ekf.measurement course. One antenna's course hardly tells them "
                       "from the stiffness (its delay objective is flat over +-60 ms while Cf moves +-35 %): calibrate "
                       "on drives with a dual-antenna heading, or take them from the receiver's and the vehicle's data")
    if args.estimate_heading_offset:  # ahead of all: the offset shapes the epochs
        from transplanter_ident.cli.delay_search import calibrate_heading

        params = calibrate_heading(lambda at: [item.epochs for item in load_bags(
            args.bags, at, local, cache_dir(args), allow_partial=args.allow_partial)], params, local, estimated)
    if args.estimate_delay or args.estimate_steering_play:  # they shape the epochs: ahead of the rest
        from transplanter_ident.cli.delay_search import calibrate_timing, checked_delay_range

        params, decoded = calibrate_timing(args.bags, params, local, estimated, delay=args.estimate_delay,
                                           play=args.estimate_steering_play,
                                           delay_range=checked_delay_range(args.delay_range), objective=args.objective,
                                           tune_stiffness_noise=args.tune_stiffness_noise, cache=cache_dir(args),
                                           allow_partial=args.allow_partial)
        if args.estimate_delay:
            report_decoded(decoded, cache_dir(args), sys.stderr)
    else:
        decoded = load_bags(args.bags, params, local, cache_dir(args), allow_partial=args.allow_partial)
    if args.estimate_steering_scale or args.estimate_yaw_inertia or args.estimate_relaxation_length:  # ahead of Q/R
        from transplanter_ident.cli.delay_search import calibrate_vehicle

        params, decoded = calibrate_vehicle(decoded, params, local, estimated, objective=args.objective,
                                            steering_scale=args.estimate_steering_scale, yaw_inertia=args.estimate_yaw_inertia,
                                            relaxation=args.estimate_relaxation_length,
                                            tune_stiffness_noise=args.tune_stiffness_noise, cache=cache_dir(args))
    return params, decoded, estimated


def _tune_bags(args: argparse.Namespace, params: EstimatorParams, local: Backend, remote: Backend) -> int:
    if args.report:
        check_report_path(args.report)
    params, decoded, estimated = _calibrate(args, params, local)
    epochs = [item.epochs for item in decoded]
    truths = [item.truth for item in decoded]
    config = params.config
    problem = MultiBagProblem.from_epochs(config, epochs, args.objective, remote, args.tune_stiffness_noise,
                                          args.q_span)
    where = f"Dask cluster {args.dask}" if args.dask else f"{local.slots} job{'s' if local.slots > 1 else ''}"
    source = args.bags[0] if len(args.bags) == 1 else f"{len(args.bags)} bags"
    print(f"tuner: {sum(map(len, epochs))} epochs from {source}; {args.algorithm} on {args.objective}, "
          f"F = {args.particles}, k_max = {args.iterations}, model {config.options.discretization}/"
          f"{config.options.stiffness_state}/{config.options.measurement}; {where}", file=sys.stderr)
    outcome = tune_problem(problem, algorithm=args.algorithm, particles=args.particles, iterations=args.iterations,
                           seed=args.seed, on_iteration=progress_printer(args.iterations))
    check_finite(outcome.result.fitness, outcome.result.evaluations, ", ".join(args.bags))
    note = edge_note(outcome)
    if note:
        print(f"tuner: note: {note}", file=sys.stderr)
    result = outcome.result
    label = f"{outcome.result.algorithm.upper()}-EKF (tuned)"
    summaries = local.map(summarize_bag, [(outcome.start_config, outcome.tuned_config, bag_epochs, label)
                                          for bag_epochs in epochs])
    comparisons = [comparison for comparison, _ in summaries]
    holdout = None
    if len(args.bags) > 1 and not args.no_leave_one_out:
        def tune_fold(fold: MultiBagProblem, seed: int) -> Any:
            return tune_problem(fold, algorithm=args.algorithm, particles=args.particles,
                                iterations=args.iterations, seed=seed).tuned_config

        holdout = leave_one_out(problem, epochs, truths, args.bags, tune_fold, outcome.seed,
                                on_fold=lambda line: print(f"tuner: {line}", file=sys.stderr, flush=True))
    written = _write_outputs(args, outcome, epochs, truths, comparisons, holdout, estimated)
    print(f"{args.algorithm}: {args.objective} {outcome.start_fitness:.6g} -> {result.fitness:.6g} "
          f"({result.evaluations} evaluations, {outcome.seconds:.1f} s, seed {outcome.seed}); wrote {args.output}")
    for bag, (comparison, bound) in zip(args.bags, summaries, strict=True):
        print(comparison.format(f"Table 2 on {bag}"))
        print(f"  tuned Q/R, {bound}")
    for _, line in estimated.values():
        print(f"estimated {line}")
    if holdout is not None:
        print(holdout.format())
    if args.report:
        print(f"report: {len(written)} files in {args.report}")
    return 0


def _write_outputs(args: argparse.Namespace, outcome: TuningOutcome, epochs: Sequence[EpochArrays],
                   truths: Sequence[StiffnessTruth | None], comparisons: Sequence[Comparison],
                   holdout: LeaveOneOut | None, estimated: dict[str, tuple[float, str]]) -> list[Path]:
    """OUT.yaml (the tuned Q/R and the calibration estimates), and with ``--report`` its folder; the report's files.

    The report folder is staged and renamed into place after OUT.yaml is written: both or neither.
    """
    written: list[Path] = []
    with report_folder(args.report) as staged:
        if staged is not None:
            from transplanter_ident.cli.plots import write_multi_report, write_report

            if len(args.bags) == 1:
                written = write_report(staged, outcome, epochs[0], comparisons[0], bag=args.bags[0],
                                       truth=truths[0])
            else:
                written = write_multi_report(staged, outcome, epochs, comparisons, bags=args.bags, truths=truths,
                                             holdout=holdout)
        flat = tuned_parameters(outcome.tuned_config)
        header = header_comment(outcome, args.bags, [len(e) for e in epochs])
        for key, (value, line) in estimated.items():
            flat[key] = float(value)
            header += f"\nestimated {line}"
        write_params_yaml(args.output, flat, header)
    return written


def summarize_bag(start: EstimatorConfig, tuned: EstimatorConfig, epochs: EpochArrays,
                  label: str) -> tuple[Comparison, str]:
    """Table 2 on one bag (the filter with the start and the tuned Q/R) and its Cramér-Rao line (a task)."""
    comparison = compare_configs(start, tuned, epochs, label)
    return comparison, final_bound_line(tuned, epochs, comparison.tuned_outputs[-1])


def check_finite(fitness: float, evaluations: int, bag: str) -> None:
    """CliError when the best objective is not finite: every candidate diverged (DIVERGENCE_PENALTY)."""
    from transplanter_ident.ekf.layout import DIVERGENCE_PENALTY

    if not (math.isfinite(fitness) and fitness < DIVERGENCE_PENALTY):
        raise CliError(f"{bag}: none of the {evaluations} candidate Q/R gave a finite objective (each filter "
                       "diverged or never updated: too slow, below ekf.min_speed, or the base parameters do not fit "
                       "the bag); nothing written")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``tuner`` executable."""
    return cli_main(build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
