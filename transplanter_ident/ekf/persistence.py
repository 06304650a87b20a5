"""The learned parameter states, kept across restarts (DESIGN.md section 7; issue #11).

A transplanter gets most of its steering excitation at headland turns, so a restart that forgets
the stiffness can mean minutes without a usable estimate. The node saves the parameter states
(theta_f, theta_r, the steering offset b and its gain's error g) and their 4 x 4 covariance, atomically, every
``persistence.period`` s and at shutdown, with a key (the vehicle, the filter's structure and the
file format) and a timestamp. At start-up it restores them when the key matches and the values
are finite and in bounds, with the covariance inflated (the surface may have changed since);
otherwise it starts cold and says why. A file of the first format (theta_f, theta_r, b, 3 x 3) is restored
with g at 0 and its configured P0.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.files import atomic_write_text

FORMAT = "transplanter_ident/learned-stiffness/2"
FORMAT_WITHOUT_GAIN = "transplanter_ident/learned-stiffness/1"  # theta_f, theta_r, b and their 3 x 3 covariance
N_LEARNED = 4  # theta_f, theta_r, b, g (layout.PARAMETER_STATES)
MAX_GAIN = 0.2  # a saved |g| beyond this is not a plausible steering gain error
#: the restored covariance: INFLATION times the saved one, plus FLOOR_REL_STD^2 relative on each stiffness
INFLATION = 4.0
FLOOR_REL_STD = 0.1


class PersistenceError(ValueError):
    """A saved state that cannot be restored; the message says why."""


@dataclass(frozen=True)
class LearnedState:
    """theta_f, theta_r (state units: ln C or C), the offset b (rad), the gain's error g and their 4 x 4 covariance."""

    theta: tuple[float, float]
    offset: float
    covariance: tuple[tuple[float, ...], ...]
    stamp: float  # data time of the last epoch, s
    gain: float = 0.0  # relative, wheel = (1 + g) sensor - b


def key_of(config: EstimatorConfig) -> dict[str, object]:
    """What a saved state is valid for: the vehicle and the filter's structure."""
    v, o = config.vehicle, config.options
    return {"format": FORMAT, "mass": v.mass, "lf": v.lf, "lr": v.lr, "iz": v.iz, "antenna_x": v.antenna_x,
            "antenna_y": v.antenna_y, "stiffness_state": o.stiffness_state, "measurement": o.measurement}


def default_path(template: str, node_name: str) -> Path | None:
    """``persistence.file`` with ``$ROS_HOME`` (default ~/.ros) and ``{node}`` filled in; None when empty."""
    if not template:
        return None
    ros_home = os.environ.get("ROS_HOME") or str(Path.home() / ".ros")
    return Path(template.replace("$ROS_HOME", ros_home).replace("{node}", node_name)).expanduser()


def save(path: Path, config: EstimatorConfig, state: LearnedState) -> None:
    """Write the state atomically (a temporary file, then a rename: never a half-written file)."""
    document = {"key": key_of(config), "saved_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "stamp": float(state.stamp), "theta": [float(v) for v in state.theta],
                "offset": float(state.offset), "gain": float(state.gain),
                "covariance": [[float(v) for v in row] for row in state.covariance]}
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, "# learned by transplanter_ident; deleted by ~/reset\n"
                      + yaml.safe_dump(document, sort_keys=False))


