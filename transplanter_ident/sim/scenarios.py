"""Named simulation scenarios for ``simulate`` (data: a dict of name -> Scenario).

Each scenario builds a :class:`transplanter_ident.sim.SimConfig` for a given duration (None:
the scenario's own). Command-line overrides (speed, tire, rates, lever arm, seed) are applied
afterwards by :func:`build_config`. Stiffness values are N/rad per tire (the model's 2*C per axle).

* ``step20-ccw``: the paper's 20 degree step steer, counter-clockwise (left), ~1 m/s, asphalt;
* ``step30-cw``: a 30 degree step steer clockwise (right), ~1 m/s, in the field (softer tires);
* ``sine``: +-15 degree sine steer with a 6 s period at 2 m/s, asphalt (identifiable excitation);
* ``surface-change``: the sine excitation while the stiffness drops part-way (asphalt to field);
* ``multisine``: a multi-sine steer at 2 m/s (broadband excitation for tuning);
* ``field-work``: rows at 2 m/s with +-2 degree path-tracking corrections, and headland U-turns
  at 1.2 m/s with 30 degrees of steering (its own speed profile: no ``speed`` override).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

from transplanter_ident.config.parameters import VehicleParams
from transplanter_ident.sim.signals import (
    StiffnessSchedule,
    field_work,
    multisine_steering,
    sine_steering,
    step_steering,
)
from transplanter_ident.sim.simulator import SimConfig

ASPHALT = StiffnessSchedule(front=(8000.0,), rear=(10000.0,))  # sim default, paper-like magnitudes
FIELD = StiffnessSchedule(front=(3500.0,), rear=(4500.0,))  # paddy field: softer tires, lower stiffness
ASPHALT_FRICTION = 0.8
FIELD_FRICTION = 0.4
WET_FRICTION = 0.3  # a wet field: the tanh tire leaves its linear range at the sine's peaks


@dataclass(frozen=True)
class Scenario:
    """A named scenario: what it is and how to build its SimConfig for a duration."""

    description: str
    default_duration: float
    build: Callable[[float], SimConfig]


def _step20_ccw(duration: float) -> SimConfig:
    return SimConfig(duration=duration, speed=1.0, steering=step_steering(math.radians(20.0), start=2.0, ramp=0.5),
                     stiffness=ASPHALT, friction=ASPHALT_FRICTION)


def _step30_cw(duration: float) -> SimConfig:
    return SimConfig(duration=duration, speed=1.0,
                     steering=step_steering(-math.radians(30.0), start=2.0, ramp=0.75),
                     stiffness=FIELD, friction=FIELD_FRICTION)


def _sine(duration: float) -> SimConfig:
    return SimConfig(duration=duration, speed=2.0, steering=sine_steering(math.radians(15.0), 6.0),
                     stiffness=ASPHALT, friction=ASPHALT_FRICTION)


def _surface_change(duration: float) -> SimConfig:
    change = round(0.5 * duration, 3)
    stiffness = StiffnessSchedule(times=(0.0, change), front=(ASPHALT.front[0], FIELD.front[0]),
                                  rear=(ASPHALT.rear[0], FIELD.rear[0]), transition=2.0)
    return SimConfig(duration=duration, speed=2.0, steering=sine_steering(math.radians(15.0), 6.0),
                     stiffness=stiffness, friction=ASPHALT_FRICTION)


def _stiffness_drop(duration: float) -> SimConfig:
    change = round(0.5 * duration, 3)
    stiffness = StiffnessSchedule(times=(0.0, change), front=(ASPHALT.front[0], 0.6 * ASPHALT.front[0]),
                                  rear=(ASPHALT.rear[0], 0.6 * ASPHALT.rear[0]), transition=0.0)
    return SimConfig(duration=duration, speed=2.0, steering=sine_steering(math.radians(15.0), 6.0),
                     stiffness=stiffness, friction=ASPHALT_FRICTION)


def _wet_saturating(duration: float) -> SimConfig:
    return SimConfig(duration=duration, speed=2.0, steering=sine_steering(math.radians(15.0), 6.0),
                     stiffness=ASPHALT, tire="saturating", friction=WET_FRICTION)


def _multisine(duration: float) -> SimConfig:
    return SimConfig(duration=duration, speed=2.0,
                     steering=multisine_steering(math.radians(20.0), (2.5, 4.0, 7.0, 11.0), seed=1),
                     stiffness=ASPHALT, friction=ASPHALT_FRICTION)


def _field_work(duration: float) -> SimConfig:
    steering, speed = field_work()
    return SimConfig(duration=duration, steering=steering, speed_profile=speed, stiffness=ASPHALT,
                     friction=ASPHALT_FRICTION)


SCENARIOS: dict[str, Scenario] = {
    "step20-ccw": Scenario("20 deg step steer to the left (counter-clockwise circle), 1 m/s, asphalt",
                           90.0, _step20_ccw),
    "step30-cw": Scenario("30 deg step steer to the right (clockwise circle), 1 m/s, field (lower stiffness)",
                          90.0, _step30_cw),
    "sine": Scenario("+-15 deg sine steer, 6 s period, 2 m/s, asphalt (identification test)", 120.0, _sine),
    "surface-change": Scenario("sine steer at 2 m/s; stiffness drops from asphalt to field half-way (2 s blend)",
                               120.0, _surface_change),
    "stiffness-drop": Scenario("sine steer at 2 m/s; both stiffnesses drop 40 % at once half-way (a wet patch)",
                               150.0, _stiffness_drop),
    "wet-saturating": Scenario("sine steer at 2 m/s on a wet field (mu 0.3, tanh tire beyond its linear range "
                               "at the peaks)", 120.0, _wet_saturating),
    "multisine": Scenario("multi-sine steer (periods 2.5-11 s, |delta| <= 20 deg), 2 m/s, asphalt",
                          120.0, _multisine),
    "field-work": Scenario("rows at 2 m/s with +-2 deg path-tracking corrections, every 40 s a 10 s headland "
                           "U-turn at 1.2 m/s with 30 deg of steering, alternating left and right", 300.0,
                           _field_work),
}

DEFAULT_SCENARIO = "sine"


def build_config(name: str, *, duration: float | None = None, seed: int | None = None,
                 speed: float | None = None, tire: str | None = None, friction: float | None = None,
                 gnss_rate: float | None = None, steering_rate: float | None = None,
                 antenna_x: float | None = None, antenna_y: float | None = None,
                 vehicle: VehicleParams | None = None, steering_offset: float | None = None,
                 gnss_delay: float | None = None) -> SimConfig:
    """The SimConfig of scenario ``name`` with the given overrides (None keeps the scenario's value)."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}")
    scenario = SCENARIOS[name]
    config = scenario.build(scenario.default_duration if duration is None else float(duration))
    if speed is not None and config.speed_profile is not None:
        raise ValueError(f"scenario {name!r} drives its own speed profile; it takes no speed")
    changes: dict[str, object] = {}
    for key, value in (("seed", seed), ("speed", speed), ("tire", tire), ("friction", friction),
                       ("gnss_rate", gnss_rate), ("steering_rate", steering_rate),
                       ("steering_offset", steering_offset), ("gnss_delay", gnss_delay)):
        if value is not None:
            changes[key] = value
    base_vehicle = vehicle if vehicle is not None else config.vehicle
    lever = {k: float(v) for k, v in (("antenna_x", antenna_x), ("antenna_y", antenna_y)) if v is not None}
    if lever or vehicle is not None:
        changes["vehicle"] = replace(base_vehicle, **lever)
    return replace(config, **changes) if changes else config
