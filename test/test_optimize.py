"""Tests of the optimisers (PSO eqs. 15-16, IPSO eqs. 17-20) and the Q/R search space (eq. 22)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import simulate_epochs

import transplanter_ident.ekf as ekf
from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, NoiseParams
from transplanter_ident.ekf.joint_ekf import kernel_input
from transplanter_ident.ekf.layout import HEADING_STATES, X_PSI
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.tuning.benchmark_functions import ackley, random_search, rastrigin, shifted
from transplanter_ident.tuning.box import Box
from transplanter_ident.tuning.problem import (
    NAMES,
    Q_SPAN,
    TuningProblem,
    batch_objective,
    candidate_matrices,
    design_box,
    noise_to_vector,
    search_box,
    search_config,
    searched_names,
    span_edges,
    vector_to_noise,
)
from transplanter_ident.tuning.pso import (
    IpsoSettings,
    OptimizeResult,
    PsoSettings,
    detection_radius,
    inertia,
    logistic_map,
    minimize,
    pso_for_budget,
    settings_for,
)
from transplanter_ident.tuning.tune import TuningOutcome, edge_note, header_comment

RASTRIGIN_BOX = Box.cube(6, -5.12, 5.12)
ACKLEY_BOX = Box.cube(6, -32.768, 32.768)
SHIFT = np.array([1.3, -2.1, 0.7, 2.9, -0.4, 1.8])  # the optimum off the box centre (eq. 17 pulls to the centre)


class Recorder:
    """A batch objective that records every evaluated point."""

    def __init__(self, function) -> None:  # noqa: ANN001
        self.function = function
        self.points: list[np.ndarray] = []
        self.calls = 0

    def __call__(self, x: np.ndarray) -> np.ndarray:
        self.points.append(np.array(x, copy=True))
        self.calls += 1
        return self.function(x)

    @property
    def count(self) -> int:
        return sum(len(p) for p in self.points)

    @property
    def all_points(self) -> np.ndarray:
        return np.vstack(self.points)


def plateau(x: np.ndarray) -> np.ndarray:
    """Flat except near one corner: every particle stagnates, so the chaotic search (eqs. 19-20) runs."""
    x = np.atleast_2d(x)
    return np.where(np.all(x > 0.9, axis=1), -1.0, 0.0)


# --------------------------------------------------------------------------- building blocks


def test_box_validation_and_helpers() -> None:
    box = Box((0.0, -1.0), (1.0, 1.0))
    assert box.dimension == 2
    np.testing.assert_allclose(box.width, [1.0, 2.0])
    np.testing.assert_allclose(box.clip(np.array([[2.0, -3.0]])), [[1.0, -1.0]])
    with pytest.raises(ValueError):
        Box((0.0,), (0.0,))
    with pytest.raises(ValueError):
        Box((0.0, 1.0), (1.0,))
    with pytest.raises(ValueError):
        Box((0.0,), (math.inf,))


@pytest.mark.parametrize("kwargs", [{"particles": 0}, {"iterations": 0}, {"c1": -1.0}, {"velocity_clamp": 0.0}])
def test_pso_settings_are_validated(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        PsoSettings(**kwargs)


@pytest.mark.parametrize("kwargs", [{"chaos_radius": 0.0}, {"chaos_steps": -1}, {"stagnation_tolerance": -1.0}])
def test_ipso_settings_are_validated(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        IpsoSettings(**kwargs)


def test_paper_defaults() -> None:
    s = IpsoSettings()
    assert (s.particles, s.iterations, s.c1, s.c2, s.c3) == (20, 40, 1.0, 1.5, 2.0)
    assert (s.chaos_steps, s.stagnation_iterations, s.radius_decay, s.stagnation_tolerance) == (10, 5, 4.0, 1e-6)
    assert inertia(s, 0.0) == pytest.approx(0.9) and inertia(s, 1.0) == pytest.approx(0.4)
    assert isinstance(settings_for("pso"), PsoSettings) and not isinstance(settings_for("pso"), IpsoSettings)
    with pytest.raises(ValueError):
        settings_for("foo")


def test_detection_radius_eq17_shrinks_to_the_centre() -> None:
    box = Box((0.0, -10.0), (2.0, 10.0))
    u = np.random.default_rng(0).random((1000, 2))
    early, late = detection_radius(box, 0.0, 4.0, u), detection_radius(box, 1.0, 4.0, u)
    assert np.all(early >= box.low - 1e-12) and np.all(early <= box.high + 1e-12)
    assert np.ptp(early[:, 1]) > 19.0  # t = 0: anywhere in the box
    assert np.max(np.abs(late - [1.0, 0.0])) <= math.exp(-4.0) * 10.0 + 1e-12  # t = 1: e^-lambda of the half width


def test_logistic_map_eq19() -> None:
    y = np.array([0.1, 0.3, 0.7])
    np.testing.assert_allclose(logistic_map(y), 4.0 * y * (1.0 - y))
    for _ in range(100):
        y = logistic_map(y)
        assert np.all((y >= 0.0) & (y <= 1.0))


# --------------------------------------------------------------------------- behaviour


@pytest.mark.parametrize("algorithm", ["ipso", "pso"])
def test_reproducible_with_a_seed(algorithm: str) -> None:
    settings = settings_for(algorithm, iterations=15)
    a = minimize(rastrigin, RASTRIGIN_BOX, settings, 7)
    b = minimize(rastrigin, RASTRIGIN_BOX, settings, np.random.default_rng(7))
    c = minimize(rastrigin, RASTRIGIN_BOX, settings, 8)
    np.testing.assert_array_equal(a.position, b.position)
    assert a.fitness == b.fitness and a.history == b.history and a.evaluations == b.evaluations
    assert c.fitness != a.fitness


@pytest.mark.parametrize("algorithm", ["ipso", "pso"])
def test_box_respected_and_evaluations_counted(algorithm: str) -> None:
    box = Box((0.0, -3.0, 10.0), (1.0, 3.0, 20.0))
    recorder = Recorder(plateau)
    result = minimize(recorder, box, settings_for(algorithm, particles=8, iterations=30), 3)
    points = recorder.all_points
    assert np.all(points >= box.low) and np.all(points <= box.high)
    assert result.evaluations == recorder.count
    assert result.history[-1].evaluations == result.evaluations
    assert np.all(result.position >= box.low) and np.all(result.position <= box.high)


def test_stagnation_triggers_the_chaotic_search() -> None:
    recorder = Recorder(plateau)
    box = Box.cube(3, 0.0, 1.0)
    settings = IpsoSettings(particles=6, iterations=20, c3=0.0)
    result = minimize(recorder, box, settings, 1)
    chaotic = sum(h.chaotic_particles for h in result.history)
    assert chaotic > 0
    assert result.evaluations > settings.particles * (settings.iterations + 1)  # chaotic steps count
    assert result.evaluations <= settings.particles * (settings.iterations + 1) + chaotic * settings.chaos_steps
    no_chaos = minimize(Recorder(plateau), box, IpsoSettings(particles=6, iterations=20, c3=0.0, chaos_steps=0), 1)
    assert no_chaos.evaluations == settings.particles * (settings.iterations + 1)


def test_chaotic_candidates_lie_within_r_d_of_the_particle() -> None:
    """With the swarm frozen (w = c1 = c2 = c3 = 0), every later point is a chaotic candidate (eq. 20)."""
    box = Box((0.0, 0.0), (1.0, 10.0))
    settings = IpsoSettings(particles=4, iterations=12, c1=0.0, c2=0.0, c3=0.0, inertia_start=0.0,
                            inertia_end=0.0, chaos_radius=0.05, stagnation_iterations=2)
    recorder = Recorder(lambda x: np.zeros(len(np.atleast_2d(x))))
    result = minimize(recorder, box, settings, 4)
    initial = recorder.points[0]
    later = np.vstack(recorder.points[1:])
    assert sum(h.chaotic_particles for h in result.history) > 0
    distance = np.min(np.max(np.abs(later[:, None, :] - initial[None, :, :]) / box.width, axis=2), axis=1)
    assert np.all(distance <= 0.05 + 1e-12)
    assert np.any(distance > 0.0)  # and the search does move


def test_budget_truncates_exactly_and_pso_for_budget_matches() -> None:
    ipso = minimize(shifted(ackley, SHIFT), ACKLEY_BOX, IpsoSettings(), 0)
    budget = ipso.evaluations
    pso = minimize(shifted(ackley, SHIFT), ACKLEY_BOX, pso_for_budget(budget), 0, max_evaluations=budget)
    assert pso.evaluations == budget
    odd = minimize(rastrigin, RASTRIGIN_BOX, IpsoSettings(iterations=100), 0, max_evaluations=333)
    assert odd.evaluations == 333
    tiny = minimize(rastrigin, RASTRIGIN_BOX, PsoSettings(), 0, max_evaluations=5)
    assert tiny.evaluations == 5


def test_warm_start_is_never_worse() -> None:
    start = np.full(6, 0.2)
    result = minimize(rastrigin, RASTRIGIN_BOX, IpsoSettings(iterations=3), 0, initial=start[None, :])
    assert result.fitness <= float(rastrigin(start)[0])
    assert result.history[0].best_fitness <= float(rastrigin(start)[0])
    assert np.all(np.diff(result.best_curve) <= 0.0)  # gbest never gets worse


def test_nan_fitness_counts_as_worst() -> None:
    def holes(x: np.ndarray) -> np.ndarray:
        values = rastrigin(x)
        values[np.atleast_2d(x)[:, 0] > 0] = np.nan
        return values

    result = minimize(holes, RASTRIGIN_BOX, IpsoSettings(iterations=10), 0)
    assert math.isfinite(result.fitness) and result.position[0] <= 0.0


@pytest.mark.parametrize("name", ["rastrigin", "ackley"])
def test_ipso_and_pso_beat_random_search_on_equal_budgets(name: str) -> None:
    """A small version of bench/ipso_vs_pso.py: 5 seeds, optimum shifted off the box centre."""
    function, box = (rastrigin, RASTRIGIN_BOX) if name == "rastrigin" else (ackley, ACKLEY_BOX)
    shift = SHIFT if name == "rastrigin" else 5.0 * SHIFT
    objective = shifted(function, shift)
    ipso, pso, rand = [], [], []
    for seed in range(5):
        a = minimize(objective, box, IpsoSettings(), seed)
        b = minimize(objective, box, pso_for_budget(a.evaluations), seed, max_evaluations=a.evaluations)
        c = random_search(objective, box, a.evaluations, seed)
        assert a.evaluations == b.evaluations == c.evaluations
        ipso.append(a.fitness)
        pso.append(b.fitness)
        rand.append(c.fitness)
    baseline = float(np.median(rand))
    assert np.median(ipso) < 0.8 * baseline
    assert np.median(pso) < 0.8 * baseline


# --------------------------------------------------------------------------- the Q/R search space


@pytest.mark.parametrize("stiffness_state", ["log", "linear"])
@pytest.mark.parametrize("measurement", ["heading", "yaw_rate"])
def test_search_box_holds_the_defaults(stiffness_state: str, measurement: str) -> None:
    options = FilterOptions(stiffness_state=stiffness_state, measurement=measurement)
    box = search_box(options)
    assert box.names == NAMES and box.dimension == 6
    expected_q = (-10.0, -2.0) if stiffness_state == "log" else (-2.0, 6.0)
    expected_r2 = (-8.0, -2.0) if measurement == "heading" else (-6.0, -1.0)
    assert (box.lower[2], box.upper[2]) == expected_q and (box.lower[5], box.upper[5]) == expected_r2
    assert (box.lower[0], box.upper[0]) == (-8.0, -1.0) and (box.lower[4], box.upper[4]) == (-6.0, -1.0)
    if stiffness_state == "log" and measurement == "heading":
        vector = noise_to_vector(NoiseParams())
        assert np.all(vector >= box.low) and np.all(vector <= box.high)


def test_vector_noise_round_trip_keeps_heading_q_and_p0() -> None:
    base = NoiseParams(heading_process_noise=3.0e-9, initial_covariance=(1e-2, 1e-2, 2.0, 3.0))
    vector = np.array([-5.0, -4.0, -7.0, -6.5, -3.0, -5.5])
    noise = vector_to_noise(vector, base)
    np.testing.assert_allclose(noise.process_noise, 10.0 ** vector[:4])
    np.testing.assert_allclose(noise.measurement_noise, 10.0 ** vector[4:])
    assert noise.heading_process_noise == 3.0e-9 and noise.initial_covariance == base.initial_covariance
    np.testing.assert_allclose(noise_to_vector(noise), vector)


@pytest.mark.parametrize("measurement", ["heading", "yaw_rate"])
def test_candidate_matrices_follow_the_filter_layout(measurement: str) -> None:
    config = EstimatorConfig(options=FilterOptions(measurement=measurement),
                             noise=NoiseParams(heading_process_noise=5.0e-9))
    vector = np.array([[-5.0, -4.0, -7.0, -6.5, -3.0, -5.5]])
    qs, rs = candidate_matrices(vector, config)
    arrays = ekf.FilterArrays.from_config(EstimatorConfig(options=config.options,
                                                          noise=vector_to_noise(vector[0], config.noise)))
    np.testing.assert_allclose(qs[0], arrays.process_noise)
    np.testing.assert_allclose(rs[0], arrays.measurement_noise)
    if measurement == "heading":
        assert qs.shape == (1, HEADING_STATES) and qs[0, X_PSI] == 5.0e-9


@pytest.mark.parametrize("measurement", ["heading", "yaw_rate"])
def test_split_q_searches_the_physical_noises_by_default(measurement: str) -> None:
    """Issue #13 split Q: vy, r, psi and R by default; the stiffness random walk only when asked."""
    options = FilterOptions(measurement=measurement)
    heading = ("q_psi",) if measurement == "heading" else ()
    assert searched_names(options) == ("q_vy", "q_r", *heading, "r_vy", "r_2")
    assert searched_names(options, tune_stiffness_noise=True) == ("q_vy", "q_r", *heading, "q_cf", "q_cr",
                                                                   "r_vy", "r_2")
    assert searched_names(FilterOptions(measurement="yaw_rate"), tune_stiffness_noise=True) == NAMES
    box = search_box(options, searched_names(options))
    assert np.all(noise_to_vector(NoiseParams(), box.names) >= box.low)
    assert np.all(noise_to_vector(NoiseParams(), box.names) <= box.high)


