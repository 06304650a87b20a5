"""`make demo`: the IPSO tuner's main job on the sample bags, end to end (paper eqs. 15-22, Table 2).

``python -m transplanter_ident.cli.demo [--out DIR] [--bags DIR] [--seed N]``

1. tunes Q and R (eq. 22) with IPSO (eqs. 17-20, the paper's settings F = 20, k_max = 40) on
   ``bags/step20-ccw``, minimising eq. (21), starting from config/estimator.yaml, and writes
   ``DIR/tuned.yaml``; a standard PSO (eqs. 15-16) with the same evaluation budget runs too,
   for Fig. 4;
2. replays ``step20-ccw`` and ``step30-cw`` with ``config/estimator.yaml`` layered under
   ``DIR/tuned.yaml`` (the way a user would) and prints the paper's Table 2 for the starting
   against the tuned Q/R, with the tuned/start ratios; the replay CSVs are written by
   :func:`transplanter_ident.cli.replay.write_csv`;
3. repeats step 1 in the paper's own configuration (forward Euler eq. 10, linear stiffness,
   z = [vy, r]) from a trial-and-error Q/R, the comparison of the paper's Figs. 6-7;
4. compares the two objectives, ``mae`` (eq. 21) and ``nll``, on the ``sine`` bag by the final
   error of the identified stiffness against the simulator's truth;
5. writes the plots (Figs. 4-7) and a summary into DIR (default ``demo_out/``) and prints its path.

Bags missing from ``bags/`` (a checkout without them) are simulated first, with the seeds of
``make bags``. Runs in well under a minute once numba's cache is warm.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from transplanter_ident.bags.samples import ensure_bag
from transplanter_ident.cli.plots import plot_convergence, plot_model_output, plot_stiffness, require_pyplot
from transplanter_ident.cli.tuner import progress_printer
from transplanter_ident.cli.util import CliError, cli_main
from transplanter_ident.config.paper import PAPER_NOISE, PAPER_OPTIONS
from transplanter_ident.config.parameters import EstimatorConfig, ValiditySettings
from transplanter_ident.config.params_file import EstimatorParams, load_params
from transplanter_ident.config.params_writer import write_params_yaml
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.ekf.layout import O_CF, O_CR, O_STATUS, StepStatus
from transplanter_ident.ekf.model import discrete_matrices
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.metrics import format_table2, stiffness_error
from transplanter_ident.evaluation.validity import decide_sequence
from transplanter_ident.files import atomic_write_text
from transplanter_ident.tuning.pso import pso_for_budget
from transplanter_ident.tuning.tune import (
    Comparison,
    compare,
    compare_configs,
    header_comment,
    tune,
    tuned_parameters,
)

ROOT = Path(__file__).resolve().parents[2]  # the checkout: its bags/ (an installed copy has none: they are simulated)
TUNE_BAG = "step20-ccw"
REPLAY_BAGS = ("step20-ccw", "step30-cw")
OBJECTIVE_BAG = "sine"



@dataclass(frozen=True)
class BagRun:
    """A bag's epochs and ground truth."""

    name: str
    path: Path
    epochs: EpochArrays
    truth: Any  # bag_io.Truth or None


def load_run(name: str, bags: Path, fallback: Path, params: EstimatorParams) -> BagRun:
    """Read one sample bag (epochs and truth)."""
    from transplanter_ident.bags import read_bag

    path = ensure_bag(name, bags, fallback)
    data = read_bag(path, params, truth=True)
    return BagRun(name, path, data.epochs, data.truth)


def base_parameters() -> tuple[list[Path], EstimatorParams]:
    """config/estimator.yaml of the checkout (the built-in defaults if it is missing)."""
    config = ROOT / "config" / "estimator.yaml"
    return ([config], load_params([config])) if config.is_file() else ([], EstimatorParams())


def stiffness_line(label: str, run: BagRun, config: EstimatorConfig) -> tuple[float, str]:
    """Final relative stiffness error against the truth: (mean of |Cf|, |Cr| errors, text)."""
    outputs = run_sequence(config, run.epochs)
    true_f, true_r = run.truth.at(run.epochs.t)
    err = stiffness_error(outputs, true_f, true_r)
    score = 0.5 * (abs(err.final_front) + abs(err.final_rear))
    return score, (f"{label:<30} final Cf {100 * err.final_front:+6.2f} %, Cr {100 * err.final_rear:+6.2f} % "
                   f"(mean |error| over the run: Cf {100 * err.mean_front:.2f} %, Cr {100 * err.mean_rear:.2f} %)")


