"""The filter's measures of model errors the configuration left out, and the validity's two tests on them.

The kernel fits its innovations to the signature of each error (``ekf.adaptation.score_signature``;
DESIGN.md section 7): a GNSS delay left out of ``gnss.delay``, a tire relaxation length left out of
``vehicle.relaxation_length`` (``ekf.relaxation_signature``), and a steering gain left out of
``vehicle.steering_scale``, which a yaw inertia off in ``vehicle.iz`` resembles, and a heading
misaligned with the vehicle beyond ``vehicle.heading_offset`` (``ekf.heading_signature``). Each measure is a
value, its std, and the relative error of Cf and Cr per unit of it (the output columns of
:data:`MODEL_ERRORS`). An estimate is not valid when a measure is ``validity.max_<name>_sigmas`` std
from zero, or when its lower 1-sigma bound moves Cf or Cr more than ``validity.max_<name>_shift`` of
their reported std: at 2 m/s a stiffness moves ~2 % per ms of delay, so 10 ms not yet 3 std from
zero already moves the estimate several times its band. The same functions serve the online
monitor (floats) and the batch decision (arrays), so both decide alike.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from transplanter_ident.config.parameters import ValiditySettings
from transplanter_ident.ekf.layout import (
    O_DELAY_ESTIMATE,
    O_DELAY_ESTIMATE_STD,
    O_DELAY_SENS_F,
    O_DELAY_SENS_R,
    O_HEADING_ESTIMATE,
    O_HEADING_ESTIMATE_STD,
    O_HEADING_SENS_F,
    O_HEADING_SENS_R,
    O_PLAY_ESTIMATE,
    O_PLAY_ESTIMATE_STD,
    O_PLAY_SENS_F,
    O_PLAY_SENS_R,
    O_RELAXATION,
    O_RELAXATION_SENS_F,
    O_RELAXATION_SENS_R,
    O_RELAXATION_STD,
    O_SCALE_ESTIMATE,
    O_SCALE_ESTIMATE_STD,
    O_SCALE_SENS_F,
    O_SCALE_SENS_R,
)

#: one measure as the decision reads it: (value, std, relative error of Cf per unit, of Cr per unit)
Measure = tuple[float, float, float, float]


def measure_shows(value, std, sigmas: float):  # noqa: ANN001, ANN201 - floats or arrays alike
    """Whether a measured model error is ``sigmas`` std from zero (never before it is measured: std 0)."""
    return (std > 0.0) & (np.abs(value) > sigmas * std)


def measure_shift(value, std, sensitivity):  # noqa: ANN001, ANN201 - floats or arrays alike
    """The relative stiffness shift the measure implies at its lower 1-sigma bound: max(|value| - std, 0) x sensitivity."""
    return np.abs(sensitivity) * np.maximum(np.abs(value) - std, 0.0)


def measure_shifts(value, std, sensitivity, rel_std, max_shift: float):  # noqa: ANN001, ANN201 - floats or arrays alike
    """Whether the measure moves a stiffness (:func:`measure_shift`) beyond ``max_shift`` of its relative std."""
    return (std > 0.0) & (measure_shift(value, std, sensitivity) > max_shift * rel_std)


@dataclass(frozen=True)
class ModelError:
    """One measured model error: its settings' name, its output columns, and what the reason says."""

    name: str  # validity.max_<name>_sigmas and validity.max_<name>_shift
    columns: tuple[int, int, int, int]  # value, std, sensitivity of Cf, of Cr (layout.O_*)
    lagging: bool  # only a positive value counts (a tire's force lags its slip, never leads it)
    describe: Callable[[float, float], str]  # (value, std) -> what the innovations show
    advice: str  # what to set

    def thresholds(self, settings: ValiditySettings) -> tuple[float, float]:
        return getattr(settings, f"max_{self.name}_sigmas"), getattr(settings, f"max_{self.name}_shift")

    def fails(self, outputs: np.ndarray, front: np.ndarray, rear: np.ndarray,
              settings: ValiditySettings) -> np.ndarray:
        """Per epoch, whether the measure fails either test; ``front``, ``rear``: the relative std of Cf, Cr."""
        value, std, sens_f, sens_r = (outputs[:, c] for c in self.columns)
        value = np.maximum(value, 0.0) if self.lagging else value
        sigmas, max_shift = self.thresholds(settings)
        return (measure_shows(value, std, sigmas) | measure_shifts(value, std, sens_f, front, max_shift)
                | measure_shifts(value, std, sens_r, rear, max_shift))

    def reason(self, measure: Measure, relative: tuple[float, float], settings: ValiditySettings) -> str | None:
        """:meth:`fails` for one epoch: None when it passes, else the reason (with the shift it implies)."""
        value, std, *sensitivity = measure
        if not std > 0.0:  # not measured yet: passes (measure_shows, measure_shifts)
            return None
        value = max(value, 0.0) if self.lagging else value
        sigmas, max_shift = self.thresholds(settings)
        if measure_shows(value, std, sigmas):
            return f"the innovations show {self.describe(measure[0], std)}: {self.advice}"
        if any(measure_shifts(value, std, s, rel, max_shift) for s, rel in zip(sensitivity, relative, strict=True)):
            shift = max(float(measure_shift(value, std, s)) for s in sensitivity)
            return (f"the innovations show {self.describe(measure[0], std)}, which moves the stiffness by "
                    f"{100 * shift:.0f} % or more, beyond its band: {self.advice}")
        return None