@pytest.mark.parametrize("tune_stiffness_noise", [False, True])
def test_process_noise_is_searched_within_q_span_of_the_start(tune_stiffness_noise: bool) -> None:
    """Q within Q_SPAN decades of the configured value (inside the bounds), R over its bounds; inf: the whole box."""
    config = EstimatorConfig(noise=NoiseParams(process_noise=(1e-4, 3e-8, 1.5e-5, 1.5e-5), heading_process_noise=0.0))
    names = searched_names(config.options, tune_stiffness_noise)
    full, box = search_box(config.options, names), design_box(config, names)
    start = full.clip(noise_to_vector(config.noise, names))
    assert Q_SPAN == 1.0 and box.names == names
    for i, name in enumerate(names):
        if name.startswith("r_"):
            assert (box.lower[i], box.upper[i]) == (full.lower[i], full.upper[i]), name
        else:
            assert box.lower[i] == max(full.lower[i], start[i] - 1.0), name
            assert box.upper[i] == min(full.upper[i], start[i] + 1.0), name
    q_r, q_psi = names.index("q_r"), names.index("q_psi")
    assert (box.lower[q_r], box.upper[q_r]) == (-8.0, pytest.approx(math.log10(3e-7)))  # near the lower bound
    assert (box.lower[q_psi], box.upper[q_psi]) == (-12.0, -11.0)  # zero: the span starts at the lower bound
    assert design_box(config, names, math.inf) == full
    assert design_box(config, names, 0.25).upper[0] == pytest.approx(-3.75)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="q_span"):
            design_box(config, names, bad)


