"""rclpy glue shared by em-record, em-replay and em-foxglove: message classes and schemas,
topic discovery, QoS conversion, CLI args."""
from __future__ import annotations

import argparse
import importlib
import math
import sys
from collections.abc import Container, Iterator, Mapping
from typing import Any, Callable

import re2
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy)
from rclpy.topic_endpoint_info import TopicEndpointInfo

from em_exploration_ros.bag_format.interface_index import find_interface_file, split_type_name
from em_exploration_ros.bag_format.mcap_ros2_schema import (
    DefinitionNotFoundError, MessageDefinition, build_message_definition)
from em_exploration_ros.bag_format.qos_yaml import DURATION_INFINITE_NS, QosProfile
from em_exploration_ros.bag_format.topic_selection import (
    TopicPatternError, TopicSelection, compile_topic_pattern)

_POLICY_ENUMS: dict[str, Any] = {
    "history": HistoryPolicy, "reliability": ReliabilityPolicy,
    "durability": DurabilityPolicy, "liveliness": LivelinessPolicy}


ROS_ARGS_FLAG = "--ros-args"


class MessageTypeError(LookupError):
    """A message type is not installed (its Python package cannot be imported)."""


def import_message_class(type_name: str) -> type:
    """The Python class of ``pkg/msg/Type``; raises MessageTypeError if it is not installed.

    The name may come from a recording, so nothing is imported unless the ament index lists
    the package with that message's definition: a schema named ``antigravity/msg/X`` would
    otherwise import (and run) whatever Python module has that name. The imported object
    must be a generated message class."""
    package, namespace, name = split_type_name(type_name)
    if namespace != "msg" or not any(find_interface_file(type_name, extension)
                                     for extension in (".msg", ".idl")):
        raise MessageTypeError(f"message type {type_name} is not installed (no message "
                               f"definition of it in the ament index)")
    try:
        message_class = getattr(importlib.import_module(f"{package}.{namespace}"), name)
    except (ImportError, AttributeError) as error:
        raise MessageTypeError(f"message type {type_name} is not installed ({error})") from None
    if not (isinstance(message_class, type)
            and hasattr(message_class, "get_fields_and_field_types")):
        raise MessageTypeError(f"{type_name} is not a generated message class")
    return message_class


def message_type_support(type_name: str) -> tuple[type, MessageDefinition]:
    """The Python class and the complete definition (schema text) of ``pkg/msg/Type``;
    raises MessageTypeError if either is not installed."""
    try:
        return import_message_class(type_name), build_message_definition(type_name)
    except DefinitionNotFoundError as error:
        raise MessageTypeError(str(error)) from None


#: The ROS graph's topics with their types, as ``Node.get_topic_names_and_types`` gives them.
TopicGraph = list[tuple[str, list[str]]]


def new_selected_topics(node: Node, graph: TopicGraph, selection: TopicSelection,
                        known: Container[str]
                        ) -> Iterator[tuple[str, list[str], list[TopicEndpointInfo]]]:
    """``(topic, types, publishers)`` of every topic of ``graph`` (``node``'s view of the ROS
    graph) that ``selection`` takes, that is not in ``known`` and that has publishers now."""
    for topic, types in graph:
        if topic in known or not selection.matches(topic):
            continue
        publishers = node.get_publishers_info_by_topic(topic)
        if publishers:
            yield topic, types, publishers


def other_types_of_taken_topics(graph: TopicGraph, taken: Mapping[str, str],
                                reported: set[tuple[str, str]]) -> list[str]:
    """One line for every type a taken topic (``taken``: topic -> the type a tool records
    or serves it as) now carries besides that one, once per topic and type (``reported``
    holds what was said): em-record and em-foxglove keep a topic's first type, and its
    messages of another type would otherwise be missing without a word."""
    lines = []
    for topic, types in graph:
        kept = taken.get(topic)
        for other in types:
            if kept is not None and other != kept and (topic, other) not in reported:
                reported.add((topic, other))
                lines.append(f"{topic} now carries {other} too; only {kept} is taken "
                             f"(messages of {other} are left out)")
    return lines


