"""Field work: rows with path-tracking corrections and headland U-turns at a lower speed (``ekf.speed_noise``).

The filter drives the model with the GNSS ground speed, which is as noisy as the velocity. In a
tight turn the yaw rate is nearly vx delta / L, so a 1 % speed error moves it by 1 %, and the
heading measures that sharply. Without the speed's noise in Q each headland turn moved the
estimate by 2-3 sigma while the std barely shrank. The scenario is ``simulate --scenario
field-work``: rows at 2 m/s with +-2 deg corrections, every 40 s a 10 s U-turn at 1.2 m/s with 30
deg of steering, 300 s, linear tires, the default sensor noise.

Measured over seeds 0-7 (this file's ``figures``), final |error| of Cf and Cr: with the speed's
noise (the default) median 3.2 %, worst 11.8 %; without it 8.6 % and 46 %.

Not fixed, so not asserted: the valid epochs still miss. From 30 s on the estimate is valid in 6.5 %
of the epochs, and 16 % of those have Cf or Cr outside +-2 sigma (33 % over seeds 0-15; 31 % of the
33 % valid without the speed's noise). Over seeds 0-11 from 100 s on, Cf's z = error / std has a mean
of -0.8 and an sd of 1.3: the turns leave a bias in Cf that the band does not hold. It needs both
the velocity and the heading noise (each alone: z mean -0.1 / -0.7, sd 0.75 / 0.55); its cause is
open (README, "The defaults on drives unlike their own").
"""

from __future__ import annotations

import functools
from dataclasses import replace

import pytest
from drives import ValidityFigures, pooled_validity_figures
from test_validity import epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions
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
    """Final |error| of Cf and Cr over the seeds: median <= 5 %, worst <= 15 % (measured 3.2 %, 11.8 %)."""
    default = figures(True)
    assert default.median <= 0.05 and max(default.finals) <= 0.15, default


def test_without_the_speeds_noise_field_work_ends_far_off() -> None:
    """The failure the option fixes, so the test above can fail: the worst final |error| >= 30 % (measured 46 %)."""
    without = figures(False)
    assert max(without.finals) >= 0.30, without


def test_field_work_refuses_a_constant_speed_and_takes_a_duration() -> None:
    """The scenario drives its own speed profile: a --speed override is refused, a duration is not."""
    with pytest.raises(ValueError, match="own speed profile"):
        build_config("field-work", speed=1.0)
    assert build_config("field-work", duration=60.0).duration == 60.0