def test_problem_box_and_start_follow_q_span(sine_epochs) -> None:  # noqa: ANN001
    config = EstimatorConfig()
    narrow = TuningProblem.from_epochs(config, sine_epochs, "nll")
    wide = TuningProblem.from_epochs(config, sine_epochs, "nll", q_span=math.inf)
    assert narrow.box == design_box(config, narrow.names) and wide.box == search_box(config.options, wide.names)
    np.testing.assert_array_equal(narrow.start, wide.start)
    assert np.all(narrow.start >= narrow.box.low) and np.all(narrow.start <= narrow.box.high)
    with pytest.raises(ValueError, match="q_span"):
        TuningProblem.from_epochs(config, sine_epochs, "nll", q_span=0.0)


def test_tuned_q_at_an_edge_of_its_span_is_named(sine_epochs) -> None:  # noqa: ANN001
    """Edges the span set are named (in the YAML header too); physical bounds and R are not."""
    config = EstimatorConfig(noise=NoiseParams(heading_process_noise=0.0))  # q_psi's span starts at its bound
    problem = TuningProblem.from_epochs(config, sine_epochs, "nll")
    start, box = problem.start, problem.box
    assert problem.names == ("q_vy", "q_r", "q_psi", "r_vy", "r_2")
    assert span_edges(config, problem.names, 1.0, start) == ()  # the start is the span's centre (q_psi: its bound)
    inside = start.copy()
    inside[2] = box.lower[2]  # on the physical lower bound: not a span edge
    inside[3], inside[4] = box.upper[3], box.lower[4]  # R on its bounds: not a span edge
    assert span_edges(config, problem.names, 1.0, inside) == ()
    edged = inside.copy()
    edged[0], edged[1] = box.upper[0] - 0.005, box.lower[1] + 0.005  # within 1 % of the 2-decade span
    assert span_edges(config, problem.names, 1.0, edged) == (("q_vy", "upper"), ("q_r", "lower"))
    assert span_edges(config, problem.names, math.inf, edged) == ()
    outcome = TuningOutcome(problem, OptimizeResult("ipso", edged, -5.0, 10), -4.0, 1, 0.1)
    note = edge_note(outcome)
    assert note.startswith("q_vy at its upper edge, q_r at its lower edge (searched within 1 decade of the start)")
    assert note in header_comment(outcome, "bag", 10).splitlines()
    assert edge_note(TuningOutcome(problem, OptimizeResult("ipso", inside, -5.0, 10), -4.0, 1, 0.1)) == ""


