"""Load, validate and write the estimator's ROS 2 parameters YAML (DESIGN.md section 3).

The file format is the one `--params-file` takes::

    estimator:
      ros__parameters:
        vehicle: {mass: 720.0, ...}
        ekf: {process_noise: [1.0e-4, ...], ...}

Nested mappings under ``ros__parameters`` are flattened to dotted keys (``ekf.process_noise``)
exactly as rclpy does. Layering follows ROS 2 closely: files apply in the order given and a later
file overrides an earlier one key by key; inside one file the ``/**`` section applies first and the
node's own section (``estimator`` or ``/estimator``) overrides it. (rcl itself merges all files'
``/**`` sections before all node sections; the simpler per-file rule above only differs when a later
file's ``/**`` sets a key that an earlier file set under the node name.)

Which keys exist, their types, ranges and choices come from the schema (:mod:`.schema`): an unknown
key is an error that names it, whatever its namespace; an integer is accepted where a float is due.
Every error is a :class:`ParamsError` whose one-line message names the file, the key and the reason.
This module does not import rclpy.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from transplanter_ident.config.parameters import (
    EstimatorConfig,
    FilterOptions,
    NoiseParams,
    ValiditySettings,
    VehicleParams,
)
from transplanter_ident.config.schema import (
    FRAMES,
    PARAMS,
    SCHEMA,
    Param,
    default_values,
    is_ros_builtin,
    unknown_key_message,
)

WILDCARD = "/**"


class ParamsError(ValueError):
    """A bad parameters file or value; ``key`` is the dotted key at fault (or None)."""

    def __init__(self, message: str, key: str | None = None) -> None:
        super().__init__(" ".join(str(message).split("\n")))
        self.key = key


@dataclass(frozen=True)
class TopicConfig:
    """Input topic names."""

    velocity: str = "/gnss/vel"
    heading: str = "/gnss/heading"
    steering: str = "/steering_angle"

    def __post_init__(self) -> None:
        for name in ("velocity", "heading", "steering"):
            if not getattr(self, name):
                raise ValueError(f"topics.{name} must be a non-empty topic name")


@dataclass(frozen=True)
class FrameConfig:
    """Frames of the GNSS velocity and heading: ``enu`` or ``ned`` (compass heading)."""

    velocity: str = "enu"
    heading: str = "enu"

    def __post_init__(self) -> None:
        for name in ("velocity", "heading"):
            if getattr(self, name) not in FRAMES:
                raise ValueError(f"frames.{name} must be one of enu, ned, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class SteeringConfig:
    """Which joint of a sensor_msgs/JointState carries the steering angle."""

    joint_name: str = "front_steering"

    def __post_init__(self) -> None:
        if not self.joint_name:
            raise ValueError("steering.joint_name must be a non-empty string")


@dataclass(frozen=True)
class GnssConfig:
    """GNSS timing: how the receiver's stamps relate to the motion they describe."""

    delay: float = 0.0  # s: velocity and heading stamped t describe the motion at t - delay
    pairing_tolerance: float = 0.05  # s: the most a velocity and a heading stamp of one epoch may differ
    max_stamp_jump: float = 1.0  # s: a sample stamped further from the others is an outlier

    def __post_init__(self) -> None:
        if not (math.isfinite(self.delay) and -1.0 <= self.delay <= 10.0):
            raise ValueError(f"gnss.delay must be a finite number of seconds in [-1, 10], got {self.delay!r}")
        if not (math.isfinite(self.pairing_tolerance) and 0.0 < self.pairing_tolerance <= 1.0):
            raise ValueError(f"gnss.pairing_tolerance must be in (0, 1] s, got {self.pairing_tolerance!r}")
        if not (math.isfinite(self.max_stamp_jump) and self.max_stamp_jump > 0.0):
            raise ValueError(f"gnss.max_stamp_jump must be a positive number of seconds, got {self.max_stamp_jump!r}")


