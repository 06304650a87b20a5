"""Figures of ``tuner --estimate-steering-scale --estimate-yaw-inertia``: the joint (scale, Iz) search on simulated drives.

Not a test (test/test_tuner_yaw_inertia.py checks one set through the CLI). Each set is three
identification drives (test/drives.py: 2 m/s, +-15 deg sine of 6 s, 120 s) of one vehicle whose
steering sensor reads the wheel angle x a gain drawn from 0.98-1.02 and whose yaw inertia is drawn
from 0.75-1.4 x the configured m lf lr (paper eq. 5); set i uses drive seeds 3i .. 3i + 2 and draws
its truth with ``numpy.random.default_rng(1000 + i)``. The search runs as the tuner runs it
(:func:`transplanter_ident.tuning.scale_and_inertia.search_scale_and_inertia`, eq. 21 locating, the NLL's
surface giving the std): per set the truth, the estimate, its std and the error in std (z); then,
per factor, the rms of z, the worst |z|, how often +-2 std covers the truth (0.95 claimed), and the
same for the NLL's own minimum (the estimate before, which leaned along the ridge).

``--inertia-only``: the sensor right (gain 1), Iz alone searched as ``tuner --estimate-yaw-inertia`` does
(:mod:`transplanter_ident.tuning.yaw_inertia`, the NLL's minimum and curvature); set i then uses drive seeds
100 + 3i .. 102 + 3i and ``default_rng(2000 + i)``. ``--scale-only``: Iz right (m lf lr), the gain alone searched
as ``tuner --estimate-steering-scale`` does (:mod:`transplanter_ident.tuning.steering_scale`); drive seeds
200 + 3i .. 202 + 3i, ``default_rng(3000 + i)``.

Run: ``.venv/bin/python bench/joint_calibration_figures.py [--sets 20] [--first 0] [--jobs 2] [--inertia-only |
--scale-only]`` (about 70 s per set on one core; 8 s with either of those).
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from transplanter_ident.tuning.scale_and_inertia import STD_INFLATION  # noqa: E402

GAINS, INERTIAS = (0.98, 1.02), (0.75, 1.4)


def three_drives(first_seed: int, inertia: float, gain: float) -> list:
    """The epochs of three identification drives (seeds from ``first_seed``): Iz x ``inertia``, the sensor x ``gain``."""
    from drives import sine_drive
    from test_validity import epochs_of

    from transplanter_ident.config.parameters import VehicleParams
    from transplanter_ident.sim.simulator import simulate

    vehicle = replace(VehicleParams(), iz=inertia * VehicleParams().yaw_inertia)
    return [epochs_of(simulate(sine_drive(seed, vehicle=vehicle, steering_scale=gain)))
            for seed in range(first_seed, first_seed + 3)]


def remembered(objective):  # noqa: ANN001, ANN201
    """``objective`` of a batch of pairs, each pair evaluated once (the bench searches the NLL's grid twice)."""
    seen: dict = {}

    def of(pairs):  # noqa: ANN001, ANN202
        todo = [p for p in pairs if p not in seen]
        if todo:
            seen.update(zip(todo, objective(todo), strict=True))
        return [seen[p] for p in pairs]

    return of


def one_set(index: int) -> dict:
    """The truth and the joint search's results on set ``index`` (factors on the configured values)."""
    from transplanter_ident.config.parameters import EstimatorConfig
    from transplanter_ident.tuning import scale_and_inertia as joint

    rng = np.random.default_rng(1000 + index)
    gain, inertia = float(rng.uniform(*GAINS)), float(rng.uniform(*INERTIAS))
    bags = three_drives(3 * index, inertia, gain)
    config, count = EstimatorConfig(), sum(len(b) for b in bags)
    locate = joint.pooled_pair_objective(bags, config, "mae")
    likelihood = remembered(joint.pooled_pair_objective(bags, config, "nll"))
    scale, iz = joint.search_scale_and_inertia(locate, (1.0, 1.0), likelihood, count)
    peak, _, surface = joint.grid_search_pair(likelihood)
    nll_vertex, _ = joint.fit_surface(surface, peak)
    return {"index": index, "truth": (1.0 / gain, inertia), "estimate": (scale.value, iz.value),
            "std": (scale.std, iz.std), "nll": nll_vertex}


def one_factor_set(index: int, factor: str) -> dict:
    """The truth and a one-dimensional search's result on set ``index``: ``factor`` "iz" or "scale", the other right."""
    from transplanter_ident.config.parameters import EstimatorConfig, VehicleParams
    from transplanter_ident.tuning import steering_scale, yaw_inertia

    inertia_run = factor == "iz"
    rng = np.random.default_rng((2000 if inertia_run else 3000) + index)
    truth = float(rng.uniform(*(INERTIAS if inertia_run else GAINS)))
    first = (100 if inertia_run else 200) + 3 * index
    bags = three_drives(first, truth, 1.0) if inertia_run else three_drives(first, 1.0, truth)
    config, count = EstimatorConfig(), sum(len(b) for b in bags)
    if inertia_run:
        found = yaw_inertia.with_std(yaw_inertia.search_yaw_inertia(
            yaw_inertia.pooled_inertia_objective(bags, config, "nll"), VehicleParams().yaw_inertia), count)
    else:
        found = steering_scale.with_std(steering_scale.search_steering_scale(
            steering_scale.pooled_scale_objective(bags, config, "nll"), 1.0), count)
        truth = 1.0 / truth  # the scale that undoes the gain
    pair = (1.0, truth), (1.0, found.factor), (math.inf, found.std / found.configured)
    if not inertia_run:
        pair = tuple(p[::-1] for p in pair)
    return {"index": index, "truth": pair[0], "estimate": pair[1], "std": pair[2]}


def summary(rows: list[dict], key: str) -> str:
    """The rms z, worst |z| and the 2-std coverage of ``key`` (estimate or nll) over the sets, per factor."""
    parts = []
    for i, name in enumerate(("scale", "Iz")):
        z = np.array([(r[key][i] - r["truth"][i]) / r["std"][i] for r in rows if math.isfinite(r["std"][i])])
        if not len(z):
            parts.append(f"{name}: no finite std")
            continue
        parts.append(f"{name}: rms z {math.sqrt(float(np.mean(z ** 2))):.2f}, worst |z| {np.max(np.abs(z)):.2f}, "
                     f"within 2 std {np.mean(np.abs(z) <= 2.0):.0%} of {len(z)}")
    return "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", type=int, default=20)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=2)
    alone = parser.add_mutually_exclusive_group()
    alone.add_argument("--inertia-only", action="store_true")
    alone.add_argument("--scale-only", action="store_true")
    args = parser.parse_args(argv)
    indices = range(args.first, args.first + args.sets)
    alone = "iz" if args.inertia_only else "scale" if args.scale_only else None
    if alone:
        k, name = (1, "Iz") if alone == "iz" else (0, "scale")
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            rows = list(pool.map(one_factor_set, indices, [alone] * len(indices)))
        for row in rows:
            truth, found, std = row["truth"][k], row["estimate"][k], row["std"][k]
            print(f"set {row['index']:2d}: truth {name} {truth:.4f} x; estimate {found:.4f} +- {std:.4f} x "
                  f"(z {(found - truth) / std:+.2f})")
        errors = [abs(r["estimate"][k] / r["truth"][k] - 1.0) for r in rows]
        print(f"{name} alone (the NLL's minimum and curvature): {summary(rows, 'estimate').split('; ')[k]}; "
              f"median |error| {100 * float(np.median(errors)):.2f} %, worst {100 * max(errors):.2f} %")
        return 0
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        rows = []
        for row in pool.map(one_set, indices):
            rows.append(row)
            (ts, ti), (es, ei), (ss, si), (ns, ni) = row["truth"], row["estimate"], row["std"], row["nll"]
            print(f"set {row['index']:2d}: truth scale {ts:.4f} Iz {ti:.3f} x; estimate {es:.4f} +- {ss:.4f}, "
                  f"{ei:.3f} +- {si:.3f} x (z {(es - ts) / ss:+.2f}, {(ei - ti) / si:+.2f}); "
                  f"NLL's minimum {ns:.4f}, {ni:.3f} x", flush=True)
    print(f"estimate (eq. 21's minimum), std x{STD_INFLATION:g}: {summary(rows, 'estimate')}")
    print(f"the NLL's own minimum, same std: {summary(rows, 'nll')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
