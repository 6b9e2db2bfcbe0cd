"""Declaring the exploration parameters on a node, with descriptions and ranges.

``declare_setting`` declares a node's own settings (not exploration parameters) the same
way. Every field of ``ExplorationParams`` becomes a read-only ROS parameter ``<group>.<field>``
(e.g. ``planner.name``, ``world.width_m``) with its description, unit and range, so
``ros2 param describe`` documents it and ``--params-file config/exploration.yaml`` sets it.
Deprecated names and values (``core.params.upgrade_deprecated``) are accepted with a warning
on the node's logger: a removed parameter is declared (so a file that sets it is no error)
and ignored.
"""
from __future__ import annotations

import dataclasses
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from em_exploration_ros.core.params import (REMOVED_PARAMETERS, ExplorationParams,
                                            upgrade_deprecated)
from em_exploration_ros.core.params_yaml import nest_dotted


def _descriptor(name: str, f: dataclasses.Field, default: Any) -> ParameterDescriptor:
    descriptor = ParameterDescriptor(name=name, description=f.metadata.get("description", ""),
                                     read_only=True)
    low, high, choices = (f.metadata.get(key) for key in ("low", "high", "choices"))
    if choices:
        descriptor.additional_constraints = "one of: " + ", ".join(choices)
    if low is not None and high is not None and not isinstance(default, bool):
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high),
                                                     step=0)]
        elif isinstance(default, float):
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=float(low), to_value=float(high), step=0.0)]
    return descriptor


def declare_exploration_params(node: Node) -> ExplorationParams:
    """Declare every exploration parameter on ``node`` and return their values.

    Raises ``ValueError`` (with the parameter's name) for a value the checks refuse; rclpy
    raises its own exception for a value outside a declared range. Deprecated parameters
    are upgraded with a warning on the node's logger.
    """
    defaults = ExplorationParams()
    values: dict[str, Any] = {}
    for group in dataclasses.fields(defaults):
        group_value = getattr(defaults, group.name)
        for f in dataclasses.fields(group_value):
            name = f"{group.name}.{f.name}"
            default = getattr(group_value, f.name)
            initial = list(default) if isinstance(default, tuple) else default
            parameter = node.declare_parameter(name, initial, _descriptor(name, f, default))
            values[name] = parameter.value
    for name, reason in REMOVED_PARAMETERS.items():
        descriptor = ParameterDescriptor(name=name, read_only=True, dynamic_typing=True,
                                         description=f"Deprecated and ignored ({reason}).")
        parameter = node.declare_parameter(name, None, descriptor)
        if parameter.value is not None:
            values[name] = parameter.value
    groups, messages = upgrade_deprecated(nest_dotted(values))
    for message in messages:
        node.get_logger().warning(message)
    return defaults.replace(**groups)


def declare_setting(node: Node, name: str, default: Any, description: str,
                    low: float | None = None, high: float | None = None) -> Any:
    """Declare a read-only node parameter (not an exploration parameter) and return its value.

    ``low``/``high`` give a floating-point range (for float defaults only).
    """
    descriptor = ParameterDescriptor(name=name, description=description, read_only=True)
    if low is not None and high is not None:
        descriptor.floating_point_range = [FloatingPointRange(from_value=float(low),
                                                              to_value=float(high), step=0.0)]
    return node.declare_parameter(name, default, descriptor).value
