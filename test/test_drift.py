"""The validity's drift test (evaluation/validity.py): a stiffness that drifts, rather than steps.

A surface or load that changes over minutes moves the stiffness faster than the random walk
(``ekf.process_noise``) lets the estimate follow, and no change alarm fires: on the 2 m/s
identification drive with both stiffnesses drifting 40 % down over 4 min, the estimate lagged 8-10 %
behind while valid in 92 % of the epochs after 30 s, 38 % of those outside +-2 sigma (10 seeds;
``bench/robustness_sweep.py "stiffness drifting -40 % over 4 min"`` with ``--validity drift_window=0``).
The drift test sums the normalised stiffness updates (layout.O_UPDATE_F/R) over
``validity.drift_window`` and calls that drift when they keep pushing one way. A surface that changes
over a minute, too slowly for the step's change test, is the filter's slow change test's
(``ekf.change_ramp_shift``, ekf/change.py): its alarm lets the estimate catch up.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from drives import LATE_DROP, Run, drift, judged_figures, run_drive, sine_drive
from test_validity import CONFIG, SETTINGS, epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, ValiditySettings
from transplanter_ident.ekf.layout import O_CHANGE, O_STATUS, O_UPDATE_F, O_UPDATE_R, StepStatus
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.validity import decide_sequence, monitor_for, sample_of
from transplanter_ident.sim.simulator import simulate

SEEDS = range(8)
DRIFT = {"duration": 240.0, "stiffness": drift(-0.4, 1.0, 240.0)}
#: a surface changing over a minute: both stiffnesses +30 % (firmer) or -20 % (wetter) from 75 to 135 s
RAMPS = {"ramp up": {"duration": 180.0, "stiffness": drift(0.3, 75.0, 135.0)},
         "ramp down": {"duration": 180.0, "stiffness": drift(-0.2, 75.0, 135.0)}}
OFF = dataclasses.replace(SETTINGS, drift_window=0.0)


#: the filter without the slow change's test (ekf.change_ramp_shift 0), whose alarms catch part of a drift
STEP_TEST_ONLY = dataclasses.replace(CONFIG, options=FilterOptions(change_ramp_shift=0.0))


@functools.cache
def runs(name: str, config: EstimatorConfig = CONFIG) -> tuple[tuple[Run, EpochArrays], ...]:
    overrides = {"drift": DRIFT, "clean": {}, "drop": {"duration": 150.0, "stiffness": LATE_DROP}, **RAMPS}[name]
    out = []
    for seed in SEEDS:
        result = simulate(sine_drive(seed, **overrides))
        out.append((run_drive(result, config), epochs_of(result)))
    return tuple(out)


def missed_and_valid(name: str, settings: ValiditySettings, config: EstimatorConfig = CONFIG) -> tuple[float, float]:
    """(share of the valid epochs after 30 s that +-2 sigma misses (Cf or Cr), valid share after 30 s), pooled."""
    figures = judged_figures((run, decide_sequence(config, settings, epochs, run.outputs))
                             for run, epochs in runs(name, config))
    return figures.missed, figures.valid


def test_a_drifting_stiffness_is_flagged_and_named() -> None:
    """-40 % over 4 min at 2 m/s, 8 seeds: the band misses less, and the reason says why.

    The filter without the slow change's test (whose alarms catch part of the drift): in <= 15 % of the
    valid epochs after 30 s and <= 1/3 of what it missed without the drift test, which misses >= 15 %
    (measured 1.4 % against 18.1 %; valid 30 % against 87 %; with the band of config/exact_calibration.yaml,
    the defaults until session 38, 10.9 % against 45.4 %). With the defaults (both): <= 15 % (measured 1.9 %;
    11.9 % with the exact claim). 15 % is what the tests achieved with the narrower band, not what a band
    promises (~5-9 %); raising the stiffness random walk is the user's lever.
    """
    with_test, valid_with = missed_and_valid("drift", SETTINGS, STEP_TEST_ONLY)
    without, valid_without = missed_and_valid("drift", OFF, STEP_TEST_ONLY)
    assert without >= 0.15, without  # the drive shows the failure the test is for
    assert with_test <= 0.15 and with_test <= without / 3.0, (with_test, without)
    assert valid_with < valid_without
    defaults, _ = missed_and_valid("drift", SETTINGS)
    assert defaults <= 0.15, defaults
    run, epochs = runs("drift", STEP_TEST_ONLY)[0]
    monitor = monitor_for(STEP_TEST_ONLY, SETTINGS)
    reasons = {r for i in range(len(epochs)) for r in monitor.step(sample_of(epochs[i], run.outputs[i])).reasons}
    assert any("keeps moving down" in r and "ekf.process_noise" in r for r in reasons), reasons


def final_errors(name: str, config: EstimatorConfig) -> np.ndarray:
    """Per seed, the worse of Cf's and Cr's |relative error| at the drive's end."""
    return np.array([max(abs(e) for e in run.final_errors()) for run, _ in runs(name, config)])


