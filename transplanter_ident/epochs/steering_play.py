"""Steering play: the free travel of the linkage between the steering sensor and the wheels (beyond the paper).

The bicycle model (paper eq. 4) takes the wheels' angle. A sensor reads it through a linkage whose play
(``vehicle.steering_play``, rad of wheel angle, the full free travel) lets the two differ by up to half of
it, towards the last motion. On a steering sine that error is a square wave in phase with the steering
rate, which the data cannot tell from a timing error or a stiffer or softer tire: 0.1 deg left out moves
Cf by about 10 % while the estimate stays valid (docs/robustness.md). The sign of the play says where it
lies:

* play > 0: the wheels follow the sensor through it (a sensor on the steering column, motor or
  cylinder). The wheel angle is the play operator of the reading, exactly:
  z_k = min(max(z_(k-1), s_k - p/2), s_k + p/2);
* play < 0: the sensor follows the wheels through it (play in the sensor's own linkage). While the
  wheels move, wheel = s + |p|/2 towards the motion; here 2 s - z, with z the play operator of s as
  above: continuous, and within |p| of the wheels during a reversal itself.

:class:`SteeringPlay` does it sample by sample for the streaming assembler; :func:`without_play` runs
the same operations over an array for the batch assembler. Both start centred on the first reading.
"""

from __future__ import annotations

import numpy as np


class SteeringPlay:
    """The wheel angle of each steering reading, in order, through a play of ``play`` rad (see the module)."""

    def __init__(self, play: float) -> None:
        self.play = float(play)
        self._half = 0.5 * abs(self.play)
        self._follower: float | None = None  # the play operator's output z

    def reset(self) -> None:
        """Forget the linkage's position: the next reading is taken as centred in the play."""
        self._follower = None

    def wheel(self, reading: float) -> float:
        """The wheel angle (rad) of the next reading ``reading`` (rad, after the sensor's scale)."""
        if self.play == 0.0:
            return reading
        z = reading if self._follower is None else min(max(self._follower, reading - self._half),
                                                      reading + self._half)
        self._follower = z
        return z if self.play > 0.0 else 2.0 * reading - z


def without_play(readings: np.ndarray, play: float) -> np.ndarray:
    """:meth:`SteeringPlay.wheel` over ``readings`` in order, from a fresh linkage (the same operations)."""
    if play == 0.0:
        return np.asarray(readings, dtype=np.float64)
    linkage = SteeringPlay(play)
    return np.array([linkage.wheel(s) for s in np.asarray(readings, dtype=np.float64).tolist()], dtype=np.float64)