def _policy_name(value: Any) -> str:
    return value.name.lower()


def _duration_ns(duration: Duration) -> int:
    return min(duration.nanoseconds, DURATION_INFINITE_NS)


def qos_from_rclpy(profile: QoSProfile) -> QosProfile:
    """An endpoint's rclpy QoS profile as a bag QoS profile (rmw policy names, ns)."""
    return QosProfile(
        history=_policy_name(profile.history), depth=profile.depth,
        reliability=_policy_name(profile.reliability),
        durability=_policy_name(profile.durability),
        deadline_ns=_duration_ns(profile.deadline), lifespan_ns=_duration_ns(profile.lifespan),
        liveliness=_policy_name(profile.liveliness),
        liveliness_lease_duration_ns=_duration_ns(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=profile.avoid_ros_namespace_conventions)


def _finite_duration(ns: int) -> Duration:
    """Durations that are infinite or unspecified stay unspecified (0): always accepted."""
    return Duration(nanoseconds=0 if ns >= DURATION_INFINITE_NS else ns)


def qos_to_rclpy(profile: QosProfile) -> QoSProfile:
    """A bag QoS profile as an rclpy QoSProfile for creating an endpoint."""
    policies = {key: enum[getattr(profile, key).upper()] for key, enum in _POLICY_ENUMS.items()}
    return QoSProfile(
        depth=profile.depth, deadline=_finite_duration(profile.deadline_ns),
        lifespan=_finite_duration(profile.lifespan_ns),
        liveliness_lease_duration=_finite_duration(profile.liveliness_lease_duration_ns),
        avoid_ros_namespace_conventions=profile.avoid_ros_namespace_conventions, **policies)


def cli_args(argv: list[str] | None) -> tuple[list[str], list[str]]:
    """Split a command line into (argv for rclpy.init, the tool's own arguments).

    ROS arguments are those from ``--ros-args`` on; everything before belongs to the tool,
    so tool options such as ``--remap /a:=/b`` are not mistaken for legacy ROS remap rules.
    """
    full = list(sys.argv if argv is None else argv)
    split = full.index(ROS_ARGS_FLAG) if ROS_ARGS_FLAG in full else len(full)
    return [full[0], *full[split:]], full[1:split]


def number_type(kind: type, *, allow_zero: bool = False, low: float | None = None,
                high: float | None = None) -> Callable[[str], Any]:
    """An argparse ``type``: a finite positive (or, with ``allow_zero``, non-negative)
    ``kind``, at most ``high`` and, unless 0, at least ``low`` where given (bounds keep the
    times and counts computed from it representable)."""
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if isinstance(value, float) and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        if value < 0 or (value == 0 and not allow_zero):
            bound = "non-negative" if allow_zero else "positive"
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        if value > 0 and low is not None and value < low:
            zero = "0 or " if allow_zero else ""
            raise argparse.ArgumentTypeError(f"must be {zero}at least {low:g}, got {text}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"must be at most {high:g}, got {text}")
        return value
    return parse


def topic_pattern(text: str) -> re2._Regexp | None:
    """The argparse ``type`` of ``--regex`` and ``--exclude``: the expression compiled with
    RE2 (None for an empty one); one refused names itself and RE2's reason."""
    try:
        return compile_topic_pattern(text)
    except TopicPatternError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def add_topic_expression_arguments(parser: argparse.ArgumentParser, verb: str,
                                   include_help: str, include_default: str | None = None
                                   ) -> None:
    """``--regex`` and ``--exclude`` of a tool that ``verb``s topics (record, play, serve),
    parsed by ``topic_pattern``; ``include_help`` says what ``--regex`` does."""
    parser.add_argument("--regex", type=topic_pattern, default=include_default, metavar="RE",
                        help=f"{include_help} (RE2 syntax)")
    parser.add_argument("--exclude", type=topic_pattern, default=None, metavar="RE",
                        help=f"never {verb} topics matching this regular expression (RE2 "
                        "syntax)")
