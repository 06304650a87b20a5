"""PNG plots of a tuning run, after the paper's Figs. 4-7 (matplotlib, Agg backend), and the report folder.

* Fig. 4 :func:`plot_convergence`: the global-best objective (eq. 21 or NLL) against iteration;
* Fig. 5 :func:`plot_stiffness`: identified Cf and Cr against time with a +-2 sigma band (the
  filter's posterior std), the truth dashed when the bag has it;
* Figs. 6-7 :func:`plot_model_output`: the identified model's output against the measurement
  for vy and r (Fig. 6 with the tuned Q/R, Fig. 7 with the starting, hand-tuned Q/R).

matplotlib is an optional dependency: :func:`require_pyplot` raises a one-line error naming
the package if it is missing. Files are written atomically (temp file, then rename).
:func:`write_report` writes one bag's figures and tables, :func:`write_multi_report` those of
a multi-bag run (Fig. 4 once, Figs. 5-7 per bag, Table 2 per bag and the leave-one-out table).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from transplanter_ident.cli.util import CliError
from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD, O_R_MODEL, O_VY_MODEL
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.metrics import propagated
from transplanter_ident.files import atomic_output_file, atomic_write_text
from transplanter_ident.tuning.pso import OptimizeResult

if TYPE_CHECKING:  # pragma: no cover
    from collections.abc import Sequence

    from transplanter_ident.tuning.multi import LeaveOneOut
    from transplanter_ident.tuning.tune import Comparison, TuningOutcome

OBJECTIVE_LABELS = {"mae": "mean |innovation| (eq. 21)", "nll": "innovation NLL"}


class StiffnessTruth(Protocol):
    """True cornering stiffness over time (simulated bags; ``bag_io.Truth``), N/rad per tire."""

    t: np.ndarray
    cf: np.ndarray
    cr: np.ndarray


def require_pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend, or a clear error if matplotlib is not installed."""
    try:
        import matplotlib
    except ImportError:
        raise CliError("plots need matplotlib, which is not installed (pip install matplotlib)") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    plt = require_pyplot()
    try:
        fig.tight_layout()
        with atomic_output_file(path, "wb", encoding=None) as handle:
            fig.savefig(handle, format="png", dpi=110)
    finally:
        plt.close(fig)
    return path


def plot_convergence(path: str | Path, results: Mapping[str, OptimizeResult], objective: str = "mae") -> Path:
    """Fig. 4: gbest objective against iteration, one curve per run (swarm median dotted if one run)."""
    plt = require_pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, result in results.items():
        iterations = [h.iteration for h in result.history]
        ax.plot(iterations, result.best_curve, marker=".", label=f"{label}: global best")
        if len(results) == 1:
            ax.plot(iterations, [h.median_fitness for h in result.history], ":", label=f"{label}: swarm median")
    ax.set_xlabel("iteration k")
    ax.set_ylabel(OBJECTIVE_LABELS.get(objective, objective))
    ax.set_title("Evolution of the objective function (Fig. 4)")
    values = np.concatenate([r.best_curve for r in results.values()])
    if np.all(values > 0) and values.max() / values.min() > 20:
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend()
    return _save(fig, Path(path))


def plot_stiffness(path: str | Path, epochs: EpochArrays, outputs: np.ndarray,
                   truth: StiffnessTruth | None = None, title: str = "") -> Path:
    """Fig. 5: Cf and Cr against time with +-2 sigma bands; truth dashed if given."""
    plt = require_pyplot()
    t0 = float(epochs.t[0]) if len(epochs) else 0.0
    t = epochs.t - t0
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for column, std, name, colour in ((O_CF, O_CF_STD, "Cf", "tab:blue"), (O_CR, O_CR_STD, "Cr", "tab:red")):
        value, sigma = outputs[:, column], outputs[:, std]
        ax.plot(t, value, color=colour, label=f"{name} identified")
        ax.fill_between(t, value - 2.0 * sigma, value + 2.0 * sigma, color=colour, alpha=0.15,
                        label=f"{name} +-2 sigma")
    if truth is not None and len(truth.t):
        ax.plot(truth.t - t0, truth.cf, "--", color="tab:blue", label="Cf true")
        ax.plot(truth.t - t0, truth.cr, "--", color="tab:red", label="Cr true")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("cornering stiffness [N/rad per tire]")
    ax.set_title(title or "Cornering stiffness of the front and rear tires (Fig. 5)")
    top = np.nanpercentile(np.concatenate([outputs[:, O_CF], outputs[:, O_CR]]), 99) if len(outputs) else 1.0
    if truth is not None and len(truth.t):
        top = max(top, float(np.max(truth.cf)), float(np.max(truth.cr)))
    ax.set_ylim(0.0, 1.6 * top if np.isfinite(top) and top > 0 else None)
    ax.grid(True, alpha=0.3)
    ax.legend(ncol=3, fontsize="small")
    return _save(fig, Path(path))