def test_split_q_keeps_the_stiffness_and_offset_noise_as_configured(sine_epochs) -> None:  # noqa: ANN001
    config = EstimatorConfig(noise=NoiseParams(heading_process_noise=2.0e-9, steering_offset_process_noise=3.0e-9))
    problem = TuningProblem.from_epochs(config, sine_epochs, "nll")
    assert problem.names == ("q_vy", "q_r", "q_psi", "r_vy", "r_2") and problem.box.dimension == 5
    position = np.array([-5.0, -4.0, -9.0, -3.0, -5.5])
    tuned = problem.tuned_config(position).noise
    np.testing.assert_allclose([*tuned.process_noise[:2], tuned.heading_process_noise, *tuned.measurement_noise],
                               10.0**position)
    assert tuned.process_noise[2:] == config.noise.process_noise[2:]
    assert tuned.steering_offset_process_noise == 3.0e-9
    qs, rs = candidate_matrices(position[None, :], config, problem.names)
    arrays = ekf.FilterArrays.from_config(problem.tuned_config(position))
    np.testing.assert_allclose(qs[0], arrays.process_noise)
    np.testing.assert_allclose(rs[0], arrays.measurement_noise)
    assert problem(position[None, :])[0] == problem.evaluate_noise(tuned)
    full = TuningProblem.from_epochs(config, sine_epochs, "nll", tune_stiffness_noise=True)
    assert full.box.dimension == 7 and full.names[3:5] == ("q_cf", "q_cr")


