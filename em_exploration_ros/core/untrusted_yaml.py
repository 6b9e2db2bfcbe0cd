"""YAML from files a user or a recording supplies (parameter files, a bag's metadata.yaml,
its rosbag2 metadata record and channel QoS): parsing it, and showing a parsed value in an
error message, both bounded in time and size.

A hostile text can nest deeper than Python's recursion limit, hold an integer whose
``repr`` raises (more than 4300 digits), or use aliases of aliases so that a few hundred
bytes parse into a value whose full ``repr`` has billions of items.
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


def load_yaml(text: str, what: str, error: type[ValueError]) -> Any:
    """Parse ``text`` (``yaml.safe_load``); raises ``error`` naming ``what`` if it is not
    YAML (an integer of more than 4300 digits included) or nests too deeply to parse."""
    try:
        return yaml.safe_load(text)
    except (yaml.YAMLError, ValueError) as problem:
        raise error(f"{what} is not valid YAML: {problem}") from None
    except RecursionError:
        raise error(f"{what} is nested too deeply to parse") from None
