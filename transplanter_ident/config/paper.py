"""The paper's filter as options and noise: eq. (10) forward Euler, linear stiffness, z = [vy, r].

Li, Li & Guo (2020) with a trial-and-error Q/R and none of this package's additions (steering
offset state, linear-range check, change detection, noise adaptation, the speed's noise in Q,
re-linearised start), so
its results stay reproducible next to the defaults (``make demo``, test/test_identification.py).
"""

from __future__ import annotations

from transplanter_ident.config.parameters import FilterOptions, NoiseParams

PAPER_OPTIONS = FilterOptions(discretization="euler", stiffness_state="linear", measurement="yaw_rate",
                              process_noise_units="per_step", estimate_steering_offset=False,
                              estimate_heading_offset=False, estimate_steering_gain=False,
                              linear_range_check=False, change_detection=False, noise_adaptation=False,
                              noise_correlation=False, speed_noise=False,
                              relinearization_window=0.0)
PAPER_NOISE = NoiseParams(process_noise=(1.0e-4, 1.0e-4, 100.0, 100.0), measurement_noise=(4.0e-4, 1.0e-3),
                          initial_stiffness=(1000.0, 1000.0), initial_covariance=(1.0e-2, 1.0e-2, 1.0e6, 1.0e6))
