"""A single antenna's heading from its own velocity (``ekf.measurement: course``), forwards and reversing.

One antenna measures the direction of its velocity, not of the vehicle: driving forwards that is the
heading plus the antenna's small sideslip (the filter models it, :mod:`..ekf.measurement_row`);
reversing, it points backwards. Through a stop the velocity's direction flips by about pi, which the
course alone shows: :class:`CourseTracker` compares each velocity fast enough for its direction to be
sure (``REVERSAL_SPEED``) with the last such one, and a turn of more than pi/2 between the two is a
change of direction (the vehicle does not turn that far while it stops). Reversing, the epoch's heading
is the course + pi and its speed negative, so the filter holds the stiffness as with a heading
(StepStatus.REVERSING). A log that starts while reversing is taken as forwards until the next stop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: m/s: below it a 0.02 m/s velocity error turns the course by more than 4 degrees (no reference then)
REVERSAL_SPEED = 0.3


@dataclass
class CourseTracker:
    """Which way the vehicle moves, from the directions of its antenna's velocity (one stream, in order)."""

    reversing: bool = False
    reference: float | None = None  # rad: the direction of the last velocity of REVERSAL_SPEED or more

    def heading(self, east: float, north: float) -> float:
        """The vehicle's heading (ENU yaw) for this velocity: its direction, + pi while reversing."""
        course = math.atan2(north, east)
        if math.hypot(east, north) >= REVERSAL_SPEED:
            if self.reference is not None and abs(math.remainder(course - self.reference, 2.0 * math.pi)) > 0.5 * math.pi:
                self.reversing = not self.reversing
            self.reference = course
        return course + math.pi if self.reversing else course
