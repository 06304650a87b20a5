"""Pairing the GNSS velocity and heading of one receiver epoch by stamp (issue #12, item 2).

Velocity and heading may come from different messages and clocks (ublox: the velocity carries the
receiver's GNSS time, the heading is stamped on arrival 35-45 ms later). A velocity and a heading
belong to the same epoch when their stamps differ by at most ``gnss.pairing_tolerance``.

:class:`GnssPairer` holds the samples that wait for their partner. Stamps of one stream strictly
increase (the assembler rejects the others), so a velocity older than the newest heading minus the
tolerance can never pair any more: it is given up at once, with the offset to the nearest heading,
so the diagnostics can say within one GNSS period by how much the two miss. Nothing is dropped
silently; the queues are bounded.

A stream that runs faster than its partner (velocity at 10 Hz, a dual-antenna heading at 5 Hz)
leaves samples that no partner exists for: those are *surplus* (:attr:`Unpaired.surplus`, its recent
rate at least :data:`SURPLUS_RATE_RATIO` x the other's), a set-up, not a fault, and counted apart.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

ROLES = ("velocity", "heading")
#: samples of one stream waiting for a partner (a silent partner topic cannot grow memory)
CAPACITY = 32
#: recent stamps per stream, to find the nearest partner of a sample given up and the streams' rates
RECENT = 8
#: a sample given up is surplus when its stream's recent rate is at least this times its partner's
SURPLUS_RATE_RATIO = 1.5


@dataclass(frozen=True)
class Unpaired:
    """A sample given up without a partner: ``offset`` = nearest partner stamp - its stamp (None: no partner seen)."""

    role: str
    stamp: float
    offset: float | None
    surplus: bool = False  # its stream runs faster than the partner's: no partner exists for it


@dataclass
class PairingStats:
    """Counts since the start: epochs paired, samples given up, and the offset of the latest miss."""

    pairs: int = 0
    misses: int = 0  # not counting the surplus
    surplus: int = 0  # samples of the faster stream given up (Unpaired.surplus)
    last_offset: float | None = None  # s, heading stamp - velocity stamp of the nearest partner
    largest_miss: float = 0.0  # s, the largest |offset| of a miss with a partner in sight
    tolerance: float = 0.0


class GnssPairer:
    """Waiting velocity and heading samples; :meth:`add` returns the pairs completed and the samples given up."""

    def __init__(self, tolerance: float) -> None:
        self.tolerance = tolerance
        self.stats = PairingStats(tolerance=tolerance)
        self._waiting: dict[str, deque[tuple[float, Any]]] = {role: deque() for role in ROLES}
        self._recent: dict[str, deque[float]] = {role: deque(maxlen=RECENT) for role in ROLES}

    def newest(self, role: str) -> float | None:
        """The stamp of the newest waiting sample of ``role`` (None when none waits)."""
        waiting = self._waiting[role]
        return waiting[-1][0] if waiting else None

    def clear(self, role: str) -> None:
        """Forget the waiting samples of ``role`` and the recent stamps of both (a time base stepped)."""
        self._waiting[role].clear()
        for recent in self._recent.values():
            recent.clear()

    def add(self, role: str, stamp: float, payload: Any) -> tuple[list[tuple[float, Any, Any]], list[Unpaired]]:
        """Queue a sample; returns ([(velocity stamp, velocity payload, heading payload)], [given up])."""
        given_up: list[Unpaired] = []
        waiting = self._waiting[role]
        if len(waiting) >= CAPACITY:
            old_stamp, _ = waiting.popleft()
            given_up.append(self._miss(role, old_stamp))
        waiting.append((stamp, payload))
        self._recent[role].append(stamp)
        pairs = self._match(given_up)
        given_up += self._prune()
        return pairs, given_up

    def _match(self, given_up: list[Unpaired]) -> list[tuple[float, Any, Any]]:
        velocity, heading = self._waiting["velocity"], self._waiting["heading"]
        for vi, (tv, v_payload) in enumerate(velocity):
            for hi, (th, h_payload) in enumerate(heading):
                if abs(tv - th) <= self.tolerance:
                    for _ in range(vi):
                        given_up.append(self._miss("velocity", velocity.popleft()[0]))
                    for _ in range(hi):
                        given_up.append(self._miss("heading", heading.popleft()[0]))
                    velocity.popleft()
                    heading.popleft()
                    self.stats.pairs += 1
                    return [(tv, v_payload, h_payload)]
        return []

    def _prune(self) -> list[Unpaired]:
        """Give up the samples that no later partner can reach (stamps of a stream only increase)."""
        given_up = []
        for role, other in (("velocity", "heading"), ("heading", "velocity")):
            if not self._recent[other]:
                continue
            horizon = self._recent[other][-1] - self.tolerance
            waiting = self._waiting[role]
            while waiting and waiting[0][0] < horizon:
                given_up.append(self._miss(role, waiting.popleft()[0]))
        return given_up

    def _miss(self, role: str, stamp: float) -> Unpaired:
        other = "heading" if role == "velocity" else "velocity"
        partners = self._recent[other]
        offset = min((p - stamp for p in partners), key=abs) if partners else None
        if offset is not None and role == "heading":
            offset = -offset  # always heading - velocity
        own_rate, other_rate = _rate(self._recent[role]), _rate(partners)
        if own_rate > 0.0 and other_rate > 0.0 and own_rate >= SURPLUS_RATE_RATIO * other_rate:
            self.stats.surplus += 1
            return Unpaired(role, stamp, offset, surplus=True)
        self.stats.misses += 1
        if offset is not None:
            self.stats.last_offset = offset
            self.stats.largest_miss = max(self.stats.largest_miss, abs(offset))
        return Unpaired(role, stamp, offset)


def _rate(stamps: deque[float]) -> float:
    """Samples per second over the recent stamps of a stream (0 with fewer than three, or no span)."""
    if len(stamps) < 3 or not stamps[-1] > stamps[0]:
        return 0.0
    return (len(stamps) - 1) / (stamps[-1] - stamps[0])