@dataclass(frozen=True)
class EstimatorParams:
    """Everything the parameters file holds; ``extra`` keeps the other schema keys flat (``diagnostics.x``)."""

    config: EstimatorConfig = field(default_factory=EstimatorConfig)
    topics: TopicConfig = field(default_factory=TopicConfig)
    frames: FrameConfig = field(default_factory=FrameConfig)
    steering: SteeringConfig = field(default_factory=SteeringConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    validity: ValiditySettings = field(default_factory=ValiditySettings)
    extra: dict[str, Any] = field(default_factory=dict)


# namespace -> (dataclass, where it lives in EstimatorParams); "ekf" is split over two dataclasses.
_SECTIONS: dict[str, tuple[type, ...]] = {
    "vehicle": (VehicleParams,),
    "ekf": (FilterOptions, NoiseParams),
    "topics": (TopicConfig,),
    "frames": (FrameConfig,),
    "steering": (SteeringConfig,),
    "gnss": (GnssConfig,),
    "validity": (ValiditySettings,),
}


def _field_names(cls: type) -> frozenset[str]:
    return frozenset(f.name for f in dataclasses.fields(cls))


#: dotted key -> default value, for every key of the schema (config/schema.py)
KNOWN_KEYS: dict[str, Any] = default_values()
#: keys written as YAML integers; every other number is written as a float.
INT_KEYS = frozenset(row.key for row in SCHEMA if row.kind == "int")
#: schema keys that a dataclass field holds
DATACLASS_KEYS = frozenset(f"{ns}.{name}" for ns, classes in _SECTIONS.items() for cls in classes
                           for name in _field_names(cls))
#: schema keys that no dataclass holds (message types, diagnostics, output frame): kept in ``extra``
NODE_ONLY_KEYS = tuple(row.key for row in SCHEMA if row.key not in DATACLASS_KEYS)


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _convert_scalar(row: Param, value: Any) -> Any:
    key = row.key
    if row.kind == "str":
        if not isinstance(value, str):
            raise ParamsError(f"{key} must be a string, got {value!r}", key)
        if row.choices and row.match(value) is None:
            raise ParamsError(f"{key} must be one of {', '.join(row.choices)}, got {value!r}", key)
        return value
    if row.kind == "bool":
        if not isinstance(value, bool):
            raise ParamsError(f"{key} must be true or false, got {value!r}", key)
        return value
    if row.kind == "int" and not (is_number(value) and isinstance(value, int)):
        raise ParamsError(f"{key} must be an integer, got {value!r}", key)
    if not is_number(value):
        raise ParamsError(f"{key} must be a number, got {value!r}", key)
    number = value if row.kind == "int" else float(value)
    if row.has_range and not row.low <= number <= row.high:
        raise ParamsError(f"{key} must be within [{row.low:g}, {row.high:g}], got {value!r}", key)
    return number


def convert_value(key: str, value: Any) -> Any:
    """Check one value against the schema; integers become floats where floats are due, lists tuples.

    Raises ParamsError naming the key: unknown key, wrong type or length, out of range, not a choice.
    """
    row = PARAMS.get(key)
    if row is None:
        raise ParamsError(unknown_key_message(key), key)
    if row.kind != "float_list":
        return _convert_scalar(row, value)
    if not isinstance(value, (list, tuple)):
        raise ParamsError(f"{key} must be a list of {row.length} numbers, got {value!r}", key)
    if len(value) != row.length:
        raise ParamsError(f"{key} must have {row.length} entries, got {len(value)}", key)
    for entry in value:
        if not is_number(entry):
            raise ParamsError(f"{key} entries must be numbers, got {entry!r}", key)
    return tuple(float(entry) for entry in value)


def _build(cls: type, values: Mapping[str, Any]) -> Any:
    """Construct one dataclass from the values that belong to it, re-raising its ValueError as ParamsError."""
    names = _field_names(cls)
    try:
        return cls(**{k: v for k, v in values.items() if k in names})
    except ValueError as exc:
        message = str(exc)
        raise ParamsError(message, message.split(" ", 1)[0]) from None


def flat_to_params(flat: Mapping[str, Any]) -> EstimatorParams:
    """Build validated parameters from flat dotted keys; missing keys keep their defaults.

    Every key must be in the schema (config/schema.py), else a ParamsError names it; rclpy's own
    parameters (``use_sim_time``, ``qos_overrides.*``) pass through. Schema keys that no dataclass
    holds (``topics.*_type``, ``diagnostics.*``, ``output.frame_id``) go to ``extra``, converted.
    """
    sections: dict[str, dict[str, Any]] = {ns: {} for ns in _SECTIONS}
    extra: dict[str, Any] = {}
    for key, value in flat.items():
        if is_ros_builtin(key):
            extra[key] = value
            continue
        converted = convert_value(key, value)
        if key in NODE_ONLY_KEYS:
            extra[key] = converted
        else:
            namespace, _, name = key.partition(".")
            sections[namespace][name] = converted

    ekf = sections["ekf"]
    config = EstimatorConfig(
        vehicle=_build(VehicleParams, sections["vehicle"]),
        options=_build(FilterOptions, ekf),
        noise=_build(NoiseParams, ekf),
    )
    return EstimatorParams(
        config=config,
        topics=_build(TopicConfig, sections["topics"]),
        frames=_build(FrameConfig, sections["frames"]),
        steering=_build(SteeringConfig, sections["steering"]),
        gnss=_build(GnssConfig, sections["gnss"]),
        validity=_build(ValiditySettings, sections["validity"]),
        extra=extra,
    )


def parameter_value(params: EstimatorParams, key: str) -> Any:
    """The value of one schema key in ``params`` (its default when the parameters did not set it)."""
    return params_to_flat(params).get(key, PARAMS[key].default)


def params_to_flat(p: EstimatorParams) -> dict[str, Any]:
    """Flatten parameters to dotted keys (tuples become lists); the inverse of :func:`flat_to_params`."""
    objects = {
        "vehicle": (p.config.vehicle,),
        "ekf": (p.config.options, p.config.noise),
        "topics": (p.topics,),
        "frames": (p.frames,),
        "steering": (p.steering,),
        "gnss": (p.gnss,),
        "validity": (p.validity,),
    }
    flat: dict[str, Any] = {}
    for namespace, objs in objects.items():
        for obj in objs:
            for f in dataclasses.fields(obj):
                value = getattr(obj, f.name)
                flat[f"{namespace}.{f.name}"] = list(value) if isinstance(value, tuple) else value
    flat.update(p.extra)
    return flat


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads YAML 1.2 floats such as ``1e-4`` as numbers, as the rcl parser does."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _flatten(mapping: Mapping[Any, Any], prefix: str, out: dict[str, Any], source: str) -> None:
    for name, value in mapping.items():
        key = f"{prefix}{name}"
        if not isinstance(name, str):
            raise ParamsError(f"{source}: parameter name {key!r} is not a string", key)
        if isinstance(value, Mapping):
            _flatten(value, key + ".", out, source)
        elif value is None:
            raise ParamsError(f"{source}: {key} has no value", key)
        else:
            out[key] = value


def read_params_file(path: str | Path, node_name: str = "estimator") -> dict[str, Any]:
    """Read one params file: the flat parameters of ``/**`` overlaid with those of ``node_name``."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ParamsError(f"{path}: cannot read parameters file: {exc.strerror or exc}") from None
    try:
        document = yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        reason = getattr(exc, "problem", None) or type(exc).__name__
        raise ParamsError(f"{path}: invalid YAML{where}: {reason}") from None
    if not isinstance(document, Mapping):
        raise ParamsError(f"{path}: top level must be a mapping of node names, got {type(document).__name__}")
    sections = [n for n in (WILDCARD, node_name, "/" + node_name.lstrip("/")) if n in document]
    if not sections:
        found = ", ".join(map(str, document)) or "nothing"
        raise ParamsError(f"{path}: no '{WILDCARD}' or '{node_name}' section (found: {found})")
    flat: dict[str, Any] = {}
    for section in dict.fromkeys(sections):
        body = document[section]
        if not isinstance(body, Mapping) or "ros__parameters" not in body:
            raise ParamsError(f"{path}: '{section}' must hold a 'ros__parameters' mapping")
        params = body["ros__parameters"] or {}
        if not isinstance(params, Mapping):
            raise ParamsError(f"{path}: '{section}.ros__parameters' must be a mapping, got {params!r}")
        _flatten(params, "", flat, str(path))
    return flat


def load_params(paths: Sequence[str | Path], node_name: str = "estimator") -> EstimatorParams:
    """Layer params files in order (later files override earlier ones per key) and validate the result."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    merged: dict[str, Any] = {}
    for path in paths:
        flat = read_params_file(path, node_name)
        try:
            flat_to_params(flat)
        except ParamsError as exc:
            raise ParamsError(f"{path}: {exc}", exc.key) from None
        merged.update(flat)
    try:
        return flat_to_params(merged)
    except ParamsError as exc:
        raise ParamsError(f"{', '.join(map(str, paths))}: {exc}", exc.key) from None


