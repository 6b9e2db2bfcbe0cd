"""The key paths of a summary's plain data, to compare two summaries' schemas level by level."""
from __future__ import annotations

from typing import Any


def key_paths(value: Any, path: str = "") -> set[str]:
    """Every key path of ``value`` (``RunSummary.to_dict`` data): ``.robots[].targets[].x``
    for a key of any entry of a list; keys under a null value are not there."""
    found: set[str] = set()
    if isinstance(value, dict):
        for key, item in value.items():
            found |= {f"{path}.{key}"} | key_paths(item, f"{path}.{key}")
    elif isinstance(value, list):
        for item in value:
            found |= key_paths(item, f"{path}[]")
    return found
