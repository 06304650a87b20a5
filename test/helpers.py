"""Shared helpers of the filter tests: simulator output -> time-ordered samples -> epochs."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

from transplanter_ident.config.paper import PAPER_NOISE, PAPER_OPTIONS
from transplanter_ident.config.parameters import EstimatorConfig, VehicleParams
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler, assemble
from transplanter_ident.epochs.epoch import Epoch, EpochArrays
from transplanter_ident.epochs.settings import course_geometry, steering_sensor
from transplanter_ident.sim.simulator import SensorNoise, SimConfig, SimResult, simulate

Sample = tuple[str, float, tuple[float, ...]]

# at equal stamps: steering first (it belongs to the interval the GNSS epoch closes), then velocity, heading
_TOPIC_ORDER = {"steering": 0, "velocity": 1, "heading": 2}

NO_NOISE = SensorNoise(velocity=0.0, heading=0.0, steering=0.0)

# The paper's Table 1 vehicle: m = 720 kg, lf = 0.7 m, lr = 0.4 m, Iz = 201.6 kg m^2, steering limit 20 deg.
TABLE1_VEHICLE = VehicleParams(mass=720.0, lf=0.7, lr=0.4, iz=201.6, max_steering=math.radians(20.0))


def sim_samples(result: SimResult, *, gnss_first: bool = False) -> list[Sample]:
    """The simulator's sensor streams as (topic, stamp, values) samples in time order.

    At equal stamps steering comes first, or last with ``gnss_first``.
    """
    order = dict(_TOPIC_ORDER, steering=3) if gnss_first else _TOPIC_ORDER
    keyed: list[tuple[float, int, Sample]] = []
    for t, (east, north), heading in zip(result.gnss_stamp, result.velocity_enu, result.heading, strict=True):
        keyed.append((float(t), order["velocity"], ("velocity", float(t), (float(east), float(north)))))
        keyed.append((float(t), order["heading"], ("heading", float(t), (float(heading),))))
    for t, angle in zip(result.steering_time, result.steering, strict=True):
        keyed.append((float(t), order["steering"], ("steering", float(t), (float(angle),))))
    keyed.sort(key=lambda item: (item[0], item[1]))
    return [sample for _, _, sample in keyed]


def assembler_settings(vehicle: VehicleParams, **overrides: object) -> AssemblerSettings:
    """AssemblerSettings with the vehicle's lever arm, heading offset, steering limit and steering sensor (scale, wheel)."""
    values = {"antenna_x": vehicle.antenna_x, "antenna_y": vehicle.antenna_y, "max_steering": vehicle.max_steering,
              "heading_offset": vehicle.heading_offset, **course_geometry(vehicle), **steering_sensor(vehicle)}
    values.update(overrides)
    return AssemblerSettings(**values)


def epochs_from_result(result: SimResult, vehicle: VehicleParams | None = None) -> list[Epoch]:
    """Feed the simulated streams through a fresh EpochAssembler; fails on any rejection."""
    assembler = EpochAssembler(assembler_settings(vehicle or VehicleParams()))
    epochs = assemble(assembler, sim_samples(result))
    rejections = assembler.drain_rejections()
    assert not rejections, f"clean simulated data was rejected: {rejections[:3]}"
    return epochs


def course_epochs(result: SimResult, vehicle: VehicleParams | None = None) -> EpochArrays:
    """A single antenna (``ekf.measurement: course``): the velocity and steering streams alone; fails on any rejection."""
    assembler = EpochAssembler(assembler_settings(vehicle or VehicleParams(), course=True))
    epochs = assemble(assembler, [s for s in sim_samples(result) if s[0] != "heading"])
    rejections = assembler.drain_rejections()
    assert not rejections, f"clean simulated data was rejected: {rejections[:3]}"
    return EpochArrays(epochs)


def heading_held(outputs: object, k: int) -> bool:
    """Whether epoch k's update held the estimated heading misalignment h (kernels.py: while the filter starts).

    Then vy's R and the innovations' correlation are not learnt. An update that releases h moves it, so a held
    one is an UPDATED epoch whose h (estimated: its std > 0) did not move.
    """
    from transplanter_ident.ekf.layout import O_HEADING_OFFSET, O_HEADING_OFFSET_STD, O_STATUS, StepStatus

    return bool(outputs[k, O_HEADING_OFFSET_STD] > 0.0 and int(outputs[k, O_STATUS]) == StepStatus.UPDATED
                and outputs[k, O_HEADING_OFFSET] == outputs[k - 1, O_HEADING_OFFSET])


def simulate_epochs(config: SimConfig) -> tuple[SimResult, EpochArrays]:
    """Simulate and assemble: (truth and samples, the filter's epochs)."""
    result = simulate(config)
    return result, EpochArrays(epochs_from_result(result, config.vehicle))


def paper_config(vehicle: VehicleParams = TABLE1_VEHICLE) -> EstimatorConfig:
    """The paper's filter: z = [vy, r], forward Euler, linear stiffness, Cf = Cr = 1000 N/rad to start (the demo's)."""
    return EstimatorConfig(vehicle=vehicle, options=PAPER_OPTIONS, noise=PAPER_NOISE)


def command(name: str) -> list[str]:
    """The console script in this venv if installed, else ``python -m``."""
    script = Path(sys.executable).parent / name
    return [str(script)] if script.exists() else [sys.executable, "-m", f"transplanter_ident.{name}"]


def run_command(name: str, *args: object) -> subprocess.CompletedProcess:
    """Run one of the package's executables from the repository root; output captured as text."""
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(root), env.get("PYTHONPATH", "")]))
    return subprocess.run(command(name) + [str(a) for a in args], capture_output=True, text=True, timeout=600,
                          env=env, cwd=root)


#: the tuner's flags for a quick Q/R search in the calibration tests (the calibration is what they check)
QUICK_TUNE = ("--particles", "4", "--iterations", "1", "--seed", "3", "--jobs", "1", "--no-epoch-cache",
              "--no-leave-one-out")


def replayed_errors(bag: object, params_file: object, capsys: object) -> tuple[tuple[float, float], tuple[float, float]]:
    """``replay``'s final Cf, Cr errors (%) of a simulated bag: (with ``params_file``, without it)."""
    from transplanter_ident.cli import replay

    out = []
    for extra in (["--params-file", str(params_file)], []):
        assert replay.main([str(bag), *extra]) == 0
        out.append(final_errors(capsys.readouterr().out))
    return out[0], out[1]


def final_errors(text: str) -> tuple[float, float]:
    """The final Cf, Cr errors (%) that ``replay`` prints against a simulated bag's truth."""
    match = re.search(r"final Cf ([-+\d.]+) %, Cr ([-+\d.]+) %", text)
    assert match, text
    return float(match.group(1)), float(match.group(2))
