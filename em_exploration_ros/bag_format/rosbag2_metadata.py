"""The bag metadata that rosbag2 (Jazzy) stores in an MCAP Metadata record named ``rosbag2``.

rosbag2's MCAP plugin writes, when a bag is closed, a Metadata record ``rosbag2`` with one key
``serialized_metadata``: ``YAML::Dump`` of its ``BagMetadata`` (version 9), keys in the order
version, storage_identifier, duration, starting_time, message_count,
topics_with_message_count, compression_format, compression_mode, relative_file_paths, files,
custom_data, ros_distro. Times are nanoseconds (``{nanoseconds: N}`` and
``{nanoseconds_since_epoch: N}``); each topic carries name, type, serialization_format,
offered_qos_profiles (since version 9 a nested sequence, not a string) and
type_description_hash. MCAP chunk compression is a storage option, so compression_format
and compression_mode stay empty as rosbag2 leaves them. An empty custom_data is written as
YAML null, as rosbag2 writes it (``custom_data: ~``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import yaml

from em_exploration_ros.bag_format.qos_yaml import (
    QosFormatError, QosProfile, qos_profile_from_node, qos_profile_node, qos_profiles_from_yaml)
from em_exploration_ros.core.untrusted_yaml import load_yaml, shown_value

METADATA_RECORD_NAME = "rosbag2"
SERIALIZED_METADATA_KEY = "serialized_metadata"
METADATA_VERSION = 9
STORAGE_IDENTIFIER = "mcap"
SERIALIZATION_FORMAT = "cdr"
ROS_DISTRO = "jazzy"
#: Starting time of a bag without messages (rosbag2 starts from the largest time point).
EMPTY_BAG_STARTING_TIME_NS = 2**63 - 1


class MetadataFormatError(ValueError):
    """A serialized bag metadata text cannot be parsed."""


@dataclass(frozen=True)
class TopicInformation:
    """One recorded topic with its message count."""

    name: str
    type: str
    message_count: int
    offered_qos_profiles: tuple[QosProfile, ...] = ()
    type_description_hash: str = ""
    serialization_format: str = SERIALIZATION_FORMAT


@dataclass(frozen=True)
class BagMetadata:
    """Summary of one single-file bag; times in nanoseconds of the recording clock."""

    relative_file_path: str
    starting_time_ns: int
    duration_ns: int
    message_count: int
    topics: tuple[TopicInformation, ...]
    custom_data: Mapping[str, str] = field(default_factory=dict)
    ros_distro: str = ROS_DISTRO
    compression_format: str = ""
    compression_mode: str = ""
    storage_identifier: str = STORAGE_IDENTIFIER
    version: int = METADATA_VERSION


def bag_metadata_node(metadata: BagMetadata) -> dict[str, Any]:
    """The metadata as the nested mapping rosbag2 encodes (key order included)."""
    topics = [{
        "topic_metadata": {
            "name": topic.name,
            "type": topic.type,
            "serialization_format": topic.serialization_format,
            "offered_qos_profiles": [qos_profile_node(p) for p in topic.offered_qos_profiles],
            "type_description_hash": topic.type_description_hash,
        },
        "message_count": topic.message_count,
    } for topic in metadata.topics]
    return {
        "version": metadata.version,
        "storage_identifier": metadata.storage_identifier,
        "duration": {"nanoseconds": metadata.duration_ns},
        "starting_time": {"nanoseconds_since_epoch": metadata.starting_time_ns},
        "message_count": metadata.message_count,
        "topics_with_message_count": topics,
        "compression_format": metadata.compression_format,
        "compression_mode": metadata.compression_mode,
        "relative_file_paths": [metadata.relative_file_path],
        "files": [{
            "path": metadata.relative_file_path,
            "starting_time": {"nanoseconds_since_epoch": metadata.starting_time_ns},
            "duration": {"nanoseconds": metadata.duration_ns},
            "message_count": metadata.message_count,
        }],
        "custom_data": dict(metadata.custom_data) or None,
        "ros_distro": metadata.ros_distro,
    }


def serialize_bag_metadata(metadata: BagMetadata) -> str:
    """The ``serialized_metadata`` value of the ``rosbag2`` Metadata record (YAML, keys in
    rosbag2's order, block style; rosbag2 reads it with yaml-cpp)."""
    return yaml.safe_dump(bag_metadata_node(metadata), sort_keys=False)


def _text(value: Any) -> str:
    """A scalar field as text; raises MetadataFormatError for a list or mapping (whose
    ``str`` could be huge)."""
    if isinstance(value, (list, dict)):
        raise MetadataFormatError(f"bad serialized bag metadata: expected text, got "
                                  f"{shown_value(value)}")
    return str(value)


def _topic_from_node(node: Mapping[str, Any], version: int) -> TopicInformation:
    topic = node["topic_metadata"]
    offered = topic.get("offered_qos_profiles", [])
    if isinstance(offered, str):  # versions 4..8 hold the profiles as a YAML string
        profiles = qos_profiles_from_yaml(offered)
    else:
        profiles = [qos_profile_from_node(p) for p in offered or []]
    return TopicInformation(
        name=_text(topic["name"]), type=_text(topic["type"]),
        message_count=int(node["message_count"]),
        offered_qos_profiles=tuple(profiles),
        type_description_hash=(_text(topic.get("type_description_hash") or "")
                               if version >= 7 else ""),
        serialization_format=_text(topic["serialization_format"]))


def parse_bag_metadata(text: str) -> BagMetadata:
    """Parse a ``serialized_metadata`` text (versions 4 to 9)."""
    try:
        node = load_yaml(text, "serialized bag metadata", MetadataFormatError)
        if not isinstance(node, Mapping):
            raise MetadataFormatError("serialized bag metadata is not a YAML mapping")
        version = int(node["version"])
        paths = node.get("relative_file_paths") or [""]
        return BagMetadata(
            relative_file_path=_text(paths[0]),
            starting_time_ns=int(node["starting_time"]["nanoseconds_since_epoch"]),
            duration_ns=int(node["duration"]["nanoseconds"]),
            message_count=int(node["message_count"]),
            topics=tuple(_topic_from_node(t, version)
                         for t in node.get("topics_with_message_count") or []),
            custom_data={_text(k): _text(v) for k, v in (node.get("custom_data") or {}).items()},
            ros_distro=_text(node.get("ros_distro") or ""),
            compression_format=_text(node.get("compression_format") or ""),
            compression_mode=_text(node.get("compression_mode") or ""),
            storage_identifier=_text(node["storage_identifier"]),
            version=version)
    except MetadataFormatError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, QosFormatError) as error:
        raise MetadataFormatError(f"bad serialized bag metadata: {error!r}") from error
