"""A single antenna's heading from its own velocity (``ekf.measurement: course``), forwards and reversing.

One antenna measures the direction of its velocity, not of the vehicle: driving forwards that is the
heading plus the antenna's small sideslip (the filter models it, :mod:`..ekf.measurement_row`);
reversing, it points backwards. :class:`CourseTracker` tells the two apart in two ways:

1. *Through a stop* the velocity's direction flips by about pi. Each velocity fast enough for its
   direction to be sure (``REVERSAL_SPEED``) is compared with the last such one, and a turn of more
   than pi/2 between the two is a change of direction.
2. *While steering* the course turns with the steering forwards and against it reversing (the yaw
   rate is vx tan(delta) / L, eq. 1's kinematic limit, and vx < 0 reversing). Once one run of steering
   beyond ``STEERED`` to one side promises a kinematic turn of ``DECISIVE_TURN``, a course turned
   against it by more than half of that says the direction believed is wrong (understeer, slip
   beyond the kinematic yaw rate, only shrinks the turn). This corrects what 1 gets wrong: a log that
   starts while reversing, and a pivot of more than pi/2 at a creep below ``REVERSAL_SPEED``. The
   antenna's kinematic sideslip, (lr + antenna_x) tan(delta) / L either way, comes off the course
   first: an antenna behind the rear axle swings out against the steering as the wheels turn.

Reversing, the epoch's heading is the course + pi and its speed negative, so the filter holds the
stiffness as with a heading (StepStatus.REVERSING).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: m/s: below it a 0.02 m/s velocity error turns the course by more than 4 degrees (no reference then)
REVERSAL_SPEED = 0.3
#: rad (3 deg): steering beyond this, less any steering offset (ekf estimates up to a few tenths of a
#: degree), turns the vehicle to its side
STEERED = math.radians(3.0)
#: rad (30 deg): the kinematic turn, |v| tan|delta| / L over time, one run of steering must promise before its
#: course decides: the course's own noise over a run, sqrt(2) sigma_v / |v|, is 0.2 rad at 0.4 m/s with a
#: 0.06 m/s velocity noise
DECISIVE_TURN = math.radians(30.0)
#: s: velocities further apart do not continue one run of steering
MAX_RUN_GAP = 1.0


@dataclass
class CourseTracker:
    """Which way the vehicle moves, from the directions of its antenna's velocity and the steering."""

    slip_per_tan: float = 0.0  # the antenna's kinematic sideslip per tan(wheel angle): (lr + antenna_x) / L
    wheelbase: float = 1.1  # m, L = lf + lr
    reversing: bool = False
    reference: tuple[float, float] | None = None  # (s, rad): the last velocity of REVERSAL_SPEED or more, its
    # direction less the slip
    side: int = 0  # the current steering run's side (+1 left, -1 right; 0: none)
    turned: float = 0.0  # rad: the course's turn over the run, towards its side if the direction believed is right
    promised: float = 0.0  # rad: the kinematic turn over the run, |v| tan|delta| / L dt

    def heading(self, t: float, east: float, north: float, steering: float = 0.0) -> float:
        """The vehicle's heading (ENU yaw) for the velocity at ``t``: its direction, + pi while reversing.

        ``steering``: the wheel angle (rad, + left) at about ``t``.
        """
        course, speed = math.atan2(north, east), math.hypot(east, north)
        if speed < REVERSAL_SPEED:
            self.side = 0
        else:
            direction = course - self.slip_per_tan * math.tan(steering)  # the vehicle's, or its reverse
            if self.reference is not None:
                turn = math.remainder(direction - self.reference[1], 2.0 * math.pi)
                if abs(turn) > 0.5 * math.pi:
                    self._toggle()
                elif 0.0 < t - self.reference[0] <= MAX_RUN_GAP:
                    self._steered_turn(turn, steering, speed * (t - self.reference[0]))
                else:  # a gap, or a GNSS time base that stepped: the run starts again
                    self.side = 0
            self.reference = (t, direction)
        return course + math.pi if self.reversing else course

    def _steered_turn(self, turn: float, steering: float, distance: float) -> None:
        """Add a turn of the course to the steering run; the direction is the other one if it went against."""
        side = 0 if abs(steering) < STEERED else (1 if steering > 0.0 else -1)
        if side != self.side:
            self.side, self.turned, self.promised = side, 0.0, 0.0
            return
        if side == 0:
            return
        self.turned += side * turn * (-1.0 if self.reversing else 1.0)
        self.promised += distance * abs(math.tan(steering)) / self.wheelbase
        if self.promised >= DECISIVE_TURN and self.turned < -0.5 * self.promised:
            self._toggle()

    def _toggle(self) -> None:
        self.reversing = not self.reversing
        self.side, self.turned, self.promised = 0, 0.0, 0.0
