"""The defaults hold what calibration leaves: 1 ms of timing and 0.3 % of steering gain, in a wider band.

config/estimator.yaml against config/exact_calibration.yaml layered over it (no timing or gain error held, max_rel_std
0.05: the defaults until session 38), as a user would load them. On the identification drive (seeds 0-5, from 30 s
on) with the steering sensor's gain 1 % low (a calibration a percent off, which the exact claim publishes as valid
and wrong):
- the valid epochs outside +-2 sigma: at most 0.7 x the exact claim's (measured 87.5 % -> 52.8 %; over 10 seeds
  82 -> 45 %, bench/robustness_sweep.py);
- the epochs valid and outside, of the whole drive after 30 s: at most 0.8 x (64.5 % -> 43.8 %; the valid share
  rises, 74 -> 83 %, as the wider band passes the delay and gain measures' shift tests more often).
On clean drives the defaults stay available (valid >= 85 %: 99.7 % measured, 97 % with the exact claim) and honest
(<= 5 % outside: none). The estimate itself is the same.
"""

from __future__ import annotations

import numpy as np
from drives import CONFIG_DIR, EXACT, Run, judged_figures, judged_run, sine_drive
from test_validity import epochs_of

from transplanter_ident.config.params_file import EstimatorParams, load_params
from transplanter_ident.ekf.layout import O_CF, O_CR
from transplanter_ident.sim.simulator import simulate

DEFAULTS = load_params([CONFIG_DIR / "estimator.yaml"])
SEEDS = range(6)


def judged(params: EstimatorParams, steering_scale: float) -> list[tuple[Run, np.ndarray]]:
    """The identification drives with that steering gain, filtered and decided with ``params``."""
    return [judged_run(simulate(sine_drive(seed, steering_scale=steering_scale)), params.config, epochs_of,
                       params.validity) for seed in SEEDS]


def test_the_defaults_hold_the_two_uncertainties_and_the_exact_claim_none() -> None:
    options = DEFAULTS.config.options
    assert (options.timing_stated, options.timing_uncertainty, options.steering_scale_uncertainty,
            DEFAULTS.validity.max_rel_std) == (False, 0.001, 0.003, 0.08)
    exact = EXACT.config.options
    assert (exact.timing_uncertainty, exact.steering_scale_uncertainty, EXACT.validity.max_rel_std) == (0.0, 0.0, 0.05)


def test_a_gain_a_percent_off_is_seldom_valid_and_wrong_with_the_defaults() -> None:
    exact, defaults = judged(EXACT, 0.99), judged(DEFAULTS, 0.99)
    before, after = judged_figures(exact), judged_figures(defaults)
    assert before.missed >= 0.3, before  # the exact claim is confidently wrong here (the row's reason to be)
    assert after.missed <= 0.7 * before.missed, (before, after)
    assert after.valid * after.missed <= 0.8 * before.valid * before.missed, (before, after)
    for (run_e, _), (run_d, _) in zip(exact, defaults, strict=True):  # the std and validity change, not the estimate
        np.testing.assert_array_equal(run_e.outputs[:, [O_CF, O_CR]], run_d.outputs[:, [O_CF, O_CR]])


def test_clean_drives_stay_available_and_honest_with_the_defaults() -> None:
    figures = judged_figures(judged(DEFAULTS, 1.0))
    assert figures.valid >= 0.85 and figures.missed <= 0.05, figures
