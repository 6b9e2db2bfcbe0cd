"""A small YAML emitter that writes block style the way yaml-cpp's ``YAML::Dump`` does.

rosbag2 serializes its metadata and QoS profiles with yaml-cpp; emitting the same layout
keeps recorded files byte-comparable with rosbag2's output for the same content:
two-space indentation, sequence items indented under their key (``key:\\n  - item``),
empty collections in flow style on the next line (``key:\\n  []``), null as ``~`` and
empty strings as ``""``. Only maps, sequences, strings, integers, booleans and None occur.
"""
from __future__ import annotations

import json
import re
from typing import Any, Mapping, Sequence

_PLAIN_STRING = re.compile(r"^[A-Za-z_/][A-Za-z0-9_/.\-]*$")
_YAML_WORDS = frozenset({"true", "false", "yes", "no", "on", "off", "null", "y", "n"})


def _scalar(value: Any) -> str:
    if value is None:
        return "~"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        if _PLAIN_STRING.match(value) and value.lower() not in _YAML_WORDS:
            return value
        return json.dumps(value)
    raise TypeError(f"cannot emit {type(value).__name__} as a YAML scalar")


def _is_collection(value: Any) -> bool:
    return isinstance(value, (Mapping, list, tuple))


def _map_lines(node: Mapping[str, Any], indent: int) -> list[str]:
    pad = " " * indent
    lines = []
    for key, value in node.items():
        if not _is_collection(value):
            lines.append(f"{pad}{key}: {_scalar(value)}")
            continue
        lines.append(f"{pad}{key}:")
        lines.extend(_block_lines(value, indent + 2))
    return lines


def _sequence_lines(node: Sequence[Any], indent: int) -> list[str]:
    pad = " " * indent
    lines = []
    for item in node:
        if isinstance(item, Mapping) and item:
            item_lines = _map_lines(item, indent + 2)
            lines.append(f"{pad}- {item_lines[0][indent + 2:]}")
            lines.extend(item_lines[1:])
        elif _is_collection(item):
            raise TypeError("nested sequences and empty maps in sequences are not supported")
        else:
            lines.append(f"{pad}- {_scalar(item)}")
    return lines


def _block_lines(node: Any, indent: int) -> list[str]:
    if isinstance(node, Mapping):
        return _map_lines(node, indent) if node else [" " * indent + "{}"]
    if isinstance(node, (list, tuple)):
        return _sequence_lines(node, indent) if node else [" " * indent + "[]"]
    return [" " * indent + _scalar(node)]


def dump_block(node: Any) -> str:
    """YAML text of ``node`` in yaml-cpp's block layout, without a trailing newline."""
    return "\n".join(_block_lines(node, 0))
