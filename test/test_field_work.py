"""Field work: rows with path-tracking corrections and headland U-turns at a lower speed (``ekf.speed_noise``).

The filter drives the model with the GNSS ground speed, which is as noisy as the velocity. In a
tight turn the yaw rate is nearly vx delta / L, so a 1 % speed error moves it by 1 %, and the
heading measures that sharply. Without the speed's noise in Q each headland turn moved the
estimate by 2-3 sigma while the std barely shrank. The scenario is ``simulate --scenario
field-work``: rows at 2 m/s with +-2 deg corrections, every 40 s a 10 s U-turn at 1.2 m/s with 30
deg of steering, 300 s, linear tires, the default sensor noise.

Measured over seeds 0-7 (this file's ``figures``), final |error| of Cf and Cr: with the speed's
noise (the default) median 2.2 %, worst 10.6 % (2.6 %, 12.4 % with the speed's errors taken as
white; 3.2 %, 11.8 % before a re-linearised pass's prior was bounded); without it 12.9 % and 27.5 %
(8.6 % and 46 % before the directional change test, whose alarms now let it recover in part).

The valid epochs were few (from 30 s on 5 % over seeds 0-7 here, 8 % over the robustness sweep's
16 seeds; none since the speed's errors are modelled as the two-sample means they are, ekf/update.py:
the Cf std after the turns stays at 5.2-6.3 %, just above validity.max_rel_std) and 18 % / 7.8 % of
them had Cf or Cr outside +-2 sigma (the sweep: 16 % before a
re-linearised pass's prior was bounded, ekf/relinearization.py: the first
row's straight start threw the stiffness, every new pass fell the same way, and the turns left Cf a
bias of -0.6 sigma). Not asserted: with two stiffnesses at +-2 sigma up to ~9 % may miss, and 16
seeds of so few valid epochs do not pin it.
"""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest
from drives import ValidityFigures, pooled_validity_figures, run_drive
from test_validity import epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions
from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.sim.simulator import SimResult, simulate

SEEDS = range(8)


@functools.cache
def field_drives() -> tuple[SimResult, ...]:
    return tuple(simulate(build_config("field-work", seed=seed)) for seed in SEEDS)


@functools.cache
def figures(speed_noise: bool) -> ValidityFigures:
    config = EstimatorConfig(options=replace(FilterOptions(), speed_noise=speed_noise))
    return pooled_validity_figures(((result, config) for result in field_drives()), epochs_of)


def test_with_the_speeds_noise_field_work_ends_close() -> None:
    """Final |error| of Cf and Cr over the seeds: median <= 5 %, worst <= 15 % (measured 2.2 %, 10.6 %)."""
    default = figures(True)
    assert default.median <= 0.05 and max(default.finals) <= 0.15, default


def test_without_the_speeds_noise_field_work_ends_far_off() -> None:
    """The failure the option fixes, so the test above can fail: median >= 8 %, worst >= 20 % (measured 12.9 %, 27.5 %)."""
    without = figures(False)
    assert without.median >= 0.08 and max(without.finals) >= 0.20, without


def test_the_band_is_centred_on_the_truth_after_the_turns() -> None:
    """Z = ln(estimate / truth) / relative std from 100 s on, averaged per drive, seeds 0-15: |mean| <= 0.4.

    Measured: Cf -0.18, Cr +0.06 (sd over the drives 0.99 / 0.69); with an unbounded prior for the
    re-linearised passes -0.58 / -0.30 (24 seeds: -0.06 / +0.10 against -0.35 / -0.16).
    """
    means = []
    for seed in range(16):
        run = run_drive(field_drives()[seed] if seed < len(SEEDS) else simulate(build_config("field-work", seed=seed)),
                        EstimatorConfig())
        o, late = run.outputs, run.t >= 100.0
        means.append([np.mean(np.log(o[late, value] / truth[late]) / (o[late, std] / o[late, value]))
                      for value, std, truth in ((O_CF, O_CF_STD, run.true_cf), (O_CR, O_CR_STD, run.true_cr))])
    assert np.all(np.abs(np.mean(means, axis=0)) <= 0.4), np.mean(means, axis=0)


def test_field_work_refuses_a_constant_speed_and_takes_a_duration() -> None:
    """The scenario drives its own speed profile: a --speed override is refused, a duration is not."""
    with pytest.raises(ValueError, match="own speed profile"):
        build_config("field-work", speed=1.0)
    assert build_config("field-work", duration=60.0).duration == 60.0
