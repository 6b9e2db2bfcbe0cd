"""Declaring the exploration parameters and a node's own settings, checked, read-only.

Every field of ``ExplorationParams`` becomes a read-only ROS parameter ``<group>.<field>``
(e.g. ``planner.name``, ``world.width_m``) and every field of the node's settings table
(``core.node_settings``) a read-only parameter of its own name, each with its
description, unit and range, so ``ros2 param describe`` documents it, ``--params-file``
sets it and ``ros2 param set`` is refused (the nodes read them once).

A value given at start (parameter file, ``-p``) goes through the checks of
``core.params`` before it is declared, so an integer where a float is expected
(``width_m: 60``) is taken as a float and a wrong type (``robot_timeout_s: "abc"``) or
an out-of-range value is a ``ValueError`` naming the parameter, which ``node_main``
turns into exit code 2 without a traceback. ``refuse_unknown_overrides`` refuses a
value given for a parameter the node does not have (a typo), naming the closest one.
Deprecated names and values (``core.params.upgrade_deprecated``) are accepted with a
warning on the node's logger: a removed parameter is declared (so a file that sets it is
no error) and ignored.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from em_exploration_ros.core.params import (REMOVED_PARAMETERS, ExplorationParams,
                                            closest_name_hint, field_choices, replace_checked,
                                            upgrade_deprecated)
from em_exploration_ros.core.params_yaml import NODE_SETTINGS_ANYWHERE, nest_dotted

#: Parameters rclpy itself may take from a parameter file besides the declared ones.
_RCLPY_PREFIXES = ("qos_overrides.",)


def _descriptor(name: str, f: dataclasses.Field, default: Any) -> ParameterDescriptor:
    descriptor = ParameterDescriptor(name=name, description=f.metadata.get("description", ""),
                                     read_only=True)
    low, high, choices = f.metadata.get("low"), f.metadata.get("high"), field_choices(f)
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


def _overrides(node: Node) -> dict[str, Any]:
    """The values given to ``node`` at start (parameter files, ``-p``), by name. rclpy keeps
    them in the node's private ``_parameter_overrides`` and has no public accessor."""
    return {name: parameter.value
            for name, parameter in node._parameter_overrides.items()}  # noqa: SLF001


def _declare_table(node: Node, table: Any, given: Mapping[str, Any], prefix: str = "") -> Any:
    """Declare every field of the dataclass instance ``table`` as ``<prefix><field>``, the
    values ``given`` at start (by field name) checked and coerced first; returns ``table``
    with those values."""
    for name, value in given.items():
        try:
            table = replace_checked(table, {name: value})
        except ValueError as error:
            raise ValueError(f"parameter {prefix}{name}: {error}") from None
    for f in dataclasses.fields(table):
        name = prefix + f.name
        value = getattr(table, f.name)
        initial = list(value) if isinstance(value, tuple) else value
        node.declare_parameter(name, initial, _descriptor(name, f, f.default),
                               ignore_override=True)
    return table


def declare_exploration_params(node: Node) -> ExplorationParams:
    """Declare every exploration parameter on ``node`` and return their values
    (``ValueError`` naming the parameter for a value the checks refuse). Deprecated
    parameters are upgraded with a warning on the node's logger."""
    defaults = ExplorationParams()
    names = set(defaults.flat()) | set(REMOVED_PARAMETERS)
    given, messages = upgrade_deprecated(nest_dotted(
        {name: value for name, value in _overrides(node).items() if name in names}))
    for message in messages:
        node.get_logger().warning(message)
    for name, reason in REMOVED_PARAMETERS.items():
        descriptor = ParameterDescriptor(name=name, read_only=True, dynamic_typing=True,
                                         description=f"Deprecated and ignored ({reason}).")
        node.declare_parameter(name, None, descriptor)
    groups = {group.name: _declare_table(node, getattr(defaults, group.name),
                                         given.get(group.name, {}), f"{group.name}.")
              for group in dataclasses.fields(defaults)}
    return dataclasses.replace(defaults, **groups)


def declare_node_settings(node: Node, settings_type: type) -> Any:
    """Declare the node's own settings (a table of ``core.node_settings``) and return them."""
    fields = {f.name for f in dataclasses.fields(settings_type)}
    given = {name: value for name, value in _overrides(node).items() if name in fields}
    return _declare_table(node, settings_type(), given)


def refuse_unknown_overrides(node: Node) -> None:
    """``ValueError`` if a value was given for a parameter ``node`` has not declared (call
    it at the end of the constructor), naming the closest declared parameter."""
    declared = node.list_parameters([], 0).names
    for name in sorted(_overrides(node)):
        if node.has_parameter(name) or name in NODE_SETTINGS_ANYWHERE or name.startswith(
                _RCLPY_PREFIXES):
            continue
        raise ValueError(f"unknown parameter '{name}'{closest_name_hint(name, declared)} "
                         f"for node {node.get_name()}")