def load(path: Path, config: EstimatorConfig) -> LearnedState:
    """The saved state if it fits this vehicle and filter, inflated; else PersistenceError with the reason."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise PersistenceError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        document = yaml.safe_load(text)
        key, theta, offset = document["key"], document["theta"], float(document["offset"])
        covariance = np.array(document["covariance"], dtype=np.float64)
        stamp = float(document.get("stamp", 0.0))
        gain = float(document.get("gain", 0.0))
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        raise PersistenceError(f"{path}: not a saved stiffness state ({type(exc).__name__})") from None
    expected = key_of(config)
    without_gain = isinstance(key, dict) and key.get("format") == FORMAT_WITHOUT_GAIN
    if without_gain:
        key = {**key, "format": FORMAT}
    if key != expected:
        differs = sorted(k for k in expected if not isinstance(key, dict) or key.get(k) != expected[k])
        raise PersistenceError(f"{path}: saved for another vehicle or filter (differs in {', '.join(differs)})")
    learned = _checked(path, config, (float(theta[0]), float(theta[1])), offset, gain, covariance,
                       N_LEARNED - 1 if without_gain else N_LEARNED, stamp)
    return _with_gain_prior(learned, config) if without_gain else learned


def _with_gain_prior(learned: LearnedState, config: EstimatorConfig) -> LearnedState:
    """A first-format state (3 x 3) with g at 0 and its configured P0, uncorrelated."""
    covariance = np.zeros((N_LEARNED, N_LEARNED))
    covariance[:-1, :-1] = learned.covariance
    covariance[-1, -1] = config.noise.steering_gain_initial_variance
    return LearnedState(learned.theta, learned.offset, tuple(tuple(float(v) for v in row) for row in covariance),
                        learned.stamp, 0.0)


def _checked(path: Path, config: EstimatorConfig, theta: tuple[float, float], offset: float, gain: float,  # noqa: PLR0913
             covariance: np.ndarray, size: int, stamp: float) -> LearnedState:
    log_state = config.options.stiffness_state == "log"
    stiffness = [math.exp(t) if log_state else t for t in theta] if all(map(math.isfinite, theta)) else []
    low, high = config.options.stiffness_bounds
    if len(stiffness) != 2 or not all(low <= c <= high for c in stiffness):
        raise PersistenceError(f"{path}: saved stiffness {theta} outside ekf.stiffness_bounds [{low:g}, {high:g}]")
    if not (math.isfinite(offset) and abs(offset) <= 0.3):
        raise PersistenceError(f"{path}: saved steering offset {offset!r} rad is not plausible")
    if not (math.isfinite(gain) and abs(gain) <= MAX_GAIN):
        raise PersistenceError(f"{path}: saved steering gain error {gain!r} is not plausible")
    if covariance.shape != (size, size) or not np.all(np.isfinite(covariance)) or \
            np.min(np.linalg.eigvalsh(0.5 * (covariance + covariance.T))) < 0.0:
        raise PersistenceError(f"{path}: saved covariance is not a finite positive semi-definite {size} x {size} matrix")
    inflated = INFLATION * 0.5 * (covariance + covariance.T)
    for k, c in enumerate(stiffness):
        floor = FLOOR_REL_STD ** 2 if log_state else (FLOOR_REL_STD * c) ** 2
        inflated[k, k] += floor
    return LearnedState(theta, offset, tuple(tuple(float(v) for v in row) for row in inflated), stamp, gain)


class Keeper:
    """The node's persistence: restore at start, save when due (only a valid estimate), forget on reset.

    ``status`` is one line for /diagnostics: what was restored, or why the filter started cold.
    """

    def __init__(self, path: Path | None, period: float, config: EstimatorConfig) -> None:
        self.path, self.period, self.config = path, period, config
        self.status = "off (persistence.file is empty)" if path is None else "nothing saved yet"
        self._last_save = -math.inf

    def restore(self) -> LearnedState | None:
        """The saved state, or None (and the reason in :attr:`status`)."""
        if self.path is None:
            return None
        for stale in self.path.parent.glob(f".{self.path.name}.*.tmp"):  # a writer killed mid-write
            stale.unlink(missing_ok=True)
        if not self.path.exists():
            self.status = f"cold start: no saved state at {self.path}"
            return None
        try:
            learned = load(self.path, self.config)
        except PersistenceError as exc:
            self.status = f"cold start: {exc}"
            return None
        self.status = f"restored from {self.path} (covariance inflated)"
        return learned

    def due(self, now: float) -> bool:
        return self.path is not None and now - self._last_save >= self.period

    def save(self, state: LearnedState, now: float) -> None:
        """Save (atomically); an I/O error goes to :attr:`status`, never up."""
        if self.path is None:
            return
        self._last_save = now
        try:
            save(self.path, self.config, state)
            self.status = f"saved to {self.path}"
        except OSError as exc:
            self.status = f"cannot save to {self.path}: {exc.strerror or exc}"

    def forget(self) -> None:
        """Delete the saved state (~/reset)."""
        if self.path is not None:
            self.path.unlink(missing_ok=True)
            self.status = f"saved state deleted by ~/reset ({self.path})"
