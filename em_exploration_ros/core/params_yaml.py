"""Reading and writing exploration parameters as ROS 2 parameter YAML files.

The file format is the one ``--ros-args --params-file`` takes, so one file serves both
the ROS nodes and the ROS-free tools (em-sim, em-bench)::

    /**:
      ros__parameters:
        world:
          width_m: 100.0
        planner.name: EM_3          # dotted names work too

Node-specific sections (``/robot_0/em_robot:``) are merged after ``/**``. Plain nested
YAML without the ``ros__parameters`` wrapper (``{world: {width_m: 100.0}}``) is accepted too.

Everything in a file is checked before it is used: exploration parameters against
``core.params``, a node section's own settings (names without a group, e.g.
``robot_timeout_s`` under ``/em_world:``) against that node's table in
``core.node_settings``; integers are accepted where numbers are expected, and an unknown
name is refused with the closest valid one. A file must be a regular file of at most
``MAX_FILE_BYTES`` whose YAML expands to at most ``MAX_FILE_VALUES`` values nested at most
``MAX_FILE_DEPTH`` levels deep (anchors and aliases are allowed within that bound).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

import yaml

from em_exploration_ros.core.node_settings import NODE_SETTINGS, checked_settings
from em_exploration_ros.core.params import ExplorationParams, closest_name_hint, field_choices
from em_exploration_ros.core.untrusted_files import (FileTooLarge, NotRegularFile,
                                                    read_regular_file)
from em_exploration_ros.core.untrusted_yaml import load_yaml, shown_value

ROS_PARAMETERS_KEY = "ros__parameters"
#: ROS parameters every node has; allowed in any section of a parameter file.
NODE_SETTINGS_ANYWHERE = frozenset({"use_sim_time"})
#: Largest parameter file read [bytes]; the shipped one, every parameter with its
#: description, is about 15 KiB.
MAX_FILE_BYTES = 1 << 20
#: Most values (mapping entries and list items, each alias counted wherever it is used)
#: a parameter file may expand to: about as many as a file of ``MAX_FILE_BYTES`` without
#: aliases can hold, so anchors stay usable while a few lines of aliases of aliases
#: expanding to 1e9 values (an "alias bomb") are refused before anything walks them.
MAX_FILE_VALUES = 100_000
#: Deepest nesting of mappings and lists in a parameter file (``/**: ros__parameters:
#: group: field: [list]`` is 5 levels).
MAX_FILE_DEPTH = 32


class ParamsFileError(ValueError):
    """A parameter file that cannot be used; the message names the file and the problem."""


def load_params(path: str | Path, base: ExplorationParams | None = None,
                max_bytes: int = MAX_FILE_BYTES) -> ExplorationParams:
    """Parameters from a YAML file of at most ``max_bytes`` bytes, applied on top of ``base``
    (default: the paper's values)."""
    file_path = Path(path)
    text = _read_text(file_path, max_bytes)
    document = load_yaml(text, str(file_path), ParamsFileError)
    try:
        check_document(document)
        groups = nest_dotted(parameter_section(document))
        base = base or ExplorationParams()
        return base.replace(**groups) if groups else base
    except ValueError as error:
        raise ParamsFileError(f"{file_path}: {error}") from None


def _read_text(file_path: Path, max_bytes: int) -> str:
    """The text of the parameter file ``file_path``: a regular file of at most
    ``max_bytes`` bytes of UTF-8 (``ParamsFileError`` otherwise)."""
    try:
        data = read_regular_file(file_path, max_bytes)
    except NotRegularFile:
        raise ParamsFileError(f"parameter file {file_path} is not a regular file") from None
    except FileTooLarge:
        raise ParamsFileError(f"parameter file {file_path} is larger than "
                              f"{max_bytes // 1024} KiB") from None
    except OSError as error:
        raise ParamsFileError(f"cannot read parameter file {file_path}: {error.strerror}") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise ParamsFileError(f"{file_path} is not UTF-8 text (byte {error.start}: "
                              f"{error.reason})") from None


def check_document(document: Any) -> None:
    """``ValueError`` if a parsed YAML document expands to more than ``MAX_FILE_VALUES``
    values, nests deeper than ``MAX_FILE_DEPTH`` levels, or holds a list whose items are
    not all of one kind (booleans, integers, floats or strings; named by its place).

    Values are counted wherever an alias uses them, and the walk stops at the bound, so it
    takes at most ``MAX_FILE_VALUES`` steps whatever the aliases expand to. The ROS nodes
    read the same file with rcl's parser, which refuses a mixed list ("Sequence should be
    of same type"): a file em-sim takes would stop every node of run_team.sh."""
    pending: list[tuple[Any, int, str]] = [(document, 0, "")]
    count = 0
    while pending:
        value, depth, where = pending.pop()
        count += 1
        if count > MAX_FILE_VALUES:
            raise ValueError(f"the file expands to more than {MAX_FILE_VALUES} values "
                             "(YAML aliases of aliases?)")
        if depth > MAX_FILE_DEPTH:
            raise ValueError(f"the file nests deeper than {MAX_FILE_DEPTH} levels")
        if isinstance(value, Mapping):
            pending.extend((child, depth + 1, f"{where}.{key}" if where else str(key))
                           for key, child in value.items())
        elif isinstance(value, list):
            kinds = {_SCALAR_KINDS.get(type(item)) for item in value} - {None}
            if len(kinds) > 1:
                raise ValueError(
                    f"{where}: the list {shown_value(value)} mixes {' and '.join(sorted(kinds))}"
                    f"; a ROS 2 parameter file needs one type per list (e.g. 1.0, not 1, "
                    f"among floats)")
            pending.extend((child, depth + 1, where) for child in value)


#: The kinds of list items rcl's parameter-file parser tells apart.
_SCALAR_KINDS = {bool: "booleans", int: "integers", float: "floats", str: "strings"}


def parameter_section(document: Any) -> dict[str, Any]:
    """The exploration parameters of a parsed YAML document (``{'group.field': value}``).

    ``ros__parameters`` sections are merged, the ``/**`` wildcard first. Node settings
    that are not exploration parameters are checked (``check_node_settings``) and skipped:
    ``use_sim_time`` anywhere, and names without a group (e.g. ``robot_timeout_s``) in
    node-specific sections such as ``/em_world:``. Everything else must name an
    exploration parameter.
    """
    if document is None:
        return {}
    if not isinstance(document, Mapping):
        raise ValueError("the top level must be a mapping")
    sections = [key for key, value in document.items()
                if isinstance(value, Mapping) and ROS_PARAMETERS_KEY in value]
    if not sections:
        return _exploration_only(flatten(document), node_specific=False)
    merged: dict[str, Any] = {}
    for key in sorted(sections, key=lambda key: key != "/**"):
        section = document[key][ROS_PARAMETERS_KEY] or {}
        if not isinstance(section, Mapping):
            raise ValueError(f"{key}.{ROS_PARAMETERS_KEY} must be a mapping")
        flat = flatten(section)
        node_specific = not _is_wildcard(key)
        if node_specific:
            check_node_settings(key, flat)
        merged.update(_exploration_only(flat, node_specific))
    return merged


def section_node_name(key: str) -> str:
    """The node name a section key applies to: its last path component
    (``/robot_0/em_robot`` -> ``em_robot``)."""
    return str(key).rstrip("/").rsplit("/", 1)[-1]


def _is_wildcard(key: str) -> bool:
    return "*" in section_node_name(key)


def check_node_settings(key: str, values: Mapping[str, Any]) -> None:
    """``ValueError`` if a node section ``key`` names no node of this system, or its own
    settings (names without a group) are unknown to that node or have a wrong type or
    value (the closest valid name is suggested)."""
    node = section_node_name(key)
    if node not in NODE_SETTINGS:
        raise ValueError(f"section '{key}' names no node of this system "
                         f"('{node}'{closest_name_hint(node, NODE_SETTINGS)}; nodes: "
                         f"{', '.join(NODE_SETTINGS)})")
    own = {name: value for name, value in values.items()
           if "." not in name and name not in NODE_SETTINGS_ANYWHERE}
    try:
        checked_settings(NODE_SETTINGS[node], own)
    except ValueError as error:
        raise ValueError(f"section '{key}': {error}") from None


def _exploration_only(values: dict[str, Any], node_specific: bool) -> dict[str, Any]:
    """``values`` without the node settings described in ``parameter_section``."""
    return {name: value for name, value in values.items()
            if name not in NODE_SETTINGS_ANYWHERE and (not node_specific or "." in name)}


def flatten(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings as ``{'a.b.c': value}``."""
    flat: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = value
    return flat


def nest_dotted(values: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """``{'group.field': v}`` (or already nested) as ``{group: {field: v}}``."""
    groups: dict[str, dict[str, Any]] = {}
    for name, value in flatten(values).items():
        group, _, field_name = name.partition(".")
        if not field_name:
            raise ValueError(f"parameter '{name}' has no group (expected e.g. 'world.width_m'; "
                             f"a node's own settings go in its section, e.g. /em_world)")
        groups.setdefault(group, {})[field_name] = value
    return groups


def dump_params(params: ExplorationParams, node_pattern: str = "/**") -> str:
    """The parameters as a ROS 2 parameter YAML document, each with its description and
    range as a comment (tuples become lists)."""
    lines = [f"{node_pattern}:", f"  {ROS_PARAMETERS_KEY}:"]
    for group in dataclasses.fields(params):
        group_value = getattr(params, group.name)
        lines.append(f"    {group.name}:")
        for f in dataclasses.fields(group_value):
            value = getattr(group_value, f.name)
            value = list(value) if isinstance(value, tuple) else value
            rendered = yaml.safe_dump(value, default_flow_style=True).strip()
            rendered = rendered.removesuffix("\n...").strip()
            lines.append(f"      # {_describe(f)}")
            lines.append(f"      {f.name}: {rendered}")
    return "\n".join(lines) + "\n"


def _describe(f: dataclasses.Field) -> str:
    """One-line description of a parameter with its range or choices."""
    text = f.metadata.get("description", "")
    choices, low, high = field_choices(f), f.metadata.get("low"), f.metadata.get("high")
    if choices:
        text += f" One of: {', '.join(choices)}."
    elif low is not None or high is not None:
        text += f" Range [{low}, {high}]."
    return text
