"""Input-side diagnostics (issues #12 and #14): GNSS velocity/heading pairing and rejections counted by kind.

:class:`PairingMonitor` turns the assembler's :class:`~transplanter_ident.epochs.pairing.PairingStats`
into the ``<node>: GNSS pairing`` status line: an ERROR as soon as velocity and heading stop
pairing (three samples given up since the last pair, i.e. within one GNSS period), saying by how
much their stamps miss and naming ``gnss.pairing_tolerance``; a WARN while some samples go
unpaired; OK otherwise. :func:`kind_values` lists rejection counts per kind as diagnostic values.
No ROS types; ``now`` is the node's monotonic clock.
"""

from __future__ import annotations

from collections import Counter

from transplanter_ident.epochs.pairing import PairingStats
from transplanter_ident.evaluation.windows import TimeWindow

OK, WARN, ERROR = 0, 1, 2
#: samples given up since the last pair that make the pairing an ERROR (more than one epoch's velocity + heading)
UNPAIRED_ERROR = 3


def kind_values(kinds: Counter) -> tuple[tuple[str, str], ...]:
    """``(rejected_<kind>, count)`` per rejection kind seen, sorted by kind."""
    return tuple((f"rejected_{kind}", str(n)) for kind, n in sorted(kinds.items()))


class PairingMonitor:
    """How the GNSS velocity and heading pair; fed the assembler's running counts."""

    def __init__(self, window: float) -> None:
        self.window = window
        self._pairs = TimeWindow(window)
        self._misses = TimeWindow(window)
        self._stats: PairingStats | None = None
        self._seen = (0, 0)  # pairs, misses of the stats object already counted
        self.misses_since_pair = 0

    def set_window(self, window: float) -> None:
        self.window = self._pairs.span = self._misses.span = window

    def update(self, stats: PairingStats, now: float) -> None:
        """Count what the assembler paired and gave up since the last call (a new stats object: a reset)."""
        if stats is not self._stats:
            self._stats, self._seen = stats, (0, 0)
        new_pairs, new_misses = stats.pairs - self._seen[0], stats.misses - self._seen[1]
        if not (new_pairs or new_misses):
            return
        self._seen = (stats.pairs, stats.misses)
        for _ in range(min(new_pairs, 1000)):
            self._pairs.add(now)
        for _ in range(min(new_misses, 1000)):
            self._misses.add(now)
        self.misses_since_pair = 0 if new_pairs else self.misses_since_pair + new_misses

    def report(self, now: float) -> tuple[int, str, tuple[tuple[str, str], ...]]:
        """(level, message, values) of the pairing status line."""
        stats = self._stats
        if stats is None or not (stats.pairs or stats.misses):
            return OK, "no GNSS sample yet", ()
        tolerance_ms = 1e3 * stats.tolerance
        recent_misses = self._misses.count(now)
        values = (("paired", str(stats.pairs)), ("unpaired", str(stats.misses)), ("surplus", str(stats.surplus)),
                  ("unpaired_recent", str(recent_misses)), ("unpaired_since_pair", str(self.misses_since_pair)),
                  ("pairing_tolerance_ms", f"{tolerance_ms:g}"), ("largest_miss_ms", f"{1e3 * stats.largest_miss:.1f}"),
                  ("last_offset_ms", "none" if stats.last_offset is None else f"{1e3 * stats.last_offset:+.1f}"))
        if self.misses_since_pair >= UNPAIRED_ERROR:
            return ERROR, self._unpaired_message(stats, tolerance_ms), values
        if recent_misses:
            return WARN, (f"{recent_misses} GNSS sample(s) without a partner within gnss.pairing_tolerance "
                          f"{tolerance_ms:g} ms in the last {self.window:g} s"), values
        return OK, f"velocity and heading pair ({self._pairs.count(now)} epochs in the last {self.window:g} s)", values

    @staticmethod
    def _unpaired_message(stats: PairingStats, tolerance_ms: float) -> str:
        if stats.last_offset is None:
            return (f"velocity and heading do not pair: no partner stamp within gnss.pairing_tolerance "
                    f"{tolerance_ms:g} ms")
        miss_ms = 1e3 * abs(stats.last_offset)
        later = "after" if stats.last_offset > 0 else "before"
        return (f"velocity and heading do not pair: their stamps miss by {miss_ms:.0f} ms (heading {later} the "
                f"velocity; up to {1e3 * stats.largest_miss:.0f} ms), beyond gnss.pairing_tolerance {tolerance_ms:g} "
                f"ms: if they are one receiver epoch, set gnss.pairing_tolerance above "
                f"{1e3 * stats.largest_miss:.0f} ms; nothing is estimated meanwhile")