def euler_unstable_fraction(config: EstimatorConfig, epochs: EpochArrays, outputs: np.ndarray) -> float:
    """Share of propagated epochs whose eq. (10) transition, at the stiffness identified before, is unstable."""
    unstable = total = 0
    for k in range(1, len(epochs)):
        if int(outputs[k, O_STATUS]) not in (StepStatus.UPDATED, StepStatus.GATED):
            continue
        dt = float(epochs.t[k] - epochs.t[k - 1])
        phi, _ = discrete_matrices(config.vehicle, float(outputs[k - 1, O_CF]), float(outputs[k - 1, O_CR]),
                                   float(epochs.speed[k]), dt, method="euler")
        unstable += int(np.max(np.abs(np.linalg.eigvals(phi))) > 1.0)
        total += 1
    return unstable / total if total else 0.0


def write_figures(out: Path, tag: str, run: BagRun, comparison: Comparison, algorithm: str) -> list[Path]:
    """Figs. 5-7 for one bag: stiffness with +-2 sigma and truth; model output tuned and start."""
    return [
        plot_stiffness(out / f"fig5_{tag}_stiffness_tuned.png", run.epochs, comparison.tuned_outputs, run.truth,
                       f"{run.name}: cornering stiffness, {algorithm}-EKF tuned Q/R (Fig. 5)"),
        plot_stiffness(out / f"fig5_{tag}_stiffness_start.png", run.epochs, comparison.start_outputs, run.truth,
                       f"{run.name}: cornering stiffness, starting Q/R"),
        plot_model_output(out / f"fig6_{tag}_model_output_tuned.png", run.epochs, comparison.tuned_outputs,
                          f"{run.name}: model output vs measurement, {algorithm}-EKF tuned Q/R (Fig. 6)"),
        plot_model_output(out / f"fig7_{tag}_model_output_start.png", run.epochs, comparison.start_outputs,
                          f"{run.name}: model output vs measurement, EKF with the starting Q/R (Fig. 7)"),
    ]


def _section(title: str) -> None:
    print(f"\n=== {title} ===", flush=True)


