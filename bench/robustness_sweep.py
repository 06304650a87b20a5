"""How often the default estimator is confidently wrong, over drives unlike the ones it was tuned on.

Not a test (the tests assert each claim on its own scenario). Each row is one condition of the
project's simulator (test/drives.py: 2 m/s, +-15 deg sine steer of 6 s, 5 Hz GNSS, 120 s, unless the
row changes it), or the same drive from a simulator that shares no code with it
(test/independent_sim.py: the "independent sim" rows) over ``--seeds`` seeds, filtered with the default parameters (the vehicle's own
parameters where the row changes the vehicle; a row's ``filter_vehicle`` (``filter_noise``) configures the estimator with
other constants than the simulated vehicle's). From 30 s on it prints the share of epochs flagged
valid, the share of valid epochs whose +-2 sigma band misses the truth (Cf or Cr) or whose error
exceeds 10 %, the share of all epochs the band misses, and the final |error| (median, worst). A
valid estimate that the band misses is the worst output; an invalid one only costs availability.

Run: ``.venv/bin/python bench/robustness_sweep.py [--seeds 5] [--option NAME=VALUE] [--validity NAME=VALUE]
[--noise NAME=VALUE] [--stiffness-noise FACTOR] [ROW ...]``.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import (  # noqa: E402
    LATE_DROP,
    NOISY_GNSS,
    NOISY_GNSS_R,
    VARYING_SPEED,
    Run,
    drift,
    judged_run,
    sine_drive,
    step_change,
    with_body_roll,
    with_steering_drift,
)
from independent_sim import independent_drive  # noqa: E402
from test_validity import epochs_of  # noqa: E402

from transplanter_ident.config.parameters import (  # noqa: E402
    EstimatorConfig,
    FilterOptions,
    NoiseParams,
    ValiditySettings,
    VehicleParams,
)
from transplanter_ident.epochs.settings import steering_sensor  # noqa: E402
from transplanter_ident.sim.signals import (  # noqa: E402
    StiffnessSchedule,
    field_work,
    multisine_steering,
    sine_steering,
)
from transplanter_ident.sim.simulator import SensorNoise, SimResult, simulate  # noqa: E402

DEG = math.radians
NOISE = SensorNoise()
FIELD_STEERING, FIELD_SPEED = field_work()  # rows at 2 m/s, +-2 deg; U-turns at 1.2 m/s, 30 deg
SLOW_FIELD_STEERING, SLOW_FIELD_SPEED = field_work(row_speed=1.2, turn_speed=0.7)
ROWS: dict[str, dict[str, object]] = {
    "clean": {},
    "1 m/s": {"speed": 1.0},
    "3 m/s": {"speed": 3.0},
    "1 m/s, 10 min": {"speed": 1.0, "duration": 600.0},
    "1.2 m/s, 180 s": {"speed": 1.2, "duration": 180.0},
    "1.5 m/s, 180 s": {"speed": 1.5, "duration": 180.0},
    "speed 1.5-2.5 m/s (a 20 s sine)": {"speed_profile": lambda t: 2.0 + 0.5 * np.sin(2.0 * np.pi * t / 20.0)},
    "speed 1-3 m/s (a 30 s sine), 180 s": VARYING_SPEED,
    # the steering gain state's rows (session 35, with --option estimate_steering_gain=true): a varying speed sets a
    # gain apart from the stiffness and from a delay
    "speed 1-3 m/s, 180 s, steering gain +1 %": {**VARYING_SPEED, "steering_scale": 1.01},
    "speed 1-3 m/s, 180 s, GNSS 5 ms late, unset": {**VARYING_SPEED, "gnss_delay": 0.005},
    "speed 1-3 m/s, 180 s, GNSS 10 ms late, unset": {**VARYING_SPEED, "gnss_delay": 0.01},
    "2 m/s slowing to 0.2 m/s for 10 s every 40 s, 180 s": {  # the simulator cannot stop (eq. 3 at vx = 0)
        "speed_profile": lambda t: 0.2 + 1.8 * np.clip((30.0 - np.mod(t, 40.0)) / 2.0, 0.0, 1.0)
        * np.clip(np.mod(t, 40.0) / 2.0, 0.0, 1.0), "duration": 180.0},
    "sine +-5 deg": {"steering": sine_steering(DEG(5.0), 6.0)},
    "sine +-25 deg": {"steering": sine_steering(DEG(25.0), 6.0)},
    "sine period 3 s": {"steering": sine_steering(DEG(15.0), 3.0)},
    "sine period 12 s": {"steering": sine_steering(DEG(15.0), 12.0)},
    "path tracking +-1 deg": {"steering": sine_steering(DEG(1.0), 8.0)},
    "multisine +-10 deg": {"steering": multisine_steering(DEG(10.0), (3.0, 5.0, 9.0, 14.0), seed=3)},
    "GNSS noise 2x": {"noise": replace(NOISE, velocity=2.0 * NOISE.velocity, heading=2.0 * NOISE.heading)},
    "GNSS noise 3x": {"noise": replace(NOISE, velocity=3.0 * NOISE.velocity, heading=3.0 * NOISE.heading)},
    "velocity noise 3x": {"noise": replace(NOISE, velocity=3.0 * NOISE.velocity)},
    "heading noise 1 deg": {"noise": replace(NOISE, heading=DEG(1.0))},
    "steering noise 0.5 deg": {"noise": replace(NOISE, steering=DEG(0.5))},
    "GNSS errors correlated 0.2 s": {"noise": replace(NOISE, correlation_time=0.2)},
    "GNSS errors correlated 0.3 s": {"noise": replace(NOISE, correlation_time=0.3)},
    "GNSS errors correlated 0.5 s": {"noise": replace(NOISE, correlation_time=0.5)},
    "GNSS errors correlated 2 s": {"noise": replace(NOISE, correlation_time=2.0)},
    "GNSS 10 Hz, errors correlated 0.1 s": {"gnss_rate": 10.0, "noise": replace(NOISE, correlation_time=0.1)},
    "GNSS 10 Hz, errors correlated 0.5 s": {"gnss_rate": 10.0, "noise": replace(NOISE, correlation_time=0.5)},
    "GNSS 10 Hz": {"gnss_rate": 10.0},
    "GNSS 2 Hz": {"gnss_rate": 2.0},
    "GNSS 20 Hz": {"gnss_rate": 20.0},
    "GNSS 20 Hz, errors correlated 0.1 s": {"gnss_rate": 20.0, "noise": replace(NOISE, correlation_time=0.1)},
    "GNSS 1 Hz": {"gnss_rate": 1.0},
    "GNSS 4 Hz": {"gnss_rate": 4.0},
    "RTK float 60-90 s (GNSS noise x10), R not told": {"gnss_degraded": (60.0, 90.0, 10.0)},
    "steering at 10 Hz": {"steering_rate": 10.0},
    "steering offset drifting 1 deg over 60 s from 40 s": {"steering_drift": (DEG(1.0), 40.0, 100.0)},
    "steering offset jumping 1 deg at 60 s, 180 s": {"steering_drift": (DEG(1.0), 60.0, 60.0), "duration": 180.0},
    "steering offset 2 deg": {"steering_offset": DEG(2.0)},
    "steering gain +0.5 %": {"steering_scale": 1.005},
    "steering gain -0.5 %": {"steering_scale": 0.995},
    "steering gain +1 %": {"steering_scale": 1.01},
    "steering gain -1 %": {"steering_scale": 0.99},
    "steering gain +3 %": {"steering_scale": 1.03},
    "steering gain +3 %, vehicle.steering_scale set": {"steering_scale": 1.03,
                                                        "filter_vehicle": VehicleParams(steering_scale=1.0 / 1.03)},
    "steering play 0.1 deg, unset": {"steering_play": DEG(0.1)},
    "steering play -0.1 deg, unset": {"steering_play": DEG(-0.1)},
    "steering play 0.3 deg, unset": {"steering_play": DEG(0.3)},
    "steering play 0.5 deg, vehicle.steering_play set": {"steering_play": DEG(0.5),
                                                         "filter_vehicle": VehicleParams(steering_play=DEG(0.5))},
    "steering play -0.3 deg, vehicle.steering_play set": {"steering_play": DEG(-0.3),
                                                          "filter_vehicle": VehicleParams(steering_play=DEG(-0.3))},
    "steering play 0.5 deg, set, 1.5 m/s": {"steering_play": DEG(0.5), "speed": 1.5, "duration": 180.0,
                                            "filter_vehicle": VehicleParams(steering_play=DEG(0.5))},
    "configured mass +10 %": {"filter_vehicle": replace(VehicleParams(), mass=792.0)},
    "configured yaw inertia +20 %": {"filter_vehicle": replace(VehicleParams(), iz=1.2 * VehicleParams().yaw_inertia)},
    "configured CG 5 cm back (lf +5 cm)": {"filter_vehicle": replace(VehicleParams(), lf=0.75, lr=0.35)},
    "GNSS 3 ms late, unset": {"gnss_delay": 0.003},
    "GNSS 5 ms late, unset": {"gnss_delay": 0.005},
    "steering 5 ms late (GNSS -5 ms), unset": {"gnss_delay": -0.005},
    "GNSS 10 ms late, unset": {"gnss_delay": 0.01},
    "GNSS 20 ms late, unset": {"gnss_delay": 0.02},
    "tanh tire, mu 0.5": {"tire": "saturating", "friction": 0.5},
    "tanh tire, mu 0.2": {"tire": "saturating", "friction": 0.2},
    "tanh tire, mu 0.3 (wet)": {"tire": "saturating", "friction": 0.3},
    "tanh tire, mu 0.2, +-25 deg": {"tire": "saturating", "friction": 0.2, "steering": sine_steering(DEG(25.0), 6.0)},
    "tanh tire, mu 0.2, 3 m/s": {"tire": "saturating", "friction": 0.2, "speed": 3.0},
    "tanh tire, mu 0.2, 1.5 m/s, 180 s": {"tire": "saturating", "friction": 0.2, "speed": 1.5, "duration": 180.0},
    "tanh tire, mu 0.3, +-25 deg": {"tire": "saturating", "friction": 0.3, "steering": sine_steering(DEG(25.0), 6.0)},
    "tanh tire, mu 0.3, 3 m/s": {"tire": "saturating", "friction": 0.3, "speed": 3.0},
    "soft tires (3000/4000)": {"stiffness": StiffnessSchedule(front=(3000.0,), rear=(4000.0,))},
    "stiff tires (30000/40000)": {"stiffness": StiffnessSchedule(front=(30000.0,), rear=(40000.0,))},
    "cos(delta) in the truth, +-15 deg": {"small_angle": False},
    "cos(delta) in the truth, +-25 deg": {"small_angle": False, "steering": sine_steering(DEG(25.0), 6.0)},
    "cos(delta), tanh tire mu 0.5, 3 m/s": {"small_angle": False, "tire": "saturating", "friction": 0.5,
                                            "speed": 3.0},
    "tire relaxation 0.1 m": {"relaxation_length": 0.1},
    "tire relaxation 0.3 m": {"relaxation_length": 0.3},
    "tire relaxation 0.6 m": {"relaxation_length": 0.6},
    "tire relaxation 0.3 m, 1 m/s": {"relaxation_length": 0.3, "speed": 1.0},
    "tire relaxation 0.3 m, 3 m/s": {"relaxation_length": 0.3, "speed": 3.0},
    "tire relaxation 0.3 m, 1.5 m/s": {"relaxation_length": 0.3, "speed": 1.5},
    "tire relaxation 0.2 m, steering noise 0.5 deg": {"relaxation_length": 0.2,
                                                      "noise": replace(NOISE, steering=DEG(0.5))},
    "tire relaxation 0.2 m, multisine +-10 deg": {"relaxation_length": 0.2,
                                                  "steering": multisine_steering(DEG(10.0), (3.0, 5.0, 9.0, 14.0), seed=3)},
    "tire relaxation 0.1 m, vehicle.relaxation_length set": {"relaxation_length": 0.1,
                                                             "filter_vehicle": VehicleParams(relaxation_length=0.1)},
    "tire relaxation 0.3 m, vehicle.relaxation_length set": {"relaxation_length": 0.3,
                                                             "filter_vehicle": VehicleParams(relaxation_length=0.3)},
    "tire relaxation 0.3 m, vehicle.relaxation_length 0.32 m": {"relaxation_length": 0.3,
                                                                "filter_vehicle": VehicleParams(relaxation_length=0.32)},
    "tire relaxation 0.6 m, vehicle.relaxation_length set": {"relaxation_length": 0.6,
                                                             "filter_vehicle": VehicleParams(relaxation_length=0.6)},
    "body roll 0.25 deg per m/s^2, antenna 1.5 m up": {"body_roll": (DEG(0.25), 1.5)},
    "body roll 0.5 deg per m/s^2, antenna 1.5 m up": {"body_roll": (DEG(0.5), 1.5)},
    "body roll 1 deg per m/s^2, antenna 1.5 m up": {"body_roll": (DEG(1.0), 1.5)},
    "body roll 0.5 deg per m/s^2, antenna 1.5 m up, 1.5 m/s": {"body_roll": (DEG(0.5), 1.5), "speed": 1.5},
    "body roll 0.25 deg per m/s^2, antenna 1.5 m up, set": {
        "body_roll": (DEG(0.25), 1.5), "filter_vehicle": VehicleParams(antenna_height=1.5, roll_gradient=DEG(0.25))},
    "body roll 0.5 deg per m/s^2, antenna 1.5 m up, set": {
        "body_roll": (DEG(0.5), 1.5), "filter_vehicle": VehicleParams(antenna_height=1.5, roll_gradient=DEG(0.5))},
    "body roll 1 deg per m/s^2, antenna 1.5 m up, set": {
        "body_roll": (DEG(1.0), 1.5), "filter_vehicle": VehicleParams(antenna_height=1.5, roll_gradient=DEG(1.0))},
    "body roll 0.5 deg per m/s^2, antenna 1.5 m up, set 20 % low": {
        "body_roll": (DEG(0.5), 1.5), "filter_vehicle": VehicleParams(antenna_height=1.5, roll_gradient=DEG(0.4))},
    "body roll 0.5 deg per m/s^2, antenna 1.5 m up, 1.5 m/s, set": {
        "body_roll": (DEG(0.5), 1.5), "speed": 1.5,
        "filter_vehicle": VehicleParams(antenna_height=1.5, roll_gradient=DEG(0.5))},
    "side slope 2 deg": {"bank_angle": DEG(2.0)},
    "side slope 5 deg": {"bank_angle": DEG(5.0)},
    "heavier, longer vehicle": {"vehicle": VehicleParams(mass=1400.0, lf=0.9, lr=0.6)},
    "field work": {"duration": 300.0, "steering": FIELD_STEERING, "speed_profile": FIELD_SPEED},
    "field work, tanh tire mu 0.4": {"duration": 300.0, "steering": FIELD_STEERING, "speed_profile": FIELD_SPEED,
                                     "tire": "saturating", "friction": 0.4},
    "field work, rows at 1.2 m/s": {"duration": 300.0, "steering": SLOW_FIELD_STEERING,
                                    "speed_profile": SLOW_FIELD_SPEED},
    "stiffness drop -40 % at 75 s, 150 s": {"duration": 150.0, "stiffness": LATE_DROP},
    "stiffness drop -40 %, GNSS noise 2x, R set to it": {"duration": 150.0, "stiffness": LATE_DROP,
                                                         "noise": NOISY_GNSS, "filter_noise": NOISY_GNSS_R},
    "stiffness rising +30 % at 75 s, 180 s": {"duration": 180.0, "stiffness": step_change(0.3, 75.0)},
    "stiffness drop -20 % at 75 s, 180 s": {"duration": 180.0, "stiffness": step_change(-0.2, 75.0)},
    "stiffness drifting -40 % over 4 min": {"duration": 240.0, "stiffness": drift(-0.4, 1.0, 240.0)},
    "stiffness drifting -30 % from 30 to 180 s": {"duration": 180.0, "stiffness": drift(-0.3, 30.0, 180.0)},
    "stiffness drifting +30 % from 30 to 180 s": {"duration": 180.0, "stiffness": drift(0.3, 30.0, 180.0)},
    "stiffness drifting -20 % from 30 to 180 s": {"duration": 180.0, "stiffness": drift(-0.2, 30.0, 180.0)},
    "stiffness ramp +30 % over 40 s from 75 s, 180 s": {"duration": 180.0, "stiffness": drift(0.3, 75.0, 115.0)},
    "stiffness ramp +30 % over 60 s from 75 s, 180 s": {"duration": 180.0, "stiffness": drift(0.3, 75.0, 135.0)},
    "stiffness ramp -20 % over 60 s from 75 s, 180 s": {"duration": 180.0, "stiffness": drift(-0.2, 75.0, 135.0)},
    "stiffness ramp -40 % over 60 s from 75 s, 180 s": {"duration": 180.0, "stiffness": drift(-0.4, 75.0, 135.0)},
    "stiffness drifting -20 % over 4.5 min, 1.5 m/s": {"duration": 300.0, "speed": 1.5,
                                                       "stiffness": drift(-0.2, 30.0, 300.0)},
}
#: the same drive from a simulator that shares no code with the package's (test/independent_sim.py)
INDEPENDENT_ROWS: dict[str, dict[str, object]] = {
    "independent sim, Magic Formula mu 0.8": {},
    "independent sim, Magic Formula mu 0.3": {"friction": 0.3},
    "independent sim, Magic Formula mu 0.2": {"friction": 0.2},
    "independent sim, relaxation 0.3 m": {"relaxation_length": 0.3},
    # a new surface under all four wheels at 75 s: (time, stiffness factor, friction after)
    "independent sim, surface -30 % and mu 0.5 at 75 s, 180 s": {"duration": 180.0, "surface": (75.0, 0.7, 0.5)},
    "independent sim, surface +30 % at 75 s, 180 s": {"duration": 180.0, "surface": (75.0, 1.3, 0.8)},
    "independent sim, surface -40 % and mu 0.3 at 75 s, 180 s": {"duration": 180.0, "surface": (75.0, 0.6, 0.3)},
    "independent sim, relaxation 0.3 m, set": {"relaxation_length": 0.3,
                                               "filter_vehicle": VehicleParams(relaxation_length=0.3)},
}
ALL_ROWS = {**ROWS, **INDEPENDENT_ROWS}


def drive(name: str, seed: int) -> tuple[SimResult, VehicleParams]:
    """One seed of a row: (sensor samples and truth, the vehicle constants the estimator is configured with)."""
    overrides = dict(ALL_ROWS[name])
    told = overrides.pop("filter_vehicle", None)  # the estimator configured with other vehicle constants
    overrides.pop("filter_noise", None)  # the estimator's Q/R (row_figures)
    roll = overrides.pop("body_roll", None)  # (gain rad per m/s^2, antenna height m): drives.with_body_roll
    offset_drift = overrides.pop("steering_drift", None)  # (rad, start s, end s): drives.with_steering_drift
    if name in INDEPENDENT_ROWS:
        return independent_drive(seed, **overrides), told or VehicleParams()
    sim = sine_drive(seed, **overrides)
    result = simulate(sim)
    result = with_steering_drift(result, *offset_drift) if offset_drift else result
    return (with_body_roll(result, *roll) if roll else result), told or sim.vehicle


def with_stiffness_noise(noise: NoiseParams, factor: float) -> NoiseParams:
    """``noise`` with the stiffness random walks (the last two entries of ekf.process_noise) x ``factor``."""
    q = noise.process_noise
    return replace(noise, process_noise=(q[0], q[1], factor * q[2], factor * q[3]))


def judged_seed(name: str, seed: int, options: FilterOptions, settings: ValiditySettings | None = None,  # noqa: PLR0913
                stiffness_noise: float = 1.0, noise_fields: tuple[str, ...] = ()) -> tuple[Run, np.ndarray]:
    """One seed of a row filtered with ``options`` (and the row's vehicle and Q/R), and its valid flag per epoch."""
    result, told = drive(name, seed)
    noise = with_stiffness_noise(ALL_ROWS[name].get("filter_noise", NoiseParams()), stiffness_noise)
    config = EstimatorConfig(vehicle=told, options=options, noise=_with(noise, list(noise_fields)))
    return judged_run(result, config, lambda r: epochs_of(r, **steering_sensor(told)), settings)


def row_figures(name: str, seeds: int, options: FilterOptions, settings: ValiditySettings | None = None,  # noqa: PLR0913
                stiffness_noise: float = 1.0, noise_fields: tuple[str, ...] = ()) -> str:
    """One row's figures; ``noise_fields``: NoiseParams ``NAME=VALUE`` pairs set on the row's (``--noise``)."""
    shares, finals = [], []
    for seed in range(seeds):
        run, valid = judged_seed(name, seed, options, settings, stiffness_noise, noise_fields)
        after = run.t >= 30.0
        front, rear = run.covered()
        missed = ~(front & rear)
        error = np.maximum(np.abs(run.cf / run.true_cf - 1.0), np.abs(run.cr / run.true_cr - 1.0))
        kept = valid & after
        shares.append((np.mean(kept[after]), np.mean(missed[kept]) if kept.any() else math.nan,
                       np.mean(error[kept] > 0.10) if kept.any() else math.nan, np.mean(missed[after])))
        finals.extend(abs(e) for e in run.final_errors())
    a = np.array(shares)
    valid_share = np.mean(a[:, 0])
    missed_valid = f"{np.nanmean(a[:, 1]):6.3f}" if np.any(np.isfinite(a[:, 1])) else "     -"
    wrong_valid = f"{np.nanmean(a[:, 2]):6.3f}" if np.any(np.isfinite(a[:, 2])) else "     -"
    return (f"{valid_share:6.2f} {missed_valid} {wrong_valid} {np.mean(a[:, 3]):8.3f} "
            f"{100 * np.median(finals):8.1f} {100 * np.max(finals):6.1f}")


def _with(base: object, pairs: list[str]) -> object:
    """``base`` with the fields of ``NAME=VALUE`` pairs replaced (numbers; true/false for a flag)."""
    def value(name: str, text: str) -> float | bool:
        if isinstance(getattr(base, name, None), bool):
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"{name} is a flag: true or false, got {text!r}")
            return text.lower() in ("true", "1")
        return float(text)

    return replace(base, **{k: value(k, v) for k, v in (o.split("=", 1) for o in pairs)})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help="a FilterOptions field (number) to set, e.g. saturation_prior=0 (repeatable)")
    parser.add_argument("--validity", action="append", default=[], metavar="NAME=VALUE",
                        help="a ValiditySettings field (number) to set, e.g. max_autocorrelation=1 (repeatable)")
    parser.add_argument("--noise", action="append", default=[], metavar="NAME=VALUE",
                        help="a NoiseParams field (number) to set, e.g. steering_gain_initial_variance=1e-4 (repeatable)")
    parser.add_argument("--stiffness-noise", type=float, default=1.0, metavar="FACTOR",
                        help="the stiffness random walks (ekf.process_noise's last two entries) x FACTOR")
    parser.add_argument("rows", nargs="*", help="rows to run (default: all): " + ", ".join(ALL_ROWS).replace("%", "%%"))
    args = parser.parse_args(argv)
    unknown = [r for r in args.rows if r not in ALL_ROWS]
    if unknown or args.seeds < 1 or not args.stiffness_noise > 0.0:
        parser.error(f"unknown rows {unknown}" if unknown else "--seeds and --stiffness-noise must be positive")
    try:
        options = _with(FilterOptions(), args.option)
        settings = _with(ValiditySettings(), args.validity)
        _with(NoiseParams(), args.noise)
    except (TypeError, ValueError) as error:
        parser.error(f"--option/--validity/--noise: {error}")
    width = max(len(name) for name in ALL_ROWS)
    noise = f" stiffness random walk x{args.stiffness_noise:g}" if args.stiffness_noise != 1.0 else ""
    changed = "".join(" " + o for o in args.option + args.validity + args.noise)
    print(f"seeds 0-{args.seeds - 1}, from 30 s on; defaults{changed}{noise}")
    print(f"{'condition':<{width}}  valid  valid&missed  valid&err>10%  missed  final |err| median, worst [%]")
    for name in args.rows or ALL_ROWS:
        figures = row_figures(name, args.seeds, options, settings, args.stiffness_noise, tuple(args.noise))
        print(f"{name:<{width}}  {figures}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