def test_a_surface_changing_over_a_minute_raises_the_slow_change_alarm() -> None:
    """+30 % and -20 % over 60 s from 75 s (180 s drives, 8 seeds): the slow change's test catches the lag.

    The step's test alone lets the estimate lag by several std (its updates push by ~0.3 std each: no
    alarm) while valid. Required, pooled over the seeds, the valid epochs after 30 s outside +-2 sigma:
    with the slow change's test <= 18 % and <= 0.6 x without it (measured: up 7.6 % against 20.4 %,
    down 2.4 % against 9.5 %; with the exact claim's band, config/exact_calibration.yaml, 14.8 % against
    28.6 % and 8.2 % against 20.7 %; without it >= 8 %, the failure shown); an alarm after 75 s on >= 6 of
    the 8 drives; and the median final error at most half of the step test's alone (2.9 / 6.9, 1.2 / 2.8 %).
    """
    for name in RAMPS:
        with_ramp, _ = missed_and_valid(name, SETTINGS)
        step_only, _ = missed_and_valid(name, SETTINGS, STEP_TEST_ONLY)
        assert step_only >= 0.08, (name, step_only)
        assert with_ramp <= 0.18 and with_ramp <= 0.6 * step_only, (name, with_ramp, step_only)
        alarmed = sum(bool(np.any((run.outputs[:, O_CHANGE] > 0.0) & (run.t > 75.0))) for run, _ in runs(name))
        assert alarmed >= 6, (name, alarmed)
        finals, finals_step_only = final_errors(name, CONFIG), final_errors(name, STEP_TEST_ONLY)
        assert np.median(finals) <= 0.5 * np.median(finals_step_only), (name, finals, finals_step_only)


def test_steady_and_stepping_stiffness_lose_nothing() -> None:
    """Clean drives and a 40 % drop at 75 s (whose alarm restarts the sums), 8 seeds each: valid as often.

    Required: the valid share with the drift test within 1 point of the share without (measured: equal,
    98.8 % and 83.7 %).
    """
    for name in ("clean", "drop"):
        _, valid_with = missed_and_valid(name, SETTINGS)
        _, valid_without = missed_and_valid(name, OFF)
        assert valid_with >= valid_without - 0.01, (name, valid_with, valid_without)


def test_the_updates_restart_at_a_change_alarm() -> None:
    """O_UPDATE_F/R: nonzero on updated epochs, 0 at an alarm and while its raised random walk lasts."""
    hold = FilterOptions().change_hold
    alarms = 0
    for run, _ in runs("drop"):
        o, t = run.outputs, run.t
        updates = o[:, [O_UPDATE_F, O_UPDATE_R]]
        for a in np.flatnonzero(o[:, O_CHANGE] > 0.0):
            alarms += 1
            assert not updates[(t >= t[a]) & (t <= t[a] + hold)].any()
        updated = o[:, O_STATUS] == int(StepStatus.UPDATED)
        assert np.mean(updates[updated, 0] != 0.0) > 0.9
    assert alarms >= len(SEEDS)
