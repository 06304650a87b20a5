"""The paper's Table 2 metrics and the replay CSV rows (DESIGN.md section 3).

Table 2 compares the identified model's output with the measurement: the maximum and mean
absolute error of vy and r. The model output is the bicycle model driven by the measured
steering and vx with the stiffness identified at each epoch, open loop from the first
measured state (computed inside the filter core, ``ekf.O_VY_MODEL`` / ``ekf.O_R_MODEL``).
Only epochs where the model was propagated (UPDATED or GATED) count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from transplanter_ident.ekf.layout import (
    O_CF,
    O_CF_STD,
    O_CR,
    O_CR_STD,
    O_OFFSET,
    O_R_MODEL,
    O_STATUS,
    O_VY_MODEL,
    StepStatus,
)
from transplanter_ident.epochs.epoch import EpochArrays

CSV_COLUMNS = ("t", "vx", "vy_meas", "r_meas", "delta", "vy_model", "r_model", "cf", "cr", "cf_std", "cr_std",
               "steering_offset", "valid")


@dataclass(frozen=True)
class Table2Row:
    """One row of the paper's Table 2."""

    label: str
    max_error_vy: float  # m/s
    max_error_r: float  # rad/s
    mean_error_vy: float
    mean_error_r: float
    epochs: int


@dataclass(frozen=True)
class StiffnessError:
    """Identified against true stiffness (simulated bags only), relative."""

    final_front: float
    final_rear: float
    mean_front: float
    mean_rear: float


def propagated(outputs: np.ndarray) -> np.ndarray:
    """Mask of epochs where the model was propagated."""
    status = outputs[:, O_STATUS].astype(int)
    return (status == StepStatus.UPDATED) | (status == StepStatus.GATED)


def table2_row(label: str, epochs: EpochArrays, outputs: np.ndarray) -> Table2Row:
    """Max and mean |model output - measurement| of vy and r."""
    mask = propagated(outputs)
    if not mask.any():
        nan = float("nan")
        return Table2Row(label, nan, nan, nan, nan, 0)
    err_vy = np.abs(outputs[mask, O_VY_MODEL] - epochs.lateral_velocity[mask])
    err_r = np.abs(outputs[mask, O_R_MODEL] - epochs.yaw_rate[mask])
    return Table2Row(label, float(err_vy.max()), float(err_r.max()), float(err_vy.mean()),
                     float(err_r.mean()), int(mask.sum()))


def format_table2(rows: list[Table2Row], title: str = "") -> str:
    """Table 2's layout: algorithm, max error vy [m/s], max error r [rad/s], mean errors."""
    head = f"{'Identification algorithm':<26}{'Max err vy':>12}{'Max err r':>12}{'Mean err vy':>13}{'Mean err r':>12}"
    units = f"{'':<26}{'[m/s]':>12}{'[rad/s]':>12}{'[m/s]':>13}{'[rad/s]':>12}"
    lines = [title] if title else []
    lines += [head, units]
    for row in rows:
        lines.append(f"{row.label:<26}{row.max_error_vy:>12.4g}{row.max_error_r:>12.4g}"
                     f"{row.mean_error_vy:>13.4g}{row.mean_error_r:>12.4g}")
    return "\n".join(lines)


def stiffness_error(outputs: np.ndarray, true_front: np.ndarray, true_rear: np.ndarray) -> StiffnessError:
    """Relative error of the identified stiffness against the truth at the same epochs."""
    rel_f = outputs[:, O_CF] / true_front - 1.0
    rel_r = outputs[:, O_CR] / true_rear - 1.0
    return StiffnessError(float(rel_f[-1]), float(rel_r[-1]), float(np.mean(np.abs(rel_f))),
                          float(np.mean(np.abs(rel_r))))


def csv_rows(epochs: EpochArrays, outputs: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The replay CSV's columns (CSV_COLUMNS) as an (N, 13) array; ``valid`` is the validity decision."""
    return np.column_stack([
        epochs.t, epochs.longitudinal_velocity, epochs.lateral_velocity, epochs.yaw_rate, epochs.steering,
        outputs[:, O_VY_MODEL], outputs[:, O_R_MODEL], outputs[:, O_CF], outputs[:, O_CR],
        outputs[:, O_CF_STD], outputs[:, O_CR_STD], outputs[:, O_OFFSET], np.asarray(valid, dtype=np.float64),
    ])
