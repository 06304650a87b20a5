"""Keys outside the schema: rclpy's own, and the message that names an unknown one (with the nearest known keys).

The schema itself is :mod:`.schema`; this module imports no ROS and no YAML.
"""

from __future__ import annotations

import difflib

from transplanter_ident.config.schema import PARAMS

#: parameters rclpy itself declares or reads; accepted everywhere and passed through untouched
ROS_BUILTIN_KEYS = ("use_sim_time", "start_type_description_service")
ROS_BUILTIN_PREFIXES = ("qos_overrides.",)


def is_ros_builtin(key: str) -> bool:
    """Parameters of rclpy itself (``use_sim_time``, QoS overrides): not ours to check."""
    return key in ROS_BUILTIN_KEYS or key.startswith(ROS_BUILTIN_PREFIXES)


def unknown_key_message(key: str) -> str:
    """One line naming an unknown key, with the nearest known keys (or the known ones of its namespace)."""
    group = [k.partition(".")[2] for k in PARAMS if k.startswith(key + ".")]
    if group:  # e.g. ``ekf: [1, 2]``: a value (a list) where a mapping of parameters belongs
        return (f"{key} is a group of parameters, not a value: write it as a mapping "
                f"({key}: {{{group[0]}: ...}}; known {key}.*: {', '.join(group)})")
    close = difflib.get_close_matches(key, PARAMS, n=3, cutoff=0.8)
    if close:
        return f"{key} is not a known parameter (did you mean {' or '.join(close)}?)"
    namespace = key.partition(".")[0] + "."
    same = [k for k in PARAMS if k.startswith(namespace)]
    if same:
        return f"{key} is not a known parameter (known {namespace}*: {', '.join(k.partition('.')[2] for k in same)})"
    spaces = ", ".join(dict.fromkeys(k.partition(".")[0] + ".*" for k in PARAMS))
    return f"{key} is not a known parameter (known: {spaces})"