def _run(args: argparse.Namespace) -> int:
    began = time.perf_counter()
    require_pyplot()
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"{out}: cannot create the output folder: {exc.strerror or exc}") from None
    bags, fallback = Path(args.bags), out / "bags"
    base_files, params = base_parameters()
    start = params.config
    summary: list[str] = []

    _section(f"1. IPSO tuning of Q/R on {TUNE_BAG} (F = 20, k_max = 40, seed {args.seed})")
    tune_run = load_run(TUNE_BAG, bags, fallback, params)
    print(f"{tune_run.path}: {len(tune_run.epochs)} epochs; starting Q/R from "
          f"{base_files[0] if base_files else 'the built-in defaults'}; objective eq. 21 (mae)")
    ipso = tune(start, tune_run.epochs, algorithm="ipso", objective="mae", seed=args.seed,
                on_iteration=progress_printer(40, sys.stdout))
    tuned_yaml = out / "tuned.yaml"
    write_params_yaml(tuned_yaml, tuned_parameters(ipso.tuned_config),
                      header_comment(ipso, str(tune_run.path), len(tune_run.epochs)))
    budget = ipso.result.evaluations
    pso = tune(start, tune_run.epochs, algorithm="pso", objective="mae", seed=args.seed,
               iterations=pso_for_budget(budget).iterations, max_evaluations=budget)
    ipso_nll = tune(start, tune_run.epochs, algorithm="ipso", objective="nll", seed=args.seed)
    tuned_nll_yaml = out / "tuned_nll.yaml"
    write_params_yaml(tuned_nll_yaml, tuned_parameters(ipso_nll.tuned_config),
                      header_comment(ipso_nll, str(tune_run.path), len(tune_run.epochs)))
    for line in (f"IPSO (mae): {ipso.start_fitness:.6g} -> {ipso.result.fitness:.6g} in {budget} evaluations "
                 f"({ipso.seconds:.1f} s); wrote {tuned_yaml}",
                 f"standard PSO (mae), same budget ({pso.result.evaluations} evaluations): {pso.result.fitness:.6g}",
                 f"IPSO (nll): {ipso_nll.start_fitness:.6g} -> {ipso_nll.result.fitness:.6g} in "
                 f"{ipso_nll.result.evaluations} evaluations; wrote {tuned_nll_yaml}"):
        print(line)
        summary.append(line)
    plot_convergence(out / "fig4_objective.png", {"IPSO": ipso.result, "PSO": pso.result}, "mae")

    _section("2. Replay with config/estimator.yaml + tuned.yaml: Table 2, starting vs tuned Q/R")
    from transplanter_ident.cli.replay import write_csv

    layered = load_params([*base_files, tuned_yaml]).config
    layered_nll = load_params([*base_files, tuned_nll_yaml]).config
    for name in REPLAY_BAGS:
        run = tune_run if name == TUNE_BAG else load_run(name, bags, fallback, params)
        comparison = compare_configs(start, layered, run.epochs, "IPSO-EKF (tuned, mae)")
        with_nll = compare_configs(start, layered_nll, run.epochs, "IPSO-EKF (tuned, nll)")
        text = "\n".join([
            format_table2([comparison.start, comparison.tuned, with_nll.tuned],
                          f"Table 2, {name} ({len(run.epochs)} epochs; Q/R tuned on {TUNE_BAG})"),
            f"ratio tuned/start, mean err vy / r: mae-tuned {comparison.ratio('mean_error_vy'):.3f} / "
            f"{comparison.ratio('mean_error_r'):.3f}; nll-tuned {with_nll.ratio('mean_error_vy'):.3f} / "
            f"{with_nll.ratio('mean_error_r'):.3f}",
        ])
        for label, config in (("start Q/R", start), ("mae-tuned Q/R", layered), ("nll-tuned Q/R", layered_nll)):
            text += "\n" + stiffness_line(f"stiffness, {label}:", run, config)[1]
        print(text)
        summary.append(text)
        valid = decide_sequence(layered, ValiditySettings(), run.epochs, comparison.tuned_outputs)
        write_csv(out / f"{name}_tuned.csv", run.epochs, comparison.tuned_outputs, valid)
        write_figures(out, name, run, comparison, "IPSO")

    _section(f"3. The paper's filter (Euler eq. 10, linear stiffness, z = [vy, r]) on {TUNE_BAG}")
    paper_start = replace(start, options=PAPER_OPTIONS, noise=PAPER_NOISE)
    paper = tune(paper_start, tune_run.epochs, algorithm="ipso", objective="mae", seed=args.seed)
    paper_cmp = compare(paper, tune_run.epochs)
    unstable = [euler_unstable_fraction(paper_start, tune_run.epochs, o)
                for o in (paper_cmp.start_outputs, paper_cmp.tuned_outputs)]
    text = "\n".join([
        paper_cmp.format(f"Table 2, {TUNE_BAG}, paper's model: trial-and-error Q/R vs IPSO-tuned Q/R "
                         f"(mae {paper.start_fitness:.4g} -> {paper.result.fitness:.4g})"),
        f"forward Euler (eq. 10) at the identified stiffness is unstable (spectral radius > 1) at "
        f"{100 * unstable[0]:.0f} % of the epochs with the starting Q/R and {100 * unstable[1]:.0f} % with the "
        "tuned Q/R: that is why the starting model output diverges (DESIGN.md section 1)",
    ])
    print(text)
    summary.append(text)
    write_figures(out, f"{TUNE_BAG}_paper_model", tune_run, paper_cmp, "IPSO")

    _section(f"4. Objectives mae (eq. 21) vs nll on {OBJECTIVE_BAG}: final stiffness error against the truth")
    sine = load_run(OBJECTIVE_BAG, bags, fallback, params)
    scores = {}
    for objective in ("mae", "nll"):
        outcome = tune(start, sine.epochs, algorithm="ipso", objective=objective, seed=args.seed)
        scores[objective], text = stiffness_line(f"tuned on {objective}:", sine, outcome.tuned_config)
        print(text)
        summary.append(text)
    better = min(scores, key=scores.get)
    other = "nll" if better == "mae" else "mae"
    line = (f"smaller final stiffness error: {better} (mean of |Cf|, |Cr| errors {100 * scores[better]:.2f} % "
            f"against {100 * scores[other]:.2f} % for {other}; one bag and seed, see bench/objectives.py "
            "for several)")
    print(line)
    summary.append(line)

    atomic_write_text(out / "summary.txt", "\n\n".join(summary) + "\n")
    print(f"\ndemo: done in {time.perf_counter() - began:.1f} s; plots, tuned.yaml, CSVs and summary.txt in "
          f"{out.resolve()}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Command line of the demo."""
    parser = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", metavar="DIR", default="demo_out", help="output folder (default demo_out/)")
    parser.add_argument("--bags", metavar="DIR", default=str(ROOT / "bags"), help="sample bags (default bags/)")
    parser.add_argument("--seed", metavar="N", type=int, default=1, help="optimiser seed (default 1)")
    parser.add_argument("--debug", action="store_true", help="print tracebacks on errors")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m transplanter_ident.cli.demo``."""
    return cli_main(build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