def plot_model_output(path: str | Path, epochs: EpochArrays, outputs: np.ndarray, title: str) -> Path:
    """Figs. 6-7: the identified model's vy and r against the measurement."""
    plt = require_pyplot()
    t = epochs.t - (float(epochs.t[0]) if len(epochs) else 0.0)
    mask = propagated(outputs)
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for ax, column, measured, name, unit in ((axes[0], O_VY_MODEL, epochs.lateral_velocity, "vy", "m/s"),
                                             (axes[1], O_R_MODEL, epochs.yaw_rate, "r", "rad/s")):
        model = np.where(mask, outputs[:, column], np.nan)
        ax.plot(t, measured, color="0.4", lw=1.0, label=f"{name} measured")
        ax.plot(t, model, color="tab:orange", lw=1.2, label=f"{name} model output")
        ax.set_ylabel(f"{name} [{unit}]")
        _limit_to_measurement(ax, measured, model)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    axes[0].set_title(title)
    axes[1].set_xlabel("time [s]")
    return _save(fig, Path(path))


def _limit_to_measurement(ax: Any, measured: np.ndarray, model: np.ndarray) -> None:
    """Keep the measurement readable when the model output runs away (diverging eq. 10 model)."""
    finite = measured[np.isfinite(measured)]
    if not len(finite):
        return
    low, high = float(finite.min()), float(finite.max())
    margin = max(high - low, 1e-3)
    low, high = low - margin, high + margin
    outside = np.isfinite(model) & ((model < low) | (model > high))
    if np.any(outside):
        ax.set_ylim(low, high)
        ax.text(0.01, 0.03, f"model output leaves the plot at {int(outside.sum())} epochs (max |value| "
                f"{np.nanmax(np.abs(model)):.3g})", transform=ax.transAxes, fontsize="small", color="tab:red")


def _report_dir(directory: str | Path) -> Path:
    require_pyplot()
    out = Path(directory)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"{out}: cannot create the report directory: {exc.strerror or exc}") from None
    return out


def _bag_figures(out: Path, suffix: str, algorithm: str, epochs: EpochArrays, comparison: Comparison,
                 truth: StiffnessTruth | None) -> list[Path]:
    """Figs. 5-7 of one bag (tuned and starting Q/R)."""
    return [
        plot_stiffness(out / f"fig5_stiffness_tuned{suffix}.png", epochs, comparison.tuned_outputs, truth,
                       f"Cornering stiffness, {algorithm}-EKF tuned Q/R (Fig. 5)"),
        plot_stiffness(out / f"fig5_stiffness_start{suffix}.png", epochs, comparison.start_outputs, truth,
                       "Cornering stiffness, starting Q/R"),
        plot_model_output(out / f"fig6_model_output_tuned{suffix}.png", epochs, comparison.tuned_outputs,
                          f"Model output vs measurement, {algorithm}-EKF tuned Q/R (Fig. 6)"),
        plot_model_output(out / f"fig7_model_output_start{suffix}.png", epochs, comparison.start_outputs,
                          "Model output vs measurement, EKF with the starting Q/R (Fig. 7)"),
    ]


def write_report(directory: str | Path, outcome: TuningOutcome, epochs: EpochArrays, comparison: Comparison, *,
                 bag: str = "", truth: StiffnessTruth | None = None,
                 extra_runs: Mapping[str, OptimizeResult] | None = None) -> list[Path]:
    """Figs. 4-7 and the metrics (report.txt) of one tuning run into ``directory`` (created)."""
    out = _report_dir(directory)
    algorithm = outcome.result.algorithm.upper()
    runs = {algorithm: outcome.result, **(extra_runs or {})}
    written = [plot_convergence(out / "fig4_objective.png", runs, outcome.problem.objective),
               *_bag_figures(out, "", algorithm, epochs, comparison, truth)]
    text = f"bag: {bag}\n{comparison.format('Table 2')}\n"
    atomic_write_text(out / "report.txt", text)
    written.append(out / "report.txt")
    return written


def write_multi_report(directory: str | Path, outcome: TuningOutcome, epochs: Sequence[EpochArrays],
                       comparisons: Sequence[Comparison], *, bags: Sequence[str],
                       truths: Sequence[StiffnessTruth | None], holdout: LeaveOneOut | None = None) -> list[Path]:
    """A multi-bag run: Fig. 4, Figs. 5-7 per bag (``_<n>_<bag name>``), report.txt with every table."""
    out = _report_dir(directory)
    algorithm = outcome.result.algorithm.upper()
    written = [plot_convergence(out / "fig4_objective.png", {algorithm: outcome.result}, outcome.problem.objective)]
    sections = []
    for n, (bag, bag_epochs, comparison, truth) in enumerate(zip(bags, epochs, comparisons, truths, strict=True), 1):
        name = "".join(c if c.isalnum() or c in "-_" else "_" for c in Path(bag).name) or "bag"
        written += _bag_figures(out, f"_{n}_{name}", algorithm, bag_epochs, comparison, truth)
        sections.append(f"bag {n}: {bag}\n{comparison.format('Table 2')}")
    if holdout is not None:
        sections.append(holdout.format())
        atomic_write_text(out / "leave_one_out.txt", holdout.format() + "\n")
        written.append(out / "leave_one_out.txt")
    atomic_write_text(out / "report.txt", "\n\n".join(sections) + "\n")
    written.append(out / "report.txt")
    return written
