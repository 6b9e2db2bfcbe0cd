"""Fully populated sample instances of every em_exploration_msgs message type.

The message types are discovered from the .msg files in msg_schemas/msg/, so a new type is
covered by every test that uses this module without any change here.

make_sample() fills every field, recursively, with a value that differs from the field's
default: numbers are non-zero and use the high bits of their type (so truncation or sign errors
show), strings hold non-ASCII characters, fixed arrays are full and sequences hold several
elements. The values are deterministic (a counter over the fields, in declaration order), so
two processes that call make_sample() for the same type get equal messages. They are arbitrary
test data, not physically meaningful (a Time's nanosec may exceed 10^9, for instance).

unpopulated_fields() lists the fields of a message that still hold their default value.

canonical_cdr() is rclpy's serialization of a message with the alignment padding set to zero.
The CDR standard leaves padding bytes unspecified and Fast DDS does not write them (they hold
whatever the buffer held), so two serializations of equal messages agree on every data byte but
not always on the padding; canonical_cdr() output is comparable byte for byte.
"""
from __future__ import annotations

import importlib
import itertools
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rclpy.serialization import serialize_message
from rosidl_parser import definition

REPO_ROOT = Path(__file__).resolve().parent.parent
MSG_DIR = REPO_ROOT / "msg_schemas" / "msg"
PACKAGE = "em_exploration_msgs"

# Number of elements put into every unbounded sequence (bounded ones get at most their bound).
SEQUENCE_LENGTH = 3

# Encoded size (= CDR alignment) of the basic types, in bytes.
_CDR_SIZE = {"boolean": 1, "octet": 1, "int8": 1, "uint8": 1,
             "int16": 2, "uint16": 2, "int32": 4, "uint32": 4, "float": 4,
             "int64": 8, "uint64": 8, "double": 8}
# The 4-byte encapsulation header that starts every serialized ROS 2 message.
_CDR_HEADER_SIZE = 4

# Width of the integer types, in bits.
_INT_BITS = {"int8": 8, "int16": 16, "int32": 32, "int64": 64,
             "uint8": 8, "uint16": 16, "uint32": 32, "uint64": 64}


def message_type_names() -> list[str]:
    """Return the names of all message types (the .msg file stems), sorted."""
    return sorted(path.stem for path in MSG_DIR.glob("*.msg"))


def message_class(name: str) -> type:
    """Return the generated Python class of em_exploration_msgs/msg/<name>."""
    return getattr(importlib.import_module(f"{PACKAGE}.msg"), name)


def make_sample(msg_class: type) -> Any:
    """Return an instance of msg_class with a non-default value in every field, recursively."""
    return _make_message(msg_class, itertools.count(1))


def unpopulated_fields(msg: Any, prefix: str = "") -> list[str]:
    """Return the dotted paths of the fields of msg (recursively) that hold their default value.

    A nested message counts through its own fields, a sequence must be non-empty, and an array
    or sequence of nested messages is checked element by element.
    """
    default = type(msg)()
    missing: list[str] = []
    for field, slot_type in zip(msg.get_fields_and_field_types(), type(msg).SLOT_TYPES):
        path = f"{prefix}{field}"
        value = getattr(msg, field)
        if isinstance(slot_type, definition.NamespacedType):
            missing += unpopulated_fields(value, f"{path}.")
        elif isinstance(slot_type, definition.AbstractNestedType):
            if len(value) == 0:
                missing.append(path)
            elif isinstance(slot_type.value_type, definition.NamespacedType):
                for index, element in enumerate(value):
                    missing += unpopulated_fields(element, f"{path}[{index}].")
            elif any(_equal(element, _default_element(slot_type)) for element in value):
                missing.append(path)
        elif _equal(value, getattr(default, field)):
            missing.append(path)
    return missing


def canonical_cdr(msg: Any) -> bytes:
    """Return serialize_message(msg) with every alignment padding byte set to zero.

    The padding is located by walking the message in the layout of plain little-endian CDR
    (XCDR1, as ROS 2 serializes): each basic value aligned to its size relative to the end of
    the encapsulation header, strings and sequences prefixed by a 4-byte-aligned uint32 length,
    strings with a terminating NUL; the data end is padded to a multiple of 4 bytes (a
    message ending in a bool or uint8). Fails if the walk does not end exactly at the end of
    the data, i.e. if the serializer's layout differs from this one.
    """
    data = bytearray(serialize_message(msg))
    end = _zero_padding(msg, data, _CDR_HEADER_SIZE)
    padded_end = end + (-(end - _CDR_HEADER_SIZE)) % 4
    if padded_end == len(data):
        data[end:padded_end] = bytes(padded_end - end)
        end = padded_end
    if end != len(data):
        raise AssertionError(f"CDR layout walk of {type(msg).__name__} ended at byte {end}, "
                             f"the serialized data has {len(data)}")
    return bytes(data)


