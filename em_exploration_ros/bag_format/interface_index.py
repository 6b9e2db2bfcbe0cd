"""Locate installed ROS interface files (.msg, .idl, type-description .json) via the ament index.

An interface package is installed under a prefix listed in ``AMENT_PREFIX_PATH``: the prefix
holds the marker ``share/ament_index/resource_index/packages/<pkg>`` and the definitions in
``share/<pkg>/msg/<Type>.msg`` (``.idl`` and ``.json`` beside it). The Python interpreter's
own prefix (a virtual environment with ROS wheels lays out an ament prefix at its root) is
searched after the listed prefixes.
"""
from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

_NAME = r"[a-zA-Z][a-zA-Z0-9_]*"
_TYPE_WITH_NAMESPACE = re.compile(rf"^({_NAME})/({_NAME})/({_NAME})$")
_TYPE_WITHOUT_NAMESPACE = re.compile(rf"^({_NAME})/({_NAME})$")


class InterfaceNameError(ValueError):
    """A type name is not of the form ``pkg/Type`` or ``pkg/msg/Type``."""


def split_type_name(type_name: str) -> tuple[str, str, str]:
    """Split ``pkg/msg/Type`` (or ``pkg/Type``, namespace ``msg``) into its three parts."""
    match = _TYPE_WITH_NAMESPACE.match(type_name)
    if match:
        return match.group(1), match.group(2), match.group(3)
    match = _TYPE_WITHOUT_NAMESPACE.match(type_name)
    if match:
        return match.group(1), "msg", match.group(2)
    raise InterfaceNameError(f"invalid interface type name {type_name!r}")


def ament_prefixes() -> list[Path]:
    """Prefixes searched for interface packages: ``AMENT_PREFIX_PATH``, then ``sys.prefix``."""
    listed = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    own = Path(sys.prefix)
    return listed if own in listed else [*listed, own]


def package_share_directory(package: str) -> Path | None:
    """``<prefix>/share/<package>`` of the first prefix whose ament index lists the package."""
    for prefix in ament_prefixes():
        if (prefix / "share" / "ament_index" / "resource_index" / "packages" / package).is_file():
            return prefix / "share" / package
    return None


def find_interface_file(type_name: str, extension: str) -> Path | None:
    """Path of the ``.msg`` / ``.idl`` / ``.json`` file of a type, or None if not installed."""
    package, namespace, name = split_type_name(type_name)
    share = package_share_directory(package)
    if share is None:
        return None
    path = share / namespace / f"{name}{extension}"
    return path if path.is_file() else None


def read_type_hash(type_name: str) -> str:
    """The ``RIHS01_...`` type description hash of an installed type, or "" if unknown.

    rosidl installs ``share/<pkg>/msg/<Type>.json`` whose ``type_hashes`` list starts with the
    hash of the type itself; this is the hash rmw reports for the type's endpoints.
    """
    path = find_interface_file(type_name, ".json")
    if path is None:
        return ""
    try:
        hashes = json.loads(path.read_text(encoding="utf-8")).get("type_hashes", [])
    except (OSError, ValueError):
        return ""
    package, namespace, name = split_type_name(type_name)
    full_name = f"{package}/{namespace}/{name}"
    return next((h.get("hash_string", "") for h in hashes if h.get("type_name") == full_name), "")
