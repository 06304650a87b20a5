"""One row of the parameter schema (:mod:`.schema`): a key's type, default, unit, range or choices, description.

The row checks itself: its default has its kind, lies in its range and is one of its choices.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

KINDS = ("float", "int", "bool", "str", "float_list")

Value = float | int | bool | str | tuple[float, ...]


@dataclass(frozen=True)
class Param:
    """One parameter: dotted key, type, default, unit, range or choices, description, read-only flag."""

    key: str
    kind: str
    default: Value
    unit: str = ""
    description: str = ""
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = True

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"{self.key}: kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if not _default_has_kind(self.default, self.kind):
            raise ValueError(f"{self.key}: default {self.default!r} is not of kind {self.kind}")
        if self.choices and self.match(str(self.default)) is None:
            raise ValueError(f"{self.key}: default {self.default!r} is not one of its choices")
        entries = self.default if isinstance(self.default, tuple) else (self.default,)
        if self.has_range and not all(self.low <= v <= self.high for v in entries):
            raise ValueError(f"{self.key}: default {self.default!r} is outside [{self.low}, {self.high}]")

    @property
    def length(self) -> int | None:
        """The number of entries of a ``float_list`` (None for scalars)."""
        return len(self.default) if isinstance(self.default, tuple) else None

    @property
    def has_range(self) -> bool:
        return self.low is not None and self.high is not None

    def match(self, value: str) -> str | None:
        """The choice that ``value`` names (full, ``pkg/Type`` or bare ``Type`` for message types), or None."""
        for choice in self.choices:
            if value in (choice, choice.replace("/msg/", "/"), choice.rsplit("/", 1)[-1]):
                return choice
        return None

    def help_text(self) -> str:
        """The description with the unit (and a list's range), as the node's ParameterDescriptor shows it."""
        text = self.description + (f" [{self.unit}]" if self.unit else "")
        if self.kind == "float_list" and self.has_range:  # rclpy checks FloatingPointRange on scalars only
            text += f"; entries within [{self.low:g}, {self.high:g}]"
        return text


def _default_has_kind(default: Any, kind: str) -> bool:
    if kind == "float_list":
        return isinstance(default, tuple) and len(default) > 0 and all(type(v) is float for v in default)
    return type(default) is {"float": float, "int": int, "bool": bool, "str": str}[kind]