@pytest.fixture(scope="module")
def sine_epochs():  # noqa: ANN201
    return simulate_epochs(build_config("sine", duration=40.0, seed=5))[1]


@pytest.mark.parametrize("options", [FilterOptions(), FilterOptions(measurement="yaw_rate"),
                                     FilterOptions(discretization="euler", stiffness_state="linear",
                                                   measurement="yaw_rate")])
@pytest.mark.parametrize("objective", ["mae", "nll"])
def test_batch_objective_equals_the_serial_filter(sine_epochs, options: FilterOptions, objective: str) -> None:  # noqa: ANN001
    """The parallel batch gives exactly ekf.sequence_objective per candidate (also guards a stale numba cache)."""
    linear = options.stiffness_state == "linear"
    base = EstimatorConfig(options=options, noise=NoiseParams(
        process_noise=(1e-4, 1e-4, 100.0, 100.0) if linear else (1e-4, 1e-4, 1e-6, 1e-6),
        initial_covariance=(1e-2, 1e-2, 1e6, 1e6) if linear else (1e-2, 1e-2, 4.0, 4.0)))
    problem = TuningProblem.from_epochs(base, sine_epochs, objective)
    candidates = problem.box.uniform(np.random.default_rng(0), 9)
    batch = problem(candidates)
    # candidates are scored without ekf.noise_adaptation (the search measures R itself)
    serial = [ekf.sequence_objective(search_config(problem.tuned_config(c)), sine_epochs, objective)
              for c in candidates]
    np.testing.assert_array_equal(batch, serial)
    np.testing.assert_array_equal(problem.evaluate_serially(candidates), batch)
    assert np.all(np.isfinite(batch))
    assert problem.evaluate_noise(base.noise) == ekf.sequence_objective(search_config(base), sine_epochs, objective)
    assert problem.tuned_config(candidates[0]).options.noise_adaptation  # the written file keeps the option


def test_divergence_gets_a_finite_penalty(sine_epochs) -> None:  # noqa: ANN001
    config = EstimatorConfig(options=FilterOptions(discretization="euler", stiffness_state="linear",
                                                   measurement="yaw_rate"))
    a = ekf.FilterArrays.from_config(config)
    qs = np.array([[1e-1, 1e-1, 1e12, 1e12, 0.0, 0.0, 0.0]])  # vy, r, Cf, Cr, steering offset and gain, h
    rs = np.array([[1e-12, 1e-12]])
    value = batch_objective(kernel_input(sine_epochs), a.initial_state, a.initial_covariance, a.vehicle,
                            a.settings, qs, rs, ekf.MAE)[0]
    assert math.isfinite(value) and 0.0 < value <= ekf.DIVERGENCE_PENALTY
