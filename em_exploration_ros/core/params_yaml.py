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
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

import yaml

from em_exploration_ros.core.params import ExplorationParams

ROS_PARAMETERS_KEY = "ros__parameters"
#: ROS parameters every node has; allowed in any section of a parameter file.
NODE_SETTINGS_ANYWHERE = frozenset({"use_sim_time"})


class ParamsFileError(ValueError):
    """A parameter file that cannot be used; the message names the file and the problem."""


def load_params(path: str | Path, base: ExplorationParams | None = None) -> ExplorationParams:
    """Parameters from a YAML file, applied on top of ``base`` (default: the paper's values)."""
    file_path = Path(path)
    try:
        text = file_path.read_text(encoding="utf-8")
    except OSError as error:
        raise ParamsFileError(f"cannot read parameter file {file_path}: {error.strerror}") from None
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ParamsFileError(f"{file_path} is not valid YAML: {error}") from None
    try:
        groups = nest_dotted(parameter_section(document))
        base = base or ExplorationParams()
        return base.replace(**groups) if groups else base
    except ValueError as error:
        raise ParamsFileError(f"{file_path}: {error}") from None


def parameter_section(document: Any) -> dict[str, Any]:
    """The exploration parameters of a parsed YAML document (``{'group.field': value}``).

    ``ros__parameters`` sections are merged, the ``/**`` wildcard first. Node settings
    that are not exploration parameters are skipped: ``use_sim_time`` anywhere, and names
    without a group (e.g. ``robot_timeout_s``) in node-specific sections such as
    ``/em_world:``. Everything else must name an exploration parameter.
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
        merged.update(_exploration_only(flatten(section), node_specific=key != "/**"))
    return merged


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
            raise ValueError(f"parameter '{name}' has no group (expected e.g. 'world.width_m')")
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
    choices, low, high = (f.metadata.get(key) for key in ("choices", "low", "high"))
    if choices:
        text += f" One of: {', '.join(choices)}."
    elif low is not None or high is not None:
        text += f" Range [{low}, {high}]."
    return text
