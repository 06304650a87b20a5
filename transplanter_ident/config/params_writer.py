"""Writing the estimator's ROS 2 parameters YAML (DESIGN.md section 3), atomically.

Every number of a float key is written as a float (the rcl parser rejects mixed int/float
lists); integer keys of the schema stay integers. The tuner's output goes through here.

Every file is sealed: its first line (``SEALED_FIRST_LINE``) says that it is complete only if it
holds the last line ``# end``, and :func:`~.params_file.read_params_file` refuses such a file without
it: a tuned file cut mid-number (``1.0e-08`` cut to ``1.``) would otherwise load as another value.
Hand-written files (no such first line) are not affected; editing a sealed file by hand is fine.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from transplanter_ident.config.params_file import INT_KEYS, ParamsError, flat_to_params, is_number
from transplanter_ident.config.safe_yaml import SEALED_FIRST_LINE, SEALED_LAST_LINE, Loader
from transplanter_ident.files import atomic_write_text


def _format_scalar(key: str, value: Any, *, as_int: bool = False) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if is_number(value):
        if as_int and isinstance(value, int):
            return str(value)
        number = float(value)
        if not math.isfinite(number):
            raise ParamsError(f"{key} must be finite, got {value!r}", key)
        text = repr(number)
        if "e" in text and "." not in text:
            text = text.replace("e", ".0e")
        return text
    if isinstance(value, str):
        plain = re.fullmatch(r"[A-Za-z_/~][A-Za-z0-9_/.~-]*", value) is not None
        if plain and yaml.load(value, Loader=Loader) == value:
            return value
        return json.dumps(value)
    raise ParamsError(f"{key} has an unsupported type {type(value).__name__}", key)


def _format_value(key: str, value: Any) -> str:
    if isinstance(value, (list, tuple)):
        if not value:
            raise ParamsError(f"{key} must not be an empty list (rcl cannot type it)", key)
        kinds = {"number" if is_number(v) else type(v).__name__ for v in value}
        if len(kinds) != 1 or kinds - {"number", "str", "bool"}:
            raise ParamsError(f"{key} must be a list of numbers, strings or booleans, not mixed", key)
        return "[" + ", ".join(_format_scalar(key, v) for v in value) + "]"
    return _format_scalar(key, value, as_int=key in INT_KEYS)


def dump_params_yaml(flat: Mapping[str, Any], header_comment: str = "", node_name: str = "estimator") -> str:
    """Render flat dotted keys as a nested ``node_name: ros__parameters:`` YAML document."""
    tree: dict[str, Any] = {}
    for key, value in flat.items():
        node = tree
        *parents, leaf = key.split(".")
        for part in parents:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ParamsError(f"{key} clashes with the parameter {part}", key)
            node = child
        if leaf in node:
            raise ParamsError(f"{key} clashes with a parameter namespace of the same name", key)
        node[leaf] = _format_value(key, value)
    lines = [SEALED_FIRST_LINE, *(f"# {line}".rstrip() for line in header_comment.splitlines())]
    lines += [f"{node_name}:", "  ros__parameters:"]

    def emit(node: dict[str, Any], indent: int) -> None:
        for name, value in node.items():
            if isinstance(value, dict):
                lines.append(f"{' ' * indent}{name}:")
                emit(value, indent + 2)
            else:
                lines.append(f"{' ' * indent}{name}: {value}")

    emit(tree, 4)
    lines.append(SEALED_LAST_LINE)
    return "\n".join(lines) + "\n"


def write_params_yaml(
    path: str | Path, flat: Mapping[str, Any], header_comment: str, node_name: str = "estimator"
) -> None:
    """Validate ``flat`` and write it atomically (temp file in the same directory, then rename).

    Every number is written as a float except integer parameters (``ekf.max_gated``); lists are in
    flow style. On any failure the temp file is removed and the target is left untouched.
    """
    flat_to_params(flat)
    atomic_write_text(path, dump_params_yaml(flat, header_comment, node_name))
