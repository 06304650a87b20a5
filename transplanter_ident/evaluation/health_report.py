"""One /diagnostics status line and its levels (those of ``diagnostic_msgs/DiagnosticStatus``).

Shared by :mod:`.health` and the reports it assembles (:mod:`.convergence_report`,
:mod:`.identifiability_report`), and by the node, which maps each line onto a DiagnosticStatus.
"""

from __future__ import annotations

from dataclasses import dataclass

OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}


@dataclass(frozen=True)
class HealthReport:
    """One status line for the dashboard (maps 1:1 onto a DiagnosticStatus)."""

    name: str
    level: int
    message: str
    values: tuple[tuple[str, str], ...] = ()

    @property
    def level_name(self) -> str:
        return LEVEL_NAMES[self.level]

    def value(self, key: str) -> str:
        """The value of one key (KeyError if absent)."""
        return dict(self.values)[key]
