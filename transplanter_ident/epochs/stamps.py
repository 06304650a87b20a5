"""Stamp outliers and time steps (issue #14): one far stamp never poisons what follows.

:class:`StampGuard` keeps, per input stream (velocity, heading, steering), the stamp of the last
sample that was used. A new stamp is *consistent* when it lies within ``max_jump`` (the
``gnss.max_stamp_jump`` parameter) of that stamp, or of the last used stamp of another stream
(so one input's gap, while the others carry on, is no outlier). GNSS stamps are compared as
motion times (stamp - ``gnss.delay``).

A stamp that is not consistent is an outlier and rejected; it never becomes the reference, so
one sample stamped in the future (or the past) leaves the stream as it was. When the clock
really stepped, the stream's following samples are outliers too, but consistent among
themselves: after :data:`RESYNC_SAMPLES` of them in a row the guard re-synchronises the stream
to the new time base by itself (no ``~/reset``), and says so.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

#: consecutive mutually consistent outliers after which a stream takes their time base
RESYNC_SAMPLES = 5


class Verdict(enum.Enum):
    """What the guard makes of a stamp."""

    CONSISTENT = 0  # use it (the caller still checks the order within the stream)
    OUTLIER = 1  # reject it; the stream keeps its time base
    RESYNC = 2  # the stream's time base stepped: forget the stream's state, then use the sample


@dataclass
class _Stream:
    last: float | None = None  # motion time of the last used sample
    candidates: list[float] = field(default_factory=list)  # consecutive outliers consistent among themselves


class StampGuard:
    """Per-stream stamp references with outlier rejection and automatic re-synchronisation."""

    def __init__(self, max_jump: float, resync_samples: int = RESYNC_SAMPLES) -> None:
        if not (math.isfinite(max_jump) and max_jump > 0.0):
            raise ValueError(f"gnss.max_stamp_jump must be a positive number of seconds, got {max_jump!r}")
        self.max_jump = max_jump
        self.resync_samples = max(1, int(resync_samples))
        self._streams: dict[str, _Stream] = {}

    def check(self, stream: str, t: float) -> tuple[Verdict, str]:
        """Judge the (motion) time ``t`` of a new sample of ``stream``; (verdict, reason for the log)."""
        state = self._streams.setdefault(stream, _Stream())
        own = state.last
        others = [s.last for name, s in self._streams.items() if name != stream and s.last is not None]
        if self._near(t, own) or (own is None and not others):
            state.candidates.clear()
            return Verdict.CONSISTENT, ""
        if any(self._near(t, other) for other in others):
            state.candidates.clear()
            if own is not None and t < own:  # the others moved back in time before this stream did
                return Verdict.RESYNC, self._resync_reason(t, own, "as the other inputs did")
            return Verdict.CONSISTENT, ""  # a gap in this stream; the others vouch for the time
        reference = own if own is not None else max(others)
        candidates = state.candidates
        if candidates and 0.0 < t - candidates[-1] <= self.max_jump:
            candidates.append(t)
        else:
            candidates[:] = [t]
        if len(candidates) >= self.resync_samples:
            candidates.clear()
            return Verdict.RESYNC, self._resync_reason(t, reference, f"after {self.resync_samples} consistent samples")
        whose = "the previous sample" if own is not None else "the other inputs"
        return Verdict.OUTLIER, (f"stamp {t - reference:+.3f} s from {whose}, beyond gnss.max_stamp_jump "
                                 f"{self.max_jump:g} s: an outlier")

    def accept(self, stream: str, t: float) -> None:
        """The sample at motion time ``t`` was used: it is the stream's new reference."""
        state = self._streams.setdefault(stream, _Stream())
        state.last = t
        state.candidates.clear()

    def last(self, stream: str) -> float | None:
        """The motion time of the stream's last used sample."""
        state = self._streams.get(stream)
        return None if state is None else state.last

    def _near(self, t: float, reference: float | None) -> bool:
        return reference is not None and abs(t - reference) <= self.max_jump

    @staticmethod
    def _resync_reason(t: float, reference: float, why: str) -> str:
        return f"time base stepped by {t - reference:+.3f} s: re-synchronised {why} (gnss.max_stamp_jump)"
