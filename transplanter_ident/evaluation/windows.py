"""Windows over time for the diagnostics: counts, RMS, latency percentiles, log throttling (bounded)."""

from __future__ import annotations

import math
import re
from collections import Counter, deque
from collections.abc import Iterable


class TimeWindow:
    """Event times within the last ``span`` seconds (amortised O(1) per event)."""

    def __init__(self, span: float) -> None:
        self.span = span
        self._times: deque[float] = deque()

    def add(self, now: float) -> None:
        self._times.append(now)
        self._trim(now)

    def count(self, now: float) -> int:
        self._trim(now)
        return len(self._times)

    def times(self, now: float) -> list[float]:
        self._trim(now)
        return list(self._times)

    def clear(self) -> None:
        self._times.clear()

    def _trim(self, now: float) -> None:
        times = self._times
        while times and times[0] < now - self.span:
            times.popleft()


class RollingRms:
    """RMS of (time, value) samples within the last ``span`` seconds of sample time."""

    def __init__(self, span: float) -> None:
        self.span = span
        self._samples: deque[tuple[float, float]] = deque()
        self._sum_sq = 0.0

    def add(self, t: float, value: float) -> None:
        if self._samples and t < self._samples[-1][0]:
            self.clear()  # time went backwards (a replayed bag restarted): start over
        self._samples.append((t, value * value))
        self._sum_sq += value * value
        while self._samples[0][0] < t - self.span:
            self._sum_sq -= self._samples.popleft()[1]
        if self._sum_sq < 0.0:  # rounding after many subtractions
            self._sum_sq = math.fsum(v for _, v in self._samples)

    def __len__(self) -> int:
        return len(self._samples)

    def rms(self) -> float:
        """The RMS, NaN when empty."""
        if not self._samples:
            return math.nan
        return math.sqrt(max(self._sum_sq, 0.0) / len(self._samples))

    def clear(self) -> None:
        self._samples.clear()
        self._sum_sq = 0.0


class LatencyStats:
    """The last ``size`` latencies (s): median and percentiles."""

    def __init__(self, size: int = 1000) -> None:
        self._values: deque[float] = deque(maxlen=size)
        self.total = 0

    def add(self, seconds: float) -> None:
        self._values.append(seconds)
        self.total += 1

    def __len__(self) -> int:
        return len(self._values)

    def percentile(self, q: float) -> float:
        """The q-th percentile (0..100, linear interpolation), NaN when empty."""
        return percentile(self._values, q)


def percentile(values: Iterable[float], q: float) -> float:
    """The q-th percentile (0..100) with linear interpolation between order statistics; NaN if empty."""
    data = sorted(values)
    if not data:
        return math.nan
    pos = (len(data) - 1) * min(max(q, 0.0), 100.0) / 100.0
    low = math.floor(pos)
    high = min(low + 1, len(data) - 1)
    return data[low] + (data[high] - data[low]) * (pos - low)


#: numbers in a message (incl. nan, inf): what varies between rejections of one class
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|\b(?:nan|inf(?:inity)?)\b", re.IGNORECASE)


def reason_class(reason: str) -> str:
    """A message with its numbers replaced by ``#``: "|0.812| rad beyond ..." and "|0.9| rad beyond ..." are one class.

    Log throttling is keyed by this, not by the text: keyed by the text, rejections that quote their
    values made one throttle entry each (101 MB/h of node memory, issue #14).
    """
    return _NUMBER.sub("#", reason)


class Throttle:
    """Allow one log line per key every ``period`` seconds; counts what was suppressed.

    Holds at most ``max_keys`` keys (the least recently logged one is forgotten first), so its
    memory is bounded whatever the keys are.
    """

    def __init__(self, period: float = 5.0, max_keys: int = 256) -> None:
        self.period = period
        self.max_keys = max_keys
        self._last: dict[object, float] = {}  # in the order of the last logged line, oldest first
        self._suppressed: Counter = Counter()

    def __len__(self) -> int:
        return len(self._last)

    def allow(self, key: object, now: float) -> tuple[bool, int]:
        """(log now?, how many were suppressed since the last line for this key)."""
        last = self._last.get(key)
        if last is not None and now - last < self.period:
            self._suppressed[key] += 1
            return False, 0
        self._last.pop(key, None)
        while len(self._last) >= self.max_keys:
            oldest = next(iter(self._last))
            del self._last[oldest]
            self._suppressed.pop(oldest, None)
        self._last[key] = now
        return True, self._suppressed.pop(key, 0)