def _zero_padding(msg: Any, data: bytearray, pos: int) -> int:
    """Zero the padding of msg's fields in data, starting at pos; return the end position."""
    for field, slot_type in zip(msg.get_fields_and_field_types(), type(msg).SLOT_TYPES):
        pos = _zero_value_padding(slot_type, getattr(msg, field), data, pos)
    return pos


def _zero_value_padding(slot_type: definition.AbstractType, value: Any, data: bytearray,
                        pos: int) -> int:
    """Zero the padding of one value of the given type at pos; return the end position."""
    if isinstance(slot_type, definition.NamespacedType):
        return _zero_padding(value, data, pos)
    if isinstance(slot_type, definition.AbstractNestedType):
        if isinstance(slot_type, definition.AbstractSequence):
            pos = _align(data, pos, 4) + 4
        for element in value:
            pos = _zero_value_padding(slot_type.value_type, element, data, pos)
        return pos
    if isinstance(slot_type, definition.AbstractString):
        return _align(data, pos, 4) + 4 + len(value.encode()) + 1
    if isinstance(slot_type, definition.BasicType) and slot_type.typename in _CDR_SIZE:
        size = _CDR_SIZE[slot_type.typename]
        return _align(data, pos, size) + size
    raise NotImplementedError(f"CDR layout of rosidl type {slot_type!r} is not modelled here")


def _align(data: bytearray, pos: int, alignment: int) -> int:
    """Zero the padding bytes before the next multiple of alignment; return that position."""
    aligned = _CDR_HEADER_SIZE + -(-(pos - _CDR_HEADER_SIZE) // alignment) * alignment
    data[pos:aligned] = bytes(aligned - pos)
    return aligned


def _make_message(msg_class: type, counter: Iterator[int]) -> Any:
    """Build msg_class with every field set from the shared counter."""
    msg = msg_class()
    for field, slot_type in zip(msg.get_fields_and_field_types(), msg_class.SLOT_TYPES):
        setattr(msg, field, _make_value(slot_type, counter))
    return msg


def _make_value(slot_type: definition.AbstractType, counter: Iterator[int]) -> Any:
    """Return a non-default value of the given rosidl type."""
    if isinstance(slot_type, definition.NamespacedType):
        return _make_message(_namespaced_class(slot_type), counter)
    if isinstance(slot_type, definition.Array):
        return [_make_value(slot_type.value_type, counter) for _ in range(slot_type.size)]
    if isinstance(slot_type, definition.AbstractSequence):
        length = SEQUENCE_LENGTH
        if isinstance(slot_type, definition.BoundedSequence):
            length = min(length, slot_type.maximum_size)
        return [_make_value(slot_type.value_type, counter) for _ in range(length)]
    k = next(counter)
    if isinstance(slot_type, definition.AbstractGenericString):
        wide = isinstance(slot_type, definition.AbstractWString)
        text = f"wide-{k}-ω" if wide else f"sample-{k}-é"
        bound = getattr(slot_type, "maximum_size", None)
        return text[:bound] if bound else text
    if isinstance(slot_type, definition.BasicType):
        return _basic_value(slot_type.typename, k)
    raise TypeError(f"no sample value for rosidl type {slot_type!r}")


def _basic_value(typename: str, k: int) -> Any:
    """Return the k-th sample value (never the default) of a basic type a .msg file can use.

    (.msg char and byte map to uint8 and octet; IDL-only types such as wchar are not covered.)
    """
    if typename == "boolean":
        return True
    if typename == "octet":
        return bytes([0x80 + k % 100])
    if typename in ("float", "double"):
        # Quarter steps are exact in float32 too, so values survive a float32 field unchanged.
        return (-1) ** k * (k + 0.25)
    # High bits set, in range even for 8-bit types: unsigned 2^(n-1)+0..63, signed -2^(n-2)-0..63.
    bits = _INT_BITS[typename]
    if typename.startswith("u"):
        return 2 ** (bits - 1) + k % 64
    return -(2 ** (bits - 2)) - k % 64


def _default_element(slot_type: definition.AbstractNestedType) -> Any:
    """Return the default value of one element of an array or sequence of basic values."""
    value_type = slot_type.value_type
    if isinstance(value_type, definition.AbstractGenericString):
        return ""
    typename = value_type.typename
    if typename == "boolean":
        return False
    if typename == "octet":
        return b"\x00"
    return 0


def _equal(a: Any, b: Any) -> bool:
    """Compare two field values, including NumPy arrays and array.array, element-wise."""
    if hasattr(a, "__len__") and not isinstance(a, (str, bytes)):
        return len(a) == len(b) and all(x == y for x, y in zip(a, b))
    return a == b


def _namespaced_class(slot_type: definition.NamespacedType) -> type:
    """Import the Python class of a nested message type such as std_msgs/msg/Header."""
    module = importlib.import_module(".".join(slot_type.namespaces))
    return getattr(module, slot_type.name)
