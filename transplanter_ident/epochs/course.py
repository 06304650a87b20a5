"""A single antenna's heading from its own velocity (``ekf.measurement: course``), forwards and reversing.

One antenna measures the direction of its velocity, not of the vehicle: driving forwards that is the
heading plus the antenna's small sideslip (the filter models it, :mod:`..ekf.measurement_row`);
reversing, it points backwards. :class:`CourseTracker` tells the two apart in two ways:

1. *Through a stop* the velocity's direction flips by about pi. Each velocity fast enough for its
   direction to be sure (``REVERSAL_SPEED``) is compared with the last such one, and a turn of more
   than pi/2 between the two is a change of direction.
2. *While steering* the course turns with the steering forwards and against it reversing (the yaw
   rate is vx tan(delta) / L, eq. 1's kinematic limit, and vx < 0 reversing). Over one run of steering
   beyond ``STEERED`` to one side, a course turned ``AGAINST_TURN`` the other way than the direction
   believed says the belief is wrong. This corrects what 1 gets wrong: a log that starts while
   reversing, and a pivot of more than pi/2 at a creep below ``REVERSAL_SPEED``. The antenna's
   kinematic sideslip, (lr + antenna_x) tan(delta) / L either way, comes off the course first: an
   antenna behind the rear axle swings out against the steering as the wheels turn.

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
#: rad (20 deg): a turn against the steering this large within one run is no sensor noise (course noise
#: about 0.05 rad at 1 m/s, twice over) nor the tires' slip beyond the kinematic one
AGAINST_TURN = math.radians(20.0)


@dataclass
class CourseTracker:
    """Which way the vehicle moves, from the directions of its antenna's velocity and the steering."""

    slip_per_tan: float = 0.0  # the antenna's kinematic sideslip per tan(wheel angle): (lr + antenna_x) / L
    reversing: bool = False
    reference: float | None = None  # rad: the direction (less the slip) of the last velocity of REVERSAL_SPEED or more
    side: int = 0  # the current steering run's side (+1 left, -1 right; 0: none)
    turned: float = 0.0  # rad: the course's turn over the run, positive towards its side

    def heading(self, east: float, north: float, steering: float = 0.0) -> float:
        """The vehicle's heading (ENU yaw) for this velocity: its direction, + pi while reversing.

        ``steering``: the wheel angle (rad, + left) at about this velocity's time.
        """
        course = math.atan2(north, east)
        if math.hypot(east, north) < REVERSAL_SPEED:
            self.side = 0
        else:
            direction = course - self.slip_per_tan * math.tan(steering)  # the vehicle's, or its reverse
            if self.reference is not None:
                turn = math.remainder(direction - self.reference, 2.0 * math.pi)
                if abs(turn) > 0.5 * math.pi:
                    self._toggle()
                else:
                    self._steered_turn(turn, steering)
            self.reference = direction
        return course + math.pi if self.reversing else course

    def _steered_turn(self, turn: float, steering: float) -> None:
        """Add a turn of the course to the steering run; the direction is the other one if it went against."""
        side = 0 if abs(steering) < STEERED else (1 if steering > 0.0 else -1)
        if side != self.side:
            self.side, self.turned = side, 0.0
            return
        if side == 0:
            return
        self.turned += side * turn * (-1.0 if self.reversing else 1.0)
        if self.turned < -AGAINST_TURN:
            self._toggle()

    def _toggle(self) -> None:
        self.reversing = not self.reversing
        self.side, self.turned = 0, 0.0