MODEL_ERRORS = (
    ModelError("delay", (O_DELAY_ESTIMATE, O_DELAY_ESTIMATE_STD, O_DELAY_SENS_F, O_DELAY_SENS_R), False,
               lambda v, s: f"a GNSS delay of {1e3 * v:+.0f} +- {1e3 * s:.0f} ms not in gnss.delay (the stiffness "
                            "moves ~2 % per ms; or a high antenna on a body that rolls in turns, which looks alike)",
               "set gnss.delay, or tuner --estimate-delay"),
    ModelError("relaxation", (O_RELAXATION, O_RELAXATION_STD, O_RELAXATION_SENS_F, O_RELAXATION_SENS_R), True,
               lambda v, s: f"the tire force lagging the slip over {v:.2f} +- {s:.2f} m of travel more than "
                            "vehicle.relaxation_length (or a high antenna on a body that rolls, which looks alike)",
               "set vehicle.relaxation_length (the tire's relaxation length, of the order of its radius), or tuner "
               "--estimate-relaxation-length"),
    ModelError("steering_gain", (O_SCALE_ESTIMATE, O_SCALE_ESTIMATE_STD, O_SCALE_SENS_F, O_SCALE_SENS_R), False,
               lambda v, s: f"a steering gain {100 * v:+.1f} +- {100 * s:.1f} % off vehicle.steering_scale, or a yaw "
                            "inertia off vehicle.iz (the two look alike, as does a high antenna on a body that rolls)",
               "check vehicle.steering_scale and vehicle.iz, or tuner --estimate-steering-scale --estimate-yaw-inertia"),
    ModelError("heading", (O_HEADING_ESTIMATE, O_HEADING_ESTIMATE_STD, O_HEADING_SENS_F, O_HEADING_SENS_R), False,
               lambda v, s: f"a heading {math.degrees(v):+.2f} +- {math.degrees(s):.2f} deg off the vehicle's axis "
                            "beyond vehicle.heading_offset (a steady lateral velocity in proportion to the speed)",
               "add it to vehicle.heading_offset (the antenna baseline's yaw from the vehicle x axis)"),
    ModelError("steering_play", (O_PLAY_ESTIMATE, O_PLAY_ESTIMATE_STD, O_PLAY_SENS_F, O_PLAY_SENS_R), False,
               lambda v, s: f"a steering play of {math.degrees(v):+.3f} +- {math.degrees(s):.3f} deg not in "
                            "vehicle.steering_play (or a GNSS delay or a tire relaxation, which look alike; the "
                            "stiffness moves ~90 % per degree)",
               "set vehicle.steering_play (the steering linkage's free travel), or tuner --estimate-steering-play"),
)


#: the heading measure's std from zero beyond which the noise check's reason names it (a misaligned heading
#: leaves a steady vy that the noise measure takes for noise)
HEADING_NOISE_SIGMAS = 3.0


def misalignment_note(measures: tuple[Measure, ...]) -> str:
    """What the noise check's reason adds when the heading measure is HEADING_NOISE_SIGMAS std from zero."""
    for error, (value, std, *_) in zip(MODEL_ERRORS, measures, strict=False):
        if error.name == "heading" and std > 0.0 and abs(value) > HEADING_NOISE_SIGMAS * std:
            return f"; or {error.describe(value, std)}: {error.advice}"
    return ""


def measures_of(row: np.ndarray) -> tuple[Measure, ...]:
    """The :data:`MODEL_ERRORS` measures of one kernel output row, in that order."""
    return tuple(tuple(float(row[c]) for c in error.columns) for error in MODEL_ERRORS)  # type: ignore[misc]
