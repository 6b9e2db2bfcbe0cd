"""Complete message definitions for MCAP schemas, built the way rosbag2 (Jazzy) builds them.

rosbag2's ``LocalMessageDefinitionSource`` stores, for a topic type ``pkg/msg/Type``, the
type's ``.msg`` text followed by every type it depends on (recursively, each once, depth
first, dependencies of one file in sorted order), each preceded by a newline, a line of 80
``=`` and a line ``MSG: <name>``, where ``<name>`` is the dependency as the field declares it
(``geometry_msgs/Pose``; a field type without package gets the declaring package). Schema
encoding ``ros2msg``. If a ``.msg`` file is missing the whole definition falls back to the
``.idl`` files (encoding ``ros2idl``), where every text, the root's included, is preceded by
the delimiter with ``IDL: pkg/msg/Type``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Callable

from em_exploration_ros.bag_format.interface_index import find_interface_file, split_type_name

#: Schema encodings (MCAP well-known names).
ENCODING_MSG = "ros2msg"
ENCODING_IDL = "ros2idl"

DELIMITER_LINE = "=" * 80

#: Maximum dependency depth (rosbag2's LOCAL_MESSAGE_DEFINITION_SOURCE_MAX_RECURSION_DEPTH).
MAX_RECURSION_DEPTH = 50

# A field type at the start of a line: "foo_msgs/Bar" in "foo_msgs/Bar[] bar" (rosbag2's regex).
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_IDL_INCLUDE = re.compile(r"(?:^|\n)#include\s+(?:\"|<)([a-zA-Z0-9_/]+)\.idl(?:\"|>)")

# Built-in field types. rosbag2's list lacks ``wstring`` (it then looks for a message named
# wstring and falls back to IDL); here wstring is a primitive, which keeps ros2msg text.
_PRIMITIVE_TYPES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string", "wstring"})


class DefinitionNotFoundError(LookupError):
    """No installed definition file for a type (the interface package is not installed)."""


@dataclass(frozen=True)
class MessageDefinition:
    """A complete message definition: what goes into an MCAP Schema record.

    ``type_name`` is the schema name (``pkg/msg/Type``), ``encoding`` the schema encoding
    and ``text`` the schema data (UTF-8 text).
    """

    type_name: str
    encoding: str
    text: str


def parse_msg_dependencies(text: str, package: str) -> list[str]:
    """Non-primitive field types of a ``.msg`` text, sorted, as ``pkg/Type`` (or as written)."""
    found = set()
    for match in _MSG_FIELD_TYPE.finditer(text):
        field_type = match.group(1)
        if field_type in _PRIMITIVE_TYPES:
            continue
        found.add(field_type if "/" in field_type else f"{package}/{field_type}")
    return sorted(found)


def parse_idl_dependencies(text: str) -> list[str]:
    """Types included by an ``.idl`` text, sorted, as ``pkg/msg/Type``."""
    return sorted({match.group(1) for match in _IDL_INCLUDE.finditer(text)})


def _read_definition(type_name: str, extension: str) -> str:
    path = find_interface_file(type_name, extension)
    if path is None:
        raise DefinitionNotFoundError(f"no {extension} definition installed for {type_name}")
    return path.read_text(encoding="utf-8")


def _full_text(root: str, extension: str, tag: str,
               dependencies: Callable[[str, str], list[str]]) -> str:
    """Root text plus each dependency once (depth first), each after its delimiter."""
    seen: set[str] = set()

    def append(type_name: str, depth: int) -> str:
        if depth <= 0:
            raise RecursionError(f"dependencies of {root} nest deeper than {MAX_RECURSION_DEPTH}")
        text = _read_definition(type_name, extension)
        package = split_type_name(type_name)[0]
        for dependency in dependencies(text, package):
            if dependency not in seen:
                seen.add(dependency)
                text += f"\n{DELIMITER_LINE}\n{tag}: {dependency}\n" + append(dependency, depth - 1)
        return text

    return append(root, MAX_RECURSION_DEPTH)


def build_message_definition(type_name: str) -> MessageDefinition:
    """The complete definition of an installed message type, as rosbag2 records it.

    Raises ``DefinitionNotFoundError`` if neither the ``.msg`` nor the ``.idl`` files of the
    type and all its dependencies are installed, and ``InterfaceNameError`` for a malformed
    type name.
    """
    split_type_name(type_name)
    try:
        text = _full_text(type_name, ".msg", "MSG", parse_msg_dependencies)
        return MessageDefinition(type_name, ENCODING_MSG, text)
    except DefinitionNotFoundError:
        text = _full_text(type_name, ".idl", "IDL",
                          lambda idl, _package: parse_idl_dependencies(idl))
        return MessageDefinition(
            type_name, ENCODING_IDL, f"{DELIMITER_LINE}\nIDL: {type_name}\n{text}")



def _definition_line(line: str) -> str:
    """A ``ros2msg`` line without its comment (a string constant keeps its whole value,
    which may hold ``#``)."""
    stripped = line.strip()
    head = stripped.split("#", 1)[0]
    if "=" in head and head.split()[0] in ("string", "wstring"):
        return stripped
    return head.strip()


def same_layout(recorded_text: str, recorded_encoding: str,
                installed: MessageDefinition) -> bool:
    """True when a recorded schema declares the same fields, types, defaults and constants
    in the same order as the installed definition, so its messages are read correctly with
    the installed type. ``ros2msg`` texts are compared without comments and blank lines,
    other encodings exactly."""
    if recorded_encoding != installed.encoding:
        return False
    if installed.encoding != ENCODING_MSG:
        return recorded_text == installed.text

    def layout(text: str) -> list[str]:
        return [line for line in map(_definition_line, text.splitlines()) if line]

    return layout(recorded_text) == layout(installed.text)
