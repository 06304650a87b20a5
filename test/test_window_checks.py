"""The validity's shared checks: window_checks.py and hysteresis.py (kernels), epoch_checks.py (predicates).

The monitor (online) and the batch (replay, tuner) both run them, so they decide alike by
construction (test_validity_batch.py checks the whole decision). Here each kernel, with the terms
window_columns builds, is held against the checks written out in plain Python over the samples
(statistics, math.fsum, sorted), on 400 random windows whose statistics fall on both sides of the
thresholds: values agree to 1e-9 (relative), the verdicts exactly (no draw lands within that of a
threshold: the test asserts it). The hysteresis is held against its rule written out, and the epoch
predicates give the same verdicts on one epoch's floats (the monitor) as on arrays (the batch).
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from collections import Counter

import numpy as np

from transplanter_ident.config.parameters import ValiditySettings
from transplanter_ident.ekf.layout import StepStatus
from transplanter_ident.evaluation import epoch_checks
from transplanter_ident.evaluation.hysteresis import hysteresis_step, initial_state
from transplanter_ident.evaluation.window_checks import (
    MIN_DRIFT_UPDATES,
    PREDICTED,
    USED,
    drift_checks,
    plausibility_checks,
    soft_checks,
    window_columns,
    window_limits,
)

LEVER, REAR_SLIP_GAIN, ANTENNA_X = 0.9, 180.0, 0.3
DISTRUSTED = {StepStatus.GATED, StepStatus.REJECTED_INVALID, StepStatus.DIVERGED}
NEAR = 1.0e-9  # relative: a statistic this close to its threshold would make the comparison a coin toss


@dataclasses.dataclass
class Draw:
    """One window of epochs, as plain lists."""

    t: list[float]
    status: list[StepStatus]
    speed: list[float]
    vy: list[float]
    r: list[float]
    steering: list[float]
    cr: list[float]
    nis: list[float]
    whitened: list[float]
    suspect: list[bool]
    updates: list[tuple[float, float]]


def _draw(rng: np.random.Generator) -> Draw:
    n = int(rng.integers(2, 90))
    t = np.cumsum(rng.uniform(0.05, 0.4, n)).tolist()
    statuses = [StepStatus.UPDATED] * 8 + [StepStatus.NONLINEAR, StepStatus.GATED, StepStatus.LOW_SPEED,
                                           StepStatus.REJECTED_INVALID]
    status = [statuses[k] for k in rng.integers(0, len(statuses), n)]
    speed = np.where(rng.random(n) < 0.05, 0.0, rng.uniform(0.5, 3.0, n))
    r = rng.normal(0.0, rng.choice((0.01, 0.2)), n)
    heading_like = rng.random() < 0.3  # a course over ground: vy about 0 while turning
    vy = rng.normal(0.0, 0.01, n) if heading_like else LEVER * r + rng.normal(0.0, rng.choice((0.05, 1.0)), n)
    if rng.random() < 0.25:  # frames mixed: the antenna's sideslip turning at about -2 r (a small one)
        r = 0.2 * np.sin(2.0 * np.array(t))
        vy = speed * np.tan(-2.0 * 0.1 * (1.0 - np.cos(2.0 * np.array(t))))
    nis = rng.chisquare(2, n) * rng.choice((1.0, 3.0))
    nis[rng.random(n) < 0.05] = math.nan
    whitened = np.zeros(n)
    rho = rng.choice((0.0, 0.9))
    for k in range(1, n):
        whitened[k] = rho * whitened[k - 1] + rng.normal()
    updates = rng.normal(rng.choice((0.0, 0.8)), 1.0, (n, 2)) * (rng.random((n, 1)) < 0.7)
    return Draw(t=t, status=status, speed=speed.tolist(), vy=vy.tolist(), r=r.tolist(),
                steering=rng.normal(0.0, rng.choice((0.005, 0.1)), n).tolist(),
                cr=rng.uniform(5000.0, 15000.0, n).tolist(), nis=nis.tolist(), whitened=whitened.tolist(),
                suspect=(rng.random(n) < rng.choice((0.02, 0.3))).tolist(), updates=[tuple(u) for u in updates])


def _settings(rng: np.random.Generator) -> ValiditySettings:
    return ValiditySettings(window=float(rng.choice((2.0, 10.0))), max_sideslip=float(rng.choice((0.1, 0.35))),
                            course_ratio=float(rng.choice((0.2, 0.5))), max_nonlinear_fraction=0.1,
                            max_suspect_fraction=0.1, max_autocorrelation=0.5, drift_window=float(rng.choice((0.0, 90.0))))


# the slow versions: the checks as written out over the window's samples


def slow_plausibility(d: Draw, s: ValiditySettings, course: bool) -> tuple[float, bool, bool, bool]:
    """Over the epochs with a one-step prediction and vx > 0 (at least 5)."""
    keep = [k for k in range(len(d.t)) if d.status[k] in PREDICTED and d.speed[k] > 0.0]
    if len(keep) < 5:
        return math.nan, False, False, False
    median = sorted(abs(d.vy[k] - ANTENNA_X * d.r[k]) / d.speed[k] for k in keep)[len(keep) // 2]
    num = den = 0.0
    for a, b in zip(keep, keep[1:], strict=False):
        turn = math.atan2(d.vy[b], d.speed[b]) - math.atan2(d.vy[a], d.speed[a])
        rate = math.remainder(turn, 2.0 * math.pi) / (d.t[b] - d.t[a])
        num += rate * d.r[b]
        den += d.r[b] ** 2
    mixed = median <= s.max_sideslip and den > 0.05 ** 2 * len(keep) and num / den < -1.0
    rms_r = math.sqrt(statistics.fmean(d.r[k] ** 2 for k in keep))
    rms_vy = math.sqrt(statistics.fmean(d.vy[k] ** 2 for k in keep))
    steady = [(LEVER - REAR_SLIP_GAIN * d.speed[k] ** 2 / d.cr[k]) * d.r[k] for k in keep]
    over_ground = not course and rms_r > 0.05 and rms_vy < s.course_ratio * math.sqrt(statistics.fmean(
        v * v for v in steady))
    return median, median > s.max_sideslip, mixed, over_ground


def slow_soft(d: Draw, s: ValiditySettings) -> tuple:
    n = len(d.t)
    suspects = sum(d.suspect)
    suspect_fails = suspects > s.max_suspect_fraction * n
    if n < 5 or d.t[-1] - d.t[0] < 0.5 * s.window:
        return suspects, suspect_fails, True, 0.0, False, False, math.nan, False, math.nan, False
    fraction = sum(x is StepStatus.NONLINEAR for x in d.status) / n
    unexcited = statistics.pstdev(d.steering) < s.min_steering_std and statistics.pstdev(d.r) < s.min_yaw_rate_std
    used = [k for k in range(n) if d.status[k] in USED and math.isfinite(d.nis[k])]
    if len(used) < 5:
        return suspects, suspect_fails, False, fraction, fraction > s.max_nonlinear_fraction, unexcited, math.nan, \
            False, math.nan, False
    total = math.fsum(d.nis[k] for k in used)
    dof = 2 * len(used)
    w = np.array([d.whitened[k] for k in used])
    c = w - w.mean()
    rho = float(np.dot(c[:-1], c[1:]) / np.dot(c, c)) if np.dot(c, c) > 0.0 else 0.0
    return (suspects, suspect_fails, False, fraction, fraction > s.max_nonlinear_fraction, unexcited,
            total / len(used), total > dof + s.nis_quantile_sigmas * math.sqrt(2.0 * dof), rho,
            rho > s.max_autocorrelation)


def slow_drift(d: Draw, s: ValiditySettings) -> tuple:
    kept = [u for u in d.updates if u != (0.0, 0.0)]
    total_f, total_r = math.fsum(u[0] for u in kept), math.fsum(u[1] for u in kept)
    if s.drift_window <= 0.0 or len(kept) < MIN_DRIFT_UPDATES:
        return len(kept), total_f, total_r, False, False
    limit = s.max_drift_sigmas * math.sqrt(len(kept))
    return len(kept), total_f, total_r, abs(total_f) > limit, abs(total_r) > limit


# the fast versions, as the monitor calls them


def _columns(d: Draw):  # noqa: ANN202
    f = np.array
    return window_columns(f(d.t), f([int(x) for x in d.status], dtype=np.int64), f(d.speed), f(d.vy), f(d.r),
                          f(d.steering), f(d.cr), f(d.nis), f(d.whitened), f(d.suspect, dtype=np.bool_),
                          (LEVER, REAR_SLIP_GAIN, ANTENNA_X))


def _same(fast: tuple, slow: tuple, what: str, thresholds: dict[int, float]) -> None:
    """Values to 1e-9, verdicts exactly; ``thresholds``: value index -> its threshold (none may sit within NEAR)."""
    assert len(fast) == len(slow), what
    for k, (a, b) in enumerate(zip(fast, slow, strict=True)):
        if isinstance(b, bool):
            assert bool(a) == b, (what, k, fast, slow)
        else:
            assert (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12), (what, k)
    for k, threshold in thresholds.items():
        if math.isfinite(slow[k]):
            assert abs(slow[k] - threshold) > NEAR * max(abs(threshold), 1e-3), (what, k, "on its threshold")


PLAUSIBILITY_VERDICTS = {1: "sideslip", 2: "frames mixed", 3: "course over ground"}
SOFT_VERDICTS = {1: "suspect", 2: "too little data", 4: "nonlinear", 5: "unexcited", 7: "NIS", 9: "autocorrelation"}
DRIFT_VERDICTS = {3: "drift Cf", 4: "drift Cr"}


def test_the_kernels_are_the_checks_written_out() -> None:
    rng = np.random.default_rng(11)
    fails = Counter()
    cases = 400
    for case in range(cases):
        d, s = _draw(rng), _settings(rng)
        course = bool(rng.random() < 0.2)
        limits = window_limits(s, 1.0, course)
        c = _columns(d)
        n = len(d.t)
        plausibility = plausibility_checks(0, len(c.plaus), c.sideslip, c.rate, c.yaw_rate, c.plaus, c.r_sq,
                                           c.vy_sq, c.steady_sq, limits)
        _same(plausibility, slow_plausibility(d, s, course), f"plausibility {case}", {0: s.max_sideslip})
        soft = soft_checks(0, n - 1, 0, len(c.consist), c.t, c.nonlinear, c.steering, c.yaw_rate, c.suspect, c.nis,
                           c.whitened, limits)
        _same(soft, slow_soft(d, s), f"soft {case}", {8: s.max_autocorrelation})
        drift = drift_checks(0, n - 1, np.array(d.updates, dtype=np.float64).reshape(-1, 2), limits)
        _same(drift, slow_drift(d, s), f"drift {case}", {})
        for result, names in ((plausibility, PLAUSIBILITY_VERDICTS), (soft, SOFT_VERDICTS), (drift, DRIFT_VERDICTS)):
            fails.update(name for k, name in names.items() if result[k])
    for name in [*PLAUSIBILITY_VERDICTS.values(), *SOFT_VERDICTS.values(), *DRIFT_VERDICTS.values()]:
        assert 10 <= fails[name] <= cases - 10, (name, fails[name])  # the draws take each check both ways


def test_the_kernels_add_in_order() -> None:
    """Sums in plain loops, never compensated (Python 3.12's ``sum`` is: 1e16 + 1 - 1e16 is 1.0 there).

    So the monitor and the batch, which both call these kernels, decide alike on any Python: the NIS
    sum of 1e16, 1, -1e16 over 5+ epochs is the loop's.
    """
    n = 12
    t = np.arange(n, dtype=np.float64)
    nis = np.array([1e16, 1.0, -1e16] + [0.0] * (n - 3))
    limits = window_limits(ValiditySettings(window=4.0), 1.0, False)
    result = soft_checks(0, n - 1, 0, n, t, np.zeros(n, dtype=np.bool_), np.ones(n), np.ones(n),
                         np.zeros(n, dtype=np.bool_), nis, np.zeros(n), limits)
    assert result[6] == 0.0  # (1e16 + 1) - 1e16 in a loop; 1 / 12 compensated


def slow_hysteresis(t: list[float], hard: list[bool], failing: list[bool], hold_on: float, hold_off: float) -> list[bool]:
    """Valid once nothing failed for hold_on s; invalid once something failed for hold_off s, or at once if hard."""
    valid, good_since, bad_since, out = False, None, None, []
    for now, h, f in zip(t, hard, failing, strict=True):
        if f:
            good_since = None
            bad_since = now if bad_since is None else bad_since
            valid = valid and not (h or now - bad_since >= hold_off)
        else:
            bad_since = None
            good_since = now if good_since is None else good_since
            valid = valid or now - good_since >= hold_on
        out.append(valid)
    return out


def test_the_hysteresis_kernel_is_the_rule_written_out() -> None:
    rng = np.random.default_rng(4)
    switches = 0
    for _ in range(200):
        n = int(rng.integers(1, 200))
        t = np.cumsum(rng.uniform(0.05, 0.5, n)).tolist()
        failing = (rng.random(n) < rng.choice((0.05, 0.3, 0.7))).tolist()
        hard = [f and rng.random() < 0.3 for f in failing]
        hold_on, hold_off = float(rng.choice((0.0, 1.0, 3.0))), float(rng.choice((0.0, 0.5, 1.0)))
        state = initial_state()
        fast = [hysteresis_step(state, now, h, f, hold_on, hold_off) for now, h, f in zip(t, hard, failing, strict=True)]
        expected = slow_hysteresis(t, hard, failing, hold_on, hold_off)
        assert fast == expected
        switches += int(np.count_nonzero(np.diff(np.array(expected, dtype=int))))
    assert switches > 200  # the sequences turn valid on and off


def test_the_epoch_checks_decide_alike_on_floats_and_arrays() -> None:
    """The monitor calls epoch_checks' predicates with one epoch's floats, the batch with arrays: same verdicts, NaN too."""
    rng = np.random.default_rng(8)
    n = 2000
    bounds = (500.0, 60000.0)
    cf = rng.choice([bounds[0], bounds[0] * 1.0101, bounds[1] / 1.01, 8000.0, math.nan], n)
    cr = rng.uniform(400.0, 70000.0, n)
    cf_std, cr_std = cf * rng.uniform(0.0, 0.1, n), cr * rng.uniform(0.0, 0.1, n)
    cr_std[rng.random(n) < 0.05] = math.nan
    factors = np.where(rng.random((n, 2)) < 0.05, math.nan, rng.uniform(0.5, 4.0, (n, 2)))
    evidence = np.where(rng.random(n) < 0.05, math.nan, rng.uniform(0.0, 1.0, n))
    nis = rng.chisquare(2, (n, 2))
    settings = ValiditySettings(max_rel_std=0.05, max_noise_factor=2.25, max_change_evidence=0.5)
    with np.errstate(invalid="ignore"):
        arrays = (epoch_checks.pinned(cf, bounds), epoch_checks.relative_stds(cf, cr, cf_std, cr_std)[2],
                  epoch_checks.noisier(factors[:, 0], factors[:, 1], settings),
                  epoch_checks.change_suspected(evidence, settings),
                  epoch_checks.consistency_nis(factors[:, 0], factors[:, 1], nis[:, 0], nis[:, 1], settings))
    unconverged = epoch_checks.unconverged(arrays[1], settings)
    for k in range(n):
        worst = epoch_checks.relative_stds(float(cf[k]), float(cr[k]), float(cf_std[k]), float(cr_std[k]))[2]
        assert bool(epoch_checks.pinned(float(cf[k]), bounds)) == arrays[0][k]
        assert bool(epoch_checks.unconverged(worst, settings)) == unconverged[k]
        assert bool(epoch_checks.noisier(float(factors[k, 0]), float(factors[k, 1]), settings)) == arrays[2][k]
        assert bool(epoch_checks.change_suspected(float(evidence[k]), settings)) == arrays[3][k]
        assert float(epoch_checks.consistency_nis(float(factors[k, 0]), float(factors[k, 1]), float(nis[k, 0]),
                                                  float(nis[k, 1]), settings)) == arrays[4][k]
    assert 0 < arrays[0].sum() < n and 0 < unconverged.sum() < n and 0 < arrays[2].sum() < n  # both ways
    worst = np.maximum(cf_std / cf, cr_std / cr)
    assert np.array_equal(unconverged[np.isfinite(worst)], worst[np.isfinite(worst)] > 0.05)  # the rule itself
    assert unconverged[np.isnan(cf)].all()  # no stiffness: never converged
