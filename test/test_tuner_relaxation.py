"""``tuner --estimate-relaxation-length``: vehicle.relaxation_length from the filter's measure (tuning/relaxation.py).

The fixed point on synthetic measures (exact), then on simulated identification drives (2 m/s,
+-15 deg, 120 s) of tires relaxing over 0.3 m and of lag-free tires, three drives a set. Tolerances:
within 0.1 m of the truth and 3 of its std (measured on seeds 0-2 / 3-5 / 6-8: 0.315 / 0.258 / 0.353
m at 0.3, 0.024 / 0 / 0.087 m at 0, std 0.032-0.035 m). Through the CLI: OUT.yaml holds the length,
and a third drive replayed with it is right.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import pytest
from drives import sine_drive
from helpers import final_errors
from test_validity import epochs_of

from transplanter_ident.cli import replay, tuner
from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.config.params_file import load_params
from transplanter_ident.sim.simulator import simulate
from transplanter_ident.tuning.relaxation import MAX_PASSES, estimate_relaxation_length, pooled

TOLERANCE = 0.1  # m


def test_the_pooled_measure_weighs_each_bag_by_its_information() -> None:
    mean, std, bags = pooled([(0.2, 0.1), (0.5, 0.0), (0.4, 0.05)])  # the second bag measured nothing
    assert bags == 2
    assert mean == pytest.approx((0.2 / 0.01 + 0.4 / 0.0025) / (1 / 0.01 + 1 / 0.0025))
    assert std == pytest.approx((1 / 0.01 + 1 / 0.0025) ** -0.5)
    assert pooled([(0.3, 0.0)]) == (0.0, math.inf, 0)


def synthetic(truth: float, std: float = 0.05, gain: float = 1.0):  # noqa: ANN201 - a TaskMap
    """A TaskMap whose bags measure ``gain`` x (truth - configured) +- ``std`` (first order, as the filter's)."""

    def run(_fn, tasks):  # noqa: ANN001, ANN202
        return [(gain * (truth - config.vehicle.relaxation_length), std) for _epochs, config in tasks]

    return run


def test_the_fixed_point_finds_the_length_and_stops() -> None:
    bags = [None, None, None]
    exact = estimate_relaxation_length(bags, EstimatorConfig(), synthetic(0.3))
    assert exact.value == pytest.approx(0.3) and exact.passes == 2 and exact.bags == 3
    assert exact.std == pytest.approx(0.05 / math.sqrt(3))
    bent = estimate_relaxation_length(bags, EstimatorConfig(), synthetic(0.3, gain=0.7))  # a measure that falls short
    assert abs(bent.value - 0.3) <= 0.02 and bent.passes <= MAX_PASSES
    assert estimate_relaxation_length(bags, EstimatorConfig(), synthetic(-0.2)).value == 0.0  # a tire only lags
    nothing = estimate_relaxation_length(bags, EstimatorConfig(), lambda fn, tasks: [(0.0, 0.0)] * len(tasks))
    assert nothing.value == 0.0 and nothing.std == math.inf and nothing.bags == 0


@functools.cache
def drives(length: float, first: int) -> tuple:
    return tuple(epochs_of(simulate(sine_drive(seed, relaxation_length=length))) for seed in range(first, first + 3))


@pytest.mark.parametrize(("length", "first"), [(0.3, 0), (0.3, 6), (0.0, 3)])
def test_the_length_is_found_on_three_drives(length: float, first: int) -> None:
    estimate = estimate_relaxation_length(list(drives(length, first)), EstimatorConfig())
    print(f"\n{length} m, seeds {first}-{first + 2}: {estimate.format()}")
    assert estimate.bags == 3 and 0.02 <= estimate.std <= 0.06
    assert abs(estimate.value - length) <= TOLERANCE and abs(estimate.value - length) <= 3.0 * estimate.std


def test_cli_writes_the_length_and_replay_with_it_is_right(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """Two 0.3 m drives: OUT.yaml holds the length and its std; a third drive replayed with it is closer to the truth.

    Required: within 0.1 m, and the final |error| of Cf and Cr at most half of that without it.
    """
    from transplanter_ident.bags import write_sim_bag

    paths = []
    for seed in (0, 1, 2):
        paths.append(tmp_path / f"drive{seed}")
        write_sim_bag(simulate(sine_drive(seed, relaxation_length=0.3)), paths[-1])
    out = tmp_path / "tuned.yaml"
    assert tuner.main([str(paths[0]), str(paths[1]), "-o", str(out), "--estimate-relaxation-length", "--particles",
                       "4", "--iterations", "1", "--seed", "3", "--jobs", "1", "--no-epoch-cache",
                       "--no-leave-one-out"]) == 0
    printed = capsys.readouterr()
    assert "tuner: vehicle.relaxation_length: " in printed.err
    assert "# estimated vehicle.relaxation_length:" in out.read_text()
    tuned = load_params([str(out)]).config
    length, uncertainty = tuned.vehicle.relaxation_length, tuned.options.relaxation_uncertainty
    assert abs(length - 0.3) <= TOLERANCE and abs(length - 0.3) <= 3.0 * uncertainty, (length, uncertainty)
    assert 0.02 <= uncertainty <= 0.08 and "# estimated ekf.relaxation_uncertainty:" in out.read_text()

    assert replay.main([str(paths[2])]) == 0
    unset = final_errors(capsys.readouterr().out)
    assert replay.main([str(paths[2]), "--params-file", str(out)]) == 0
    printed = capsys.readouterr().out
    calibrated = final_errors(printed)
    print(f"\nlength {length:.3f} +- {uncertainty:.3f} m; replayed final errors {calibrated} against {unset} unset; "
          f"{next(line for line in printed.splitlines() if line.startswith('Identified'))}")
    assert max(map(abs, calibrated)) <= 0.5 * max(map(abs, unset)), (calibrated, unset)
