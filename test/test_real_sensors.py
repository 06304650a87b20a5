"""Right on real sensors (issue #10): offset, GNSS timing, arrival order, surface change, saturation, rate.

Every claim is measured on the project's simulator against its ground truth, over seeds 0-9, with the
default parameters (test/drives.py: 2 m/s, +-15 deg sine steer of 6 s, linear tires Cf = 8000 and
Cr = 10000 N/rad, 5 Hz GNSS, 50 Hz steering, the default sensor noise). Tolerances are the issue's.
Coverage is pooled over the seeds' epochs: the fraction whose +-2 sigma band holds the truth, for Cf
and for Cr (a calibrated Gaussian claims 95 %).
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import pytest
from drives import (
    NOISY_GNSS_R,
    TRUE_CF,
    TRUE_CR,
    median_and_worst,
    noisy_late_drop,
    pooled_coverage,
    run_drive,
    sine_drive,
)
from test_validity import epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, ValiditySettings
from transplanter_ident.ekf.layout import O_CF_STD
from transplanter_ident.evaluation.validity import decide_sequence
from transplanter_ident.sim.signals import StiffnessSchedule, step_steering
from transplanter_ident.sim.simulator import simulate

SEEDS = range(10)
PAPER_STEP = {"speed": 1.0, "steering": step_steering(math.radians(20.0), start=2.0, ramp=0.5), "duration": 90.0}


@functools.cache
def clean_runs(estimate_offset: bool = True) -> tuple:
    config = EstimatorConfig(options=FilterOptions(estimate_steering_offset=estimate_offset))
    return tuple(run_drive(sine_drive(seed), config) for seed in SEEDS)


@pytest.mark.parametrize("degrees", [0.5, 1.0])
def test_a_steering_offset_is_estimated_and_costs_no_accuracy(degrees: float) -> None:
    """Offsets of 0.5 and 1 deg: stiffness median |error| <= 2 %, worst <= 4 %; offset within 0.1 deg."""
    offset = math.radians(degrees)
    runs = [run_drive(sine_drive(seed, steering_offset=offset)) for seed in SEEDS]
    errors = [e for r in runs for e in r.final_errors()]
    median, worst = median_and_worst(errors)
    assert median <= 0.02 and worst <= 0.04, (median, worst)
    assert max(abs(r.offset - offset) for r in runs) <= math.radians(0.1)


def test_drives_without_an_offset_lose_no_accuracy_to_the_offset_state() -> None:
    """Median |error| with the offset state within 0.3 points of the filter without it (no offset present)."""
    with_state = median_and_worst([e for r in clean_runs(True) for e in r.final_errors()])[0]
    without = median_and_worst([e for r in clean_runs(False) for e in r.final_errors()])[0]
    assert with_state <= without + 0.003, (with_state, without)
    assert with_state <= 0.02


def test_an_80_ms_gnss_delay_is_removed_by_gnss_delay() -> None:
    """GNSS stamped 80 ms late, gnss.delay = 0.08: median |error| <= 2 % (unset, the estimate is far off)."""
    runs = [run_drive(sine_drive(seed, gnss_delay=0.08), gnss_delay=0.08) for seed in SEEDS]
    assert median_and_worst([e for r in runs for e in r.final_errors()])[0] <= 0.02
    unset = run_drive(sine_drive(0, gnss_delay=0.08))
    assert max(abs(e) for e in unset.final_errors()) > 0.10  # the test has teeth


@pytest.mark.parametrize("seed", SEEDS)
def test_the_arrival_order_of_gnss_and_steering_does_not_matter(seed: int) -> None:
    """GNSS logged before or after the same-instant steering sample: the same final stiffness within 0.1 %."""
    result = simulate(sine_drive(seed))
    before, after = run_drive(result, gnss_first=True), run_drive(result, gnss_first=False)
    assert before.cf[-1] == pytest.approx(after.cf[-1], rel=1e-3)
    assert before.cr[-1] == pytest.approx(after.cr[-1], rel=1e-3)


CHANGE = 60.0
DROP = StiffnessSchedule(times=(0.0, CHANGE), front=(TRUE_CF, 0.6 * TRUE_CF), rear=(TRUE_CR, 0.6 * TRUE_CR),
                         transition=0.0)


@functools.cache
def drop_runs() -> tuple:
    return tuple(run_drive(sine_drive(seed, duration=150.0, stiffness=DROP)) for seed in SEEDS)


def test_a_40_percent_stiffness_drop_is_tracked_fast_and_honestly() -> None:
    """2 m/s, 5 Hz, both stiffnesses drop 40 % at 60 s (asphalt to wet field).

    Median time back within 10 % <= 10 s and within 5 % <= 20 s; before the change median |error|
    <= 1.5 %; from 30 s on, +-2 sigma covers the truth in >= 90 % of epochs, the transient included.
    """
    runs = drop_runs()
    assert np.median([r.recovery_time(CHANGE, 0.10) for r in runs]) <= 10.0
    assert np.median([r.recovery_time(CHANGE, 0.05) for r in runs]) <= 20.0
    before = [float(r.cf[r.t < CHANGE][-1] / TRUE_CF - 1.0) for r in runs]
    before += [float(r.cr[r.t < CHANGE][-1] / TRUE_CR - 1.0) for r in runs]
    assert median_and_worst(before)[0] <= 0.015
    front, rear = pooled_coverage(list(runs), 30.0)
    assert front >= 0.90 and rear >= 0.90, (front, rear)


def noisy_drop_figures(options: FilterOptions) -> tuple[float, float, float]:
    """A drop at 75 s of 150 s, GNSS noise 2x and R set to it, seeds 0-9 (the robustness sweep's row).

    Returns the valid share from 30 s on, the share of those (pooled) missing Cf or Cr at +-2 sigma,
    and the worst final |error|.
    """
    config = EstimatorConfig(options=options, noise=NOISY_GNSS_R)
    valid_after, missed, finals = [], [], []
    for seed in range(10):
        result = simulate(noisy_late_drop(seed))
        run = run_drive(result, config)
        valid = decide_sequence(config, ValiditySettings(), epochs_of(result), run.outputs)
        front, rear = run.covered()
        after = run.t >= 30.0
        valid_after.append(valid[after])
        missed.append(~(front & rear)[valid & after])
        finals.extend(abs(e) for e in run.final_errors())
    kept = np.concatenate(missed)
    return float(np.mean(np.concatenate(valid_after))), float(np.mean(kept)) if len(kept) else 0.0, max(finals)


def test_a_drop_is_seen_through_noisier_sensors_whose_r_is_set() -> None:
    """A 40 % drop, GNSS noise 2x and R set to it (4x): valid >= 15 %, of which <= 5 % miss; worst final <= 6 %.

    Through such sensors the drop barely raises the innovations' variance, and the estimate follows
    it at the stiffness random walk's pace, valid and wrong, unless a test sees it. The directional
    test (ekf/change.py: the stiffness updates keep pushing one way) sees it on every seed within
    3-6 s. Measured: valid 28 %, none of those missed, worst final 4.1 %. The variance test alone
    (``ekf.change_scale`` 2, threshold 8) missed it on 2 of 10 seeds, worst final 14 %, once the
    speed's errors were taken as the two-sample means they are (ekf/update.py); with ``change_scale``
    4 and threshold 12 on 9 of 10.
    """
    valid, missed, worst = noisy_drop_figures(FilterOptions())
    assert valid >= 0.15 and missed <= 0.05 and worst <= 0.06, (valid, missed, worst)


def test_the_variance_test_alone_missed_the_drop_through_noisier_sensors() -> None:
    """The teeth of the test above: without the directional test (its threshold out of reach), a final error > 10 %."""
    _, _, worst = noisy_drop_figures(FilterOptions(change_shift_threshold=1.0e9, change_ramp_shift=0.0))
    assert worst > 0.10, worst


def test_constant_stiffness_raises_at_most_one_false_alarm_per_10_minutes() -> None:
    """10 seeds x 2 min of constant stiffness (20 min): at most 2 change alarms, none before the change."""
    alarms = sum(r.alarms_between(0.0, math.inf) for r in clean_runs(True))
    assert alarms <= 2
    assert sum(r.alarms_between(0.0, CHANGE) for r in drop_runs()) <= 1


WET = {"tire": "saturating", "friction": 0.3}


@functools.cache
def wet_runs(correction: bool = False, measured: bool = True) -> tuple:
    options = FilterOptions(saturation_correction=correction, saturation_prior=FilterOptions().saturation_prior
                            if measured else 0.0)
    return tuple(run_drive(sine_drive(seed, **WET), EstimatorConfig(options=options)) for seed in SEEDS)


def test_a_saturating_tire_is_identified_by_its_small_slip_stiffness() -> None:
    """A wet field (mu 0.3, tanh tire): the tires reach ~35 % of their friction limit at the sine's peaks.

    The linear tire then reads the secant stiffness, 1-7 % below the small-slip one; the saturation the
    innovations show (test_tire_saturation.py) takes part of that back (median |error| <= 5 %). The
    reported std holds what the data leave of the bias a tire saturating at ekf.min_friction (0.3) gives:
    +-2 sigma covers the truth in >= 90 % of the epochs after 30 s and >= 90 % of the final errors. Told
    the field's friction (ekf.saturation_correction), every seed's final error is <= 5 %. Beyond the
    linear range (3 m/s), every seed is within 5 % with the defaults: test_tire_saturation.py.
    """
    runs = wet_runs()
    errors = [e for r in runs for e in r.final_errors()]
    assert median_and_worst(errors)[0] <= 0.05
    front, rear = pooled_coverage(list(runs), 30.0)
    assert front >= 0.90 and rear >= 0.90, (front, rear)
    z = [abs(e) / std for r in runs for e, std in zip(r.final_errors(), r.final_rel_std(), strict=True)]
    assert np.mean(np.asarray(z) <= 2.0) >= 0.90, z
    corrected = [e for r in wet_runs(correction=True) for e in r.final_errors()]
    assert median_and_worst(corrected)[1] <= 0.05, corrected


def test_the_saturation_term_widens_the_std_and_leaves_the_estimate() -> None:
    """With the measure off (ekf.saturation_prior 0), ekf.min_friction adds the bias to the std only.

    The estimate is then bit-identical with the term off (min_friction 0); the bias it reports on the
    wet field is the one measured (the mean final error, within 1.5 points), and on grippier fields
    (mu 0.5, linear tires) it is an upper bound: every final error within +-2 sigma (defaults).
    """
    unmeasured = FilterOptions(saturation_prior=0.0)
    off = EstimatorConfig(options=replace(unmeasured, min_friction=0.0))
    result = simulate(sine_drive(0, **WET))
    with_term, without = run_drive(result, EstimatorConfig(options=unmeasured)), run_drive(result, off)
    np.testing.assert_array_equal(with_term.cf, without.cf)
    np.testing.assert_array_equal(with_term.cr, without.cr)
    # (to 1e-4: in the first seconds the identifiability guard's raise along a weak direction, which reads the
    # std and P's correlation, can give back a few 1e-5 of it)
    assert np.all(with_term.outputs[:, O_CF_STD] >= (1.0 - 1.0e-4) * without.outputs[:, O_CF_STD])
    runs = wet_runs(measured=False)
    for k in (0, 1):
        measured = -np.mean([r.final_errors()[k] for r in runs])
        reported = np.mean([r.final_tire_bias()[k] for r in runs])
        assert abs(measured - reported) <= 0.015, (k, measured, reported)
    grippy = [run_drive(sine_drive(seed, tire="saturating", friction=0.5)) for seed in SEEDS] + list(clean_runs(True))
    for r in grippy:
        assert all(abs(e) <= 2.0 * std for e, std in zip(r.final_errors(), r.final_rel_std(), strict=True))


@pytest.mark.parametrize("rate", [5.0, 10.0, 20.0, 100.0])
def test_one_parameter_file_fits_every_gnss_rate(rate: float) -> None:
    """The same drive and defaults at 5, 10, 20 and 100 Hz: median |error| <= 2 %, +-2 sigma coverage >= 90 %."""
    duration = 120.0 if rate <= 20.0 else 60.0
    runs = [run_drive(sine_drive(seed, gnss_rate=rate, steering_rate=max(50.0, rate), duration=duration))
            for seed in SEEDS]
    assert median_and_worst([e for r in runs for e in r.final_errors()])[0] <= 0.02
    front, rear = pooled_coverage(runs, 30.0)
    assert front >= 0.90 and rear >= 0.90, (front, rear)


def test_the_paper_slow_step_publishes_a_band_that_holds_the_truth() -> None:
    """The paper's test (1 m/s, 20 deg step held 90 s), 10 seeds: +-2 sigma covers Cf and Cr in >= 90 % after 30 s.

    Cf is hardly identifiable there (ekf/identifiability.py): the band along the weak direction is the prior's.
    """
    runs = [run_drive(sine_drive(seed, **PAPER_STEP)) for seed in SEEDS]
    front, rear = pooled_coverage(runs, 30.0)
    assert front >= 0.90 and rear >= 0.90, (front, rear)
