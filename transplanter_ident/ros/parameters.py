"""The node's parameters from the schema: declarations, ParameterDescriptors, overrides and validation.

Everything here derives from config/schema.py: the default each key is declared with, its
ParameterDescriptor (description with the unit, FloatingPointRange / IntegerRange, read-only,
the choices as additional constraints), the check of the overrides a node got at start-up
(``--params-file`` and ``-p``: an unknown key is an error naming it; an integer where a float is due
becomes a float, since rclpy would refuse it), and :func:`validate`, which turns a complete set
of values into the :class:`NodeSettings` the node runs with. Validation is that of the offline
drivers (:func:`transplanter_ident.config.params_file.flat_to_params`), so a file the node refuses
is refused by ``replay`` and ``tuner`` too, with the same reason.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.parameter import Parameter

from transplanter_ident.config.keys import is_ros_builtin
from transplanter_ident.config.params_file import (
    NODE_ONLY_KEYS,
    EstimatorParams,
    ParamsError,
    convert_value,
    flat_to_params,
    params_to_flat,
)
from transplanter_ident.config.schema import PARAMS, SCHEMA, default_values
from transplanter_ident.epochs.settings import INPUT_ROLES
from transplanter_ident.evaluation.health import HealthThresholds

ODOMETRY = "nav_msgs/msg/Odometry"


def ros_value(value: Any) -> Any:
    """A schema value as rclpy declares it (tuples become lists)."""
    return list(value) if isinstance(value, tuple) else value


def plain(value: Any) -> Any:
    """A parameter value as a plain Python value (arrays become lists)."""
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    return list(value)


def parameter_defaults() -> dict[str, Any]:
    """Every parameter the node declares, with its default."""
    return {row.key: ros_value(row.default) for row in SCHEMA}


#: the parameters that only the node reads (no dataclass of config/ holds them), with their defaults
NODE_PARAMETERS: dict[str, Any] = {key: ros_value(PARAMS[key].default) for key in NODE_ONLY_KEYS}


def is_read_only(name: str) -> bool:
    """Whether ``name`` is fixed at start-up (topics, frames, vehicle, the filter's structure, ...)."""
    return PARAMS[name].read_only


def descriptor_for(name: str, default: Any = None) -> ParameterDescriptor:
    """The ParameterDescriptor the node declares ``name`` with (``default`` is ignored; kept for callers)."""
    row = PARAMS[name]
    descriptor = ParameterDescriptor(description=row.help_text(), read_only=row.read_only)
    if row.has_range and row.kind == "float":
        descriptor.floating_point_range = [FloatingPointRange(from_value=float(row.low), to_value=float(row.high),
                                                              step=0.0)]
    elif row.has_range and row.kind == "int":
        descriptor.integer_range = [IntegerRange(from_value=int(row.low), to_value=int(row.high), step=1)]
    if row.choices:
        descriptor.additional_constraints = "one of " + ", ".join(row.choices)
    return descriptor


def start_values(overrides: Mapping[str, Parameter]) -> dict[str, Any]:
    """The value to declare each schema key with: its override (converted to the schema's type) or default.

    ``overrides`` are the node's parameter overrides (``Node._parameter_overrides``: ``--params-file``
    and ``-p``). Raises ParamsError naming the first unknown key, or a value of the wrong type.
    """
    values = parameter_defaults()
    for name, parameter in overrides.items():
        if not is_ros_builtin(name):
            values[name] = ros_value(convert_value(name, plain(parameter.value)))
    return values


def coerce(parameters: list[Parameter]) -> list[Parameter]:
    """Integers set at run time where the schema wants floats (or float lists) become floats; others unchanged."""
    out = []
    for parameter in parameters:
        row = PARAMS.get(parameter.name)
        if row is not None and row.kind == "float" and parameter.type_ == Parameter.Type.INTEGER:
            parameter = Parameter(parameter.name, value=float(parameter.value))
        elif row is not None and row.kind == "float_list" and parameter.type_ == Parameter.Type.INTEGER_ARRAY:
            parameter = Parameter(parameter.name, value=[float(v) for v in parameter.value])
        out.append(parameter)
    return out


@dataclass(frozen=True)
class NodeSettings:
    """A validated, complete set of the node's parameters."""

    params: EstimatorParams
    thresholds: HealthThresholds
    message_types: dict[str, str]  # role (velocity, heading, steering) -> 'pkg/msg/Type'
    diagnostics_period: float
    latency_log: str
    frame_id: str


def validate(flat: Mapping[str, Any]) -> NodeSettings:
    """Check a set of parameter values (missing keys: defaults); raises ParamsError naming the key and the reason."""
    params = flat_to_params(flat)
    values = {**default_values(), **params_to_flat(params)}
    message_types = {role: str(PARAMS[f"topics.{role}_type"].match(values[f"topics.{role}_type"])) for role in INPUT_ROLES}
    if params.topics.velocity == params.topics.heading and not (
            message_types["velocity"] == message_types["heading"] == ODOMETRY):
        raise ParamsError(f"topics.velocity and topics.heading are both {params.topics.velocity}: only one "
                          "nav_msgs/Odometry topic can serve both (set topics.velocity_type and topics.heading_type "
                          "to Odometry, or name two topics)", "topics.heading")
    return NodeSettings(
        params=params,
        thresholds=health_thresholds(values),
        message_types=message_types,
        diagnostics_period=float(values["diagnostics.period"]),
        latency_log=str(values["diagnostics.latency_log"]),
        frame_id=str(values["output.frame_id"]),
    )


def health_thresholds(values: Mapping[str, Any]) -> HealthThresholds:
    """HealthThresholds from the ``diagnostics.<field>`` keys of ``values``."""
    try:
        return HealthThresholds(**{f.name: values[f"diagnostics.{f.name}"] for f in
                                   dataclasses.fields(HealthThresholds)})
    except ValueError as exc:
        raise ParamsError(str(exc), str(exc).split(" ", 1)[0]) from None
