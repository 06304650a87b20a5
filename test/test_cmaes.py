"""Tests of CMA-ES (the ``cma`` package) as the tuner's third optimiser, beside PSO (eqs. 15-16) and IPSO (17-20)."""

from __future__ import annotations

import numpy as np
import pytest

from transplanter_ident.tuning.benchmark_functions import random_search, rastrigin, shifted
from transplanter_ident.tuning.box import Box
from transplanter_ident.tuning.cmaes import CmaesSettings, minimize_cmaes
from transplanter_ident.tuning.tune import ALGORITHMS, optimize

BOX = Box.cube(6, -5.12, 5.12)
SHIFT = np.array([1.3, -2.1, 0.7, 2.9, -0.4, 1.8])


class Recorder:
    """A batch objective that records every evaluated batch."""

    def __init__(self, function) -> None:  # noqa: ANN001
        self.function = function
        self.batches: list[np.ndarray] = []

    def __call__(self, x: np.ndarray) -> np.ndarray:
        self.batches.append(np.array(x, copy=True))
        return self.function(x)

    @property
    def points(self) -> np.ndarray:
        return np.vstack(self.batches)


def sphere(x: np.ndarray) -> np.ndarray:
    return np.sum((x - SHIFT) ** 2, axis=1)


def test_budget_is_that_of_standard_pso_and_history_has_one_record_per_generation() -> None:
    recorder = Recorder(sphere)
    result = minimize_cmaes(recorder, BOX, CmaesSettings(particles=7, iterations=5), 0)
    assert result.algorithm == "cmaes" and result.evaluations == 7 * 6 == len(recorder.points)
    assert [len(b) for b in recorder.batches] == [7] * 6
    assert [h.iteration for h in result.history] == list(range(6))
    assert [h.evaluations for h in result.history] == [7 * (k + 1) for k in range(6)]
    assert np.all(np.diff(result.best_curve) <= 0.0)
    assert result.fitness == pytest.approx(float(sphere(result.position[None, :])[0]))


def test_max_evaluations_truncates_the_last_batch() -> None:
    recorder = Recorder(sphere)
    result = minimize_cmaes(recorder, BOX, CmaesSettings(particles=6, iterations=10), 1, max_evaluations=20)
    assert result.evaluations == 20 == len(recorder.points)
    assert [len(b) for b in recorder.batches] == [6, 6, 6, 2]
    with pytest.raises(ValueError, match="max_evaluations"):
        minimize_cmaes(sphere, BOX, CmaesSettings(), 1, max_evaluations=0)


def test_same_seed_same_result_and_global_numpy_state_untouched() -> None:
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    runs = [minimize_cmaes(Recorder(rastrigin), BOX, CmaesSettings(particles=8, iterations=6), 42) for _ in range(2)]
    np.testing.assert_array_equal(np.random.get_state()[1], before)
    assert runs[0].fitness == runs[1].fitness
    np.testing.assert_array_equal(runs[0].position, runs[1].position)
    other = minimize_cmaes(rastrigin, BOX, CmaesSettings(particles=8, iterations=6), 43)
    assert other.fitness != runs[0].fitness


def test_every_point_is_in_the_box_and_the_warm_start_comes_first() -> None:
    box = Box((-8.0, -8.0, -10.0, -10.0, -6.0, -8.0), (-1.0, -1.0, -2.0, -2.0, -1.0, -2.0))
    start = np.array([-4.0, -4.0, -6.0, -6.0, -3.4, -4.9])
    recorder = Recorder(lambda x: np.sum((x - box.low) ** 2, axis=1))  # optimum at a corner
    result = minimize_cmaes(recorder, box, CmaesSettings(particles=6, iterations=8), 3, initial=start[None, :])
    points = recorder.points
    assert np.all(points >= box.low) and np.all(points <= box.high)
    np.testing.assert_allclose(recorder.batches[0][0], start, atol=1e-12)
    assert result.fitness <= float(np.sum((start - box.low) ** 2))


def test_a_diverging_candidate_does_not_stop_the_search() -> None:
    def objective(x: np.ndarray) -> np.ndarray:
        values = sphere(x)
        values[::3] = np.nan  # failed filter runs (NaN counts as +inf)
        return values

    result = minimize_cmaes(objective, BOX, CmaesSettings(particles=6, iterations=5), 2)
    assert np.isfinite(result.fitness) and result.evaluations == 36


def test_cmaes_beats_random_search_on_a_shifted_rastrigin() -> None:
    objective = shifted(rastrigin, SHIFT)
    wins = 0
    for seed in range(5):
        cmaes = minimize_cmaes(objective, BOX, CmaesSettings(), seed)
        rand = random_search(objective, BOX, cmaes.evaluations, seed)
        wins += cmaes.fitness < rand.fitness
    assert wins >= 4


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_optimize_dispatches_every_algorithm(algorithm: str) -> None:
    result = optimize(algorithm, sphere, BOX, particles=5, iterations=3, seed=0, max_evaluations=18)
    assert result.algorithm == algorithm and result.evaluations == 18


def test_bad_settings_are_rejected() -> None:
    with pytest.raises(ValueError, match="particles"):
        CmaesSettings(particles=0)
    with pytest.raises(ValueError, match="sigma0"):
        CmaesSettings(sigma0=0.0)
    with pytest.raises(ValueError, match="algorithm"):
        optimize("de", sphere, BOX)
