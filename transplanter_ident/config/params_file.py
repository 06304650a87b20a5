"""Load and validate the estimator's ROS 2 parameters YAML (DESIGN.md section 3; writing: params_writer).

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
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from transplanter_ident.config.keys import is_ros_builtin, unknown_key_message
from transplanter_ident.config.parameters import (
    EstimatorConfig,
    FilterOptions,
    NoiseParams,
    ValiditySettings,
    VehicleParams,
    check_fields,
)
from transplanter_ident.config.safe_yaml import (
    YamlLimitError,
    check_sealed,
    load_yaml_text,
    read_text_file,
    short_repr,
)
from transplanter_ident.config.schema import (
    FRAMES,
    PARAMS,
    SCHEMA,
    Param,
    default_values,
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
            value = getattr(self, name)
            if not value:
                raise ValueError(f"topics.{name} must be a non-empty topic name")
            if not is_topic_name(value):
                raise ValueError(f"topics.{name} {short_repr(value)} is not a valid ROS 2 topic name (letters, digits, "
                                 "_ and / only, a name part never starting with a digit, no // and no / at the end)")


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
    """Which joint of a sensor_msgs/JointState carries the steering angle, and how long an epoch waits for it."""

    joint_name: str = "front_steering"
    max_wait: float = 0.25  # s of GNSS stamp time an epoch waits for the steering to cover it

    def __post_init__(self) -> None:
        if not self.joint_name:
            raise ValueError("steering.joint_name must be a non-empty string")
        check_fields(self, "steering", non_negative=("max_wait",))


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


#: one part of a ROS 2 topic name: letters, digits and _ (not leading with a digit), or a {substitution}
_TOKEN = r"(?:[A-Za-z_]|\{[A-Za-z_][A-Za-z0-9_]*\})(?:[A-Za-z0-9_]|\{[A-Za-z_][A-Za-z0-9_]*\})*"
_TOPIC_NAME = re.compile(rf"(?:~|~?/?{_TOKEN}(?:/{_TOKEN})*)")


def is_topic_name(name: str) -> bool:
    """Whether ``name`` is a valid (unexpanded) ROS 2 topic name, as rcl_validate_topic_name decides."""
    return _TOPIC_NAME.fullmatch(name) is not None


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _convert_scalar(row: Param, value: Any) -> Any:
    key = row.key
    if row.kind == "str":
        if not isinstance(value, str):
            raise ParamsError(f"{key} must be a string, got {short_repr(value)}", key)
        if row.choices and row.match(value) is None:
            raise ParamsError(f"{key} must be one of {', '.join(row.choices)}, got {short_repr(value)}", key)
        return value
    if row.kind == "bool":
        if not isinstance(value, bool):
            raise ParamsError(f"{key} must be true or false, got {short_repr(value)}", key)
        return value
    if row.kind == "int" and not (is_number(value) and isinstance(value, int)):
        raise ParamsError(f"{key} must be an integer, got {short_repr(value)}", key)
    if not is_number(value):
        raise ParamsError(f"{key} must be a number, got {short_repr(value)}", key)
    number = value if row.kind == "int" else _to_float(key, value)
    _check_range(row, number, value)
    return number


def _to_float(key: str, value: int | float) -> float:
    try:
        return float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise ParamsError(f"{key}: {short_repr(value)} is out of the range of a float", key) from None


def _check_range(row: Param, number: float, value: Any) -> None:
    """The schema range (inclusive); NaN is outside every range. The message says which bound is missed."""
    if not row.has_range or row.low <= number <= row.high:
        return
    name = f"{row.key} entries" if row.kind == "float_list" else row.key
    span = f"[{row.low:g}, {row.high:g}]"
    if isinstance(number, float) and not math.isfinite(number):  # an int may be too large for a float
        need = f"must be finite numbers within {span}" if row.kind == "float_list" else f"must be finite, within {span}"
    elif number < row.low:
        need = f"must be >= {row.low:g} (within {span})"
    else:
        need = f"must be within {span}"
    raise ParamsError(f"{name} {need}, got {short_repr(value)}", row.key)


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
        raise ParamsError(f"{key} must be a list of {row.length} numbers, got {short_repr(value)}", key)
    if len(value) != row.length:
        raise ParamsError(f"{key} must have {row.length} entries, got {len(value)}", key)
    numbers = []
    for entry in value:
        if not is_number(entry):
            raise ParamsError(f"{key} entries must be numbers, got {short_repr(entry)}", key)
        numbers.append(_to_float(key, entry))
        _check_range(row, numbers[-1], entry)
    return tuple(numbers)


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
    parts = {"vehicle": _build(VehicleParams, sections["vehicle"]), "options": _build(FilterOptions, ekf),
             "noise": _build(NoiseParams, ekf)}
    config = _build(EstimatorConfig, parts)
    return EstimatorParams(
        config=config, topics=_build(TopicConfig, sections["topics"]), frames=_build(FrameConfig, sections["frames"]),
        steering=_build(SteeringConfig, sections["steering"]), gnss=_build(GnssConfig, sections["gnss"]),
        validity=_build(ValiditySettings, sections["validity"]), extra=extra)


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
            _check_list(value, key, source)
            out[key] = value


def _check_list(value: Any, key: str, source: str) -> None:
    """The rcl parser (so the node) refuses a list mixing integers and floats: so do we, offline too, naming it."""
    if not isinstance(value, list):
        return
    kinds = {type(v) for v in value}
    if int in kinds and float in kinds:
        raise ParamsError(f"{source}: {key} mixes integers and floats ({short_repr(value)}); the ROS 2 parameter "
                          "parser refuses such a list: write every entry as a float (1.0, not 1)", key)


def read_params_file(path: str | Path, node_name: str = "estimator", *,
                     require_section: bool = True) -> dict[str, Any]:
    """Read one params file: the flat parameters of ``/**`` overlaid with those of ``node_name``.

    Read safely (:mod:`.safe_yaml`: size, aliases, nesting); a file that says it was written by
    :mod:`.params_writer` must hold its closing line (:data:`~.safe_yaml.SEALED_LAST_LINE`), else it was cut short.
    A list that mixes integers and floats (``[1, 1.0e-4]``) is refused, as the rcl parser refuses it.
    ``require_section`` False: a file without a section for ``node_name`` gives no parameters instead
    of an error (the node: rcl applies none of it).
    """
    try:
        text = read_text_file(path)
        check_sealed(text)  # first: a file cut short is also often invalid YAML, but being cut is the cause
        document = load_yaml_text(text)
    except OSError as exc:
        raise ParamsError(f"{path}: cannot read parameters file: {exc.strerror or exc}") from None
    except YamlLimitError as exc:
        raise ParamsError(f"{path}: {exc}") from None
    if document is None:
        raise ParamsError(f"{path}: the file holds no parameters (empty)")
    if not isinstance(document, Mapping):
        raise ParamsError(f"{path}: top level must be a mapping of node names, got {type(document).__name__}")
    sections = [n for n in (WILDCARD, node_name, "/" + node_name.lstrip("/")) if n in document]
    if not sections and not require_section:
        return {}
    if not sections:
        found = short_repr(list(map(str, document))) if document else "nothing"
        raise ParamsError(f"{path}: no '{WILDCARD}' or '{node_name}' section (found: {found})")
    flat: dict[str, Any] = {}
    for section in dict.fromkeys(sections):
        body = document[section]
        if not isinstance(body, Mapping) or "ros__parameters" not in body:
            raise ParamsError(f"{path}: '{section}' must hold a 'ros__parameters' mapping")
        params = body["ros__parameters"] or {}
        if not isinstance(params, Mapping):
            raise ParamsError(f"{path}: '{section}.ros__parameters' must be a mapping, got {short_repr(params)}")
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


