"""One epoch's estimate as a Python type: the kernel's output row read back (layout.O_*)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from transplanter_ident.ekf.layout import (
    O_CF,
    O_CF_STD,
    O_CHANGE,
    O_CHANGE_EVIDENCE,
    O_CORRELATION,
    O_CR,
    O_CR_STD,
    O_DELAY_ESTIMATE,
    O_DELAY_ESTIMATE_STD,
    O_DELAY_SENS_F,
    O_DELAY_SENS_R,
    O_E0,
    O_E1,
    O_HEADING_ESTIMATE,
    O_HEADING_ESTIMATE_STD,
    O_HEADING_OFFSET,
    O_HEADING_OFFSET_STD,
    O_NIS,
    O_NOISE_CORRELATION_SECOND,
    O_NOISE_CORRELATION_VY,
    O_NOISE_SCALE_SECOND,
    O_NOISE_SCALE_VY,
    O_OFFSET,
    O_OFFSET_STD,
    O_PLAY_ESTIMATE,
    O_PLAY_ESTIMATE_STD,
    O_PLAY_SENS_F,
    O_PLAY_SENS_R,
    O_R,
    O_R_MODEL,
    O_RELAXATION,
    O_RELAXATION_SENS_F,
    O_RELAXATION_SENS_R,
    O_RELAXATION_STD,
    O_S00,
    O_S01,
    O_S11,
    O_SATURATION,
    O_SATURATION_STD,
    O_SCALE_ESTIMATE,
    O_SCALE_ESTIMATE_STD,
    O_SCALE_SENS_F,
    O_SCALE_SENS_R,
    O_STATUS,
    O_STEERING_GAIN,
    O_STEERING_GAIN_STD,
    O_TIRE_BIAS_F,
    O_TIRE_BIAS_R,
    O_VY,
    O_VY_MODEL,
    StepStatus,
)


@dataclass(frozen=True)
class Estimate:
    """What one epoch produced (Cf, Cr in N/rad per tire)."""

    t: float
    status: StepStatus
    lateral_velocity: float
    yaw_rate: float
    cornering_stiffness_front: float
    cornering_stiffness_rear: float
    cornering_stiffness_front_std: float
    cornering_stiffness_rear_std: float
    lateral_velocity_model: float
    yaw_rate_model: float
    innovation: tuple[float, float]
    innovation_covariance: tuple[float, float, float]  # S00, S01, S11
    normalized_innovation_squared: float
    steering_offset: float = 0.0  # rad, wheel = sensor - offset
    steering_offset_std: float = 0.0
    stiffness_correlation: float = 0.0  # of the two stiffness states (ln Cf, ln Cr in log mode)
    change_detected: bool = False  # the surface-change test fired at this epoch
    row: tuple[float, ...] = ()  # the whole kernel output row (layout.O_*)

    def _pair(self, first: int, second: int, default: float) -> tuple[float, float]:
        """Two slots of the output row (layout.O_*); ``default`` for a row from before they existed."""
        if len(self.row) <= max(first, second):
            return (default, default)
        return (self.row[first], self.row[second])

    @property
    def tire_bias(self) -> tuple[float, float]:
        """Relative bias of Cf, Cr on a tire saturating at ekf.min_friction (adaptation.py; held in the std)."""
        return self._pair(O_TIRE_BIAS_F, O_TIRE_BIAS_R, 0.0)

    @property
    def delay_sensitivity(self) -> tuple[float, float]:
        """Relative error of Cf, Cr per second of GNSS delay left out of gnss.delay (adaptation.py; first order)."""
        return self._pair(O_DELAY_SENS_F, O_DELAY_SENS_R, 0.0)

    @property
    def scale_sensitivity(self) -> tuple[float, float]:
        """Relative error of Cf, Cr per unit of steering gain left out (0 unless ekf.steering_scale_uncertainty)."""
        return self._pair(O_SCALE_SENS_F, O_SCALE_SENS_R, 0.0)

    @property
    def delay_estimate(self) -> tuple[float, float]:
        """(s, std s) of the GNSS delay left out of gnss.delay, as the innovations show it (std 0: not yet)."""
        return self._pair(O_DELAY_ESTIMATE, O_DELAY_ESTIMATE_STD, 0.0)

    @property
    def relaxation_estimate(self) -> tuple[float, float]:
        """(m, std m) of the tire relaxation length left out of vehicle.relaxation_length (std 0: not yet)."""
        return self._pair(O_RELAXATION, O_RELAXATION_STD, 0.0)

    @property
    def relaxation_sensitivity(self) -> tuple[float, float]:
        """Relative error of Cf, Cr per metre of tire relaxation length left out (relaxation_signature.py)."""
        return self._pair(O_RELAXATION_SENS_F, O_RELAXATION_SENS_R, 0.0)

    @property
    def steering_gain_estimate(self) -> tuple[float, float]:
        """(relative, std) of the steering gain left out of vehicle.steering_scale (or Iz's look-alike; std 0: not yet).

        The filter's state g while ``ekf.estimate_steering_gain``, else the innovations' measure of it.
        """
        state = self._pair(O_STEERING_GAIN, O_STEERING_GAIN_STD, 0.0)
        return state if state[1] > 0.0 else self._pair(O_SCALE_ESTIMATE, O_SCALE_ESTIMATE_STD, 0.0)

    @property
    def steering_play_estimate(self) -> tuple[float, float]:
        """(rad, std rad) of a steering play left out of vehicle.steering_play (play_signature.py; std 0: not yet)."""
        return self._pair(O_PLAY_ESTIMATE, O_PLAY_ESTIMATE_STD, 0.0)

    @property
    def play_sensitivity(self) -> tuple[float, float]:
        """Relative error of Cf, Cr per radian of steering play left out (play_signature.py)."""
        return self._pair(O_PLAY_SENS_F, O_PLAY_SENS_R, 0.0)

    @property
    def saturation(self) -> tuple[float, float]:
        """(a, std a): the tires' saturation the innovations show, 1 = a tire at ekf.min_friction (std 0: not yet)."""
        return self._pair(O_SATURATION, O_SATURATION_STD, 0.0)

    @property
    def heading_misalignment(self) -> tuple[float, float]:
        """(rad, std rad) of a heading misaligned with the vehicle beyond vehicle.heading_offset (std 0: not yet).

        The filter's state h while ``ekf.estimate_heading_offset``, else the innovations' measure of it.
        """
        state = self._pair(O_HEADING_OFFSET, O_HEADING_OFFSET_STD, 0.0)
        return state if state[1] > 0.0 else self._pair(O_HEADING_ESTIMATE, O_HEADING_ESTIMATE_STD, 0.0)

    @property
    def change_evidence(self) -> float:
        """The directional change test's CUSUM over its alarm level (0 .. 1; 0 when not recorded)."""
        return self.row[O_CHANGE_EVIDENCE] if len(self.row) > O_CHANGE_EVIDENCE else 0.0

    @property
    def noise_factors(self) -> tuple[float, float]:
        """The factors on R (vy, then psi or r) the innovations have shown (adaptation.noise_scale; 1: none)."""
        return self._pair(O_NOISE_SCALE_VY, O_NOISE_SCALE_SECOND, 1.0)

    @property
    def noise_correlations(self) -> tuple[float, float]:
        """The lag-1 autocorrelations (vy, then psi or r) that widen R (noise_correlation.py; 0: none)."""
        return self._pair(O_NOISE_CORRELATION_VY, O_NOISE_CORRELATION_SECOND, 0.0)

    @classmethod
    def from_row(cls, t: float, row: np.ndarray) -> Estimate:
        """Build from one kernel output row."""
        return cls(
            t=t,
            status=StepStatus(int(row[O_STATUS])),
            lateral_velocity=float(row[O_VY]),
            yaw_rate=float(row[O_R]),
            cornering_stiffness_front=float(row[O_CF]),
            cornering_stiffness_rear=float(row[O_CR]),
            cornering_stiffness_front_std=float(row[O_CF_STD]),
            cornering_stiffness_rear_std=float(row[O_CR_STD]),
            lateral_velocity_model=float(row[O_VY_MODEL]),
            yaw_rate_model=float(row[O_R_MODEL]),
            innovation=(float(row[O_E0]), float(row[O_E1])),
            innovation_covariance=(float(row[O_S00]), float(row[O_S01]), float(row[O_S11])),
            normalized_innovation_squared=float(row[O_NIS]),
            steering_offset=float(row[O_OFFSET]),
            steering_offset_std=float(row[O_OFFSET_STD]),
            stiffness_correlation=float(row[O_CORRELATION]),
            change_detected=bool(row[O_CHANGE] > 0.5),
            row=tuple(float(v) for v in row),
        )
