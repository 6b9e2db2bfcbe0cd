"""YAML from files a user or a recording supplies (parameter files, a bag's metadata.yaml,
its rosbag2 metadata record and channel QoS): parsing it, and showing a parsed value in an
error message, both bounded in time and size.

A hostile text can nest deeper than Python's recursion limit, hold an integer whose
``repr`` raises (more than 4300 digits), or use aliases of aliases so that a few hundred
bytes parse into a value whose full ``repr`` has billions of items. A mapping that holds
one key twice is refused (``yaml.safe_load`` keeps the last value silently: a parameter
set twice in a file took the second value without a word).
"""
from __future__ import annotations

import math
import reprlib
from typing import Any

import yaml


class _BoundedRepr(reprlib.Repr):
    """``reprlib.Repr`` that also shortens integers of any size (``repr`` of one with more
    than 4300 digits raises ``ValueError``)."""

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() <= 128:
            return repr(x)
        digits = math.floor(x.bit_length() * math.log10(2)) + 1
        return f"{'-' if x < 0 else ''}<integer of about {digits} digits>"


_VALUE_REPR = _BoundedRepr()
_VALUE_REPR.maxlevel, _VALUE_REPR.maxlist, _VALUE_REPR.maxtuple = 2, 4, 4
_VALUE_REPR.maxdict, _VALUE_REPR.maxset = 4, 4
_VALUE_REPR.maxstring, _VALUE_REPR.maxother = 60, 60


def shown_value(value: Any) -> str:
    """``repr(value)`` cut to a few dozen characters, for error messages."""
    return _VALUE_REPR.repr(value)


class DuplicateKeyError(yaml.YAMLError):
    """A mapping holds one key twice; the message names the key and its 1-based line."""


_MERGE_TAG = "tag:yaml.org,2002:merge"
_VALUE_TAG = "tag:yaml.org,2002:value"


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a mapping holding one key twice, at any depth.

    Only a mapping's own keys are compared: a key given explicitly may still override one
    brought in by a merge key (``<<: *base``), as YAML's merge rule says. Each mapping is
    checked once, before ``flatten_mapping`` folds its merged keys into it (which happens
    to an anchored mapping when another mapping merges it, possibly before its own turn),
    so aliases cost no more than they already do."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._checked_mappings: set[int] = set()

    def flatten_mapping(self, node: yaml.MappingNode) -> None:
        if id(node) not in self._checked_mappings:
            self._checked_mappings.add(id(node))
            self._refuse_duplicate_keys(node)
        super().flatten_mapping(node)

    def _refuse_duplicate_keys(self, node: yaml.MappingNode) -> None:
        first_lines: dict[Any, int] = {}
        for key_node, _ in node.value:
            # A sequence or mapping key is unhashable here: construct_mapping refuses it.
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == _MERGE_TAG:
                continue
            key = (key_node.value if key_node.tag == _VALUE_TAG
                   else self.construct_object(key_node, deep=True))
            line = key_node.start_mark.line + 1
            try:
                first = first_lines.get(key)
            except TypeError:  # unhashable: construct_mapping refuses it
                continue
            if first is not None:
                raise DuplicateKeyError(f"duplicate key {shown_value(key)} at line {line} "
                                        f"(first at line {first})")
            first_lines[key] = line


def load_yaml(text: str, what: str, error: type[ValueError]) -> Any:
    """Parse ``text`` (``yaml.safe_load``, and a mapping may not hold one key twice);
    raises ``error`` naming ``what`` if it is not YAML (an integer of more than 4300
    digits included), holds a duplicate key (named with its line), or nests too deeply
    to parse. The error is one line: PyYAML's own spans several (the problem, where, the
    line quoted with a caret under the place), which become its parts joined by "; ",
    without the caret."""
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
    except DuplicateKeyError as problem:
        raise error(f"{what}: {problem}") from None
    except (yaml.YAMLError, ValueError) as problem:
        parts = (part.strip() for part in str(problem).splitlines())
        shown = "; ".join(part for part in parts if part not in ("", "^"))
        raise error(f"{what} is not valid YAML: {shown}") from None
    except RecursionError:
        raise error(f"{what} is nested too deeply to parse") from None
