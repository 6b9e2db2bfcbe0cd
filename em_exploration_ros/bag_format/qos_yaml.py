"""QoS profiles as rosbag2 (Jazzy, metadata version 9) stores them, and its QoS adaptation rules.

A channel's ``offered_qos_profiles`` metadata is the YAML of a sequence with one profile per
publisher seen at subscription time; each profile maps ``history``, ``depth``,
``reliability``, ``durability``, ``deadline``, ``lifespan``, ``liveliness``,
``liveliness_lease_duration`` (durations as ``{sec, nsec}``) and
``avoid_ros_namespace_conventions``. Since version 9 the policies are the rmw names
(``keep_last``, ``reliable``, ``transient_local``, ``automatic``; ``unknown`` when rmw could
not tell); older files hold the rmw enum integers, which are read too.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Iterable, Mapping, Sequence

import yaml

from em_exploration_ros.core.untrusted_yaml import load_yaml, shown_value

SYSTEM_DEFAULT = "system_default"
UNKNOWN = "unknown"
BEST_AVAILABLE = "best_available"
KEEP_LAST = "keep_last"
KEEP_ALL = "keep_all"
RELIABLE = "reliable"
BEST_EFFORT = "best_effort"
TRANSIENT_LOCAL = "transient_local"
VOLATILE = "volatile"
AUTOMATIC = "automatic"
MANUAL_BY_TOPIC = "manual_by_topic"

#: rmw enum values (rmw/types.h) of each policy name, for metadata written before version 9.
HISTORY_VALUES = {SYSTEM_DEFAULT: 0, KEEP_LAST: 1, KEEP_ALL: 2, UNKNOWN: 3}
RELIABILITY_VALUES = {SYSTEM_DEFAULT: 0, RELIABLE: 1, BEST_EFFORT: 2, UNKNOWN: 3,
                      BEST_AVAILABLE: 4}
DURABILITY_VALUES = {SYSTEM_DEFAULT: 0, TRANSIENT_LOCAL: 1, VOLATILE: 2, UNKNOWN: 3,
                     BEST_AVAILABLE: 4}
LIVELINESS_VALUES = {SYSTEM_DEFAULT: 0, AUTOMATIC: 1, MANUAL_BY_TOPIC: 3, UNKNOWN: 4,
                     BEST_AVAILABLE: 5}

_NS_PER_S = 1_000_000_000
#: RMW_DURATION_INFINITE in nanoseconds: {sec: 9223372036, nsec: 854775807}.
DURATION_INFINITE_NS = 2**63 - 1
#: "Infinite" durations that Foxy-era rmw implementations reported, as (sec, nsec).
_LEGACY_INFINITE = {(0x7FFFFFFF, 0xFFFFFFFF), (0x7FFFFFFF, 0x7FFFFFFF)}


class QosFormatError(ValueError):
    """An offered_qos_profiles text cannot be parsed."""


@dataclass(frozen=True)
class QosProfile:
    """One QoS profile with rmw policy names; durations in nanoseconds (0 = unspecified)."""

    history: str = KEEP_LAST
    depth: int = 10
    reliability: str = RELIABLE
    durability: str = VOLATILE
    deadline_ns: int = 0
    lifespan_ns: int = 0
    liveliness: str = SYSTEM_DEFAULT
    liveliness_lease_duration_ns: int = 0
    avoid_ros_namespace_conventions: bool = False


def _duration_node(ns: int) -> dict[str, int]:
    return {"sec": ns // _NS_PER_S, "nsec": ns % _NS_PER_S}


def qos_profile_node(profile: QosProfile) -> dict[str, Any]:
    """The YAML mapping of one profile (version 9 layout, keys in rosbag2's order)."""
    return {
        "history": profile.history,
        "depth": profile.depth,
        "reliability": profile.reliability,
        "durability": profile.durability,
        "deadline": _duration_node(profile.deadline_ns),
        "lifespan": _duration_node(profile.lifespan_ns),
        "liveliness": profile.liveliness,
        "liveliness_lease_duration": _duration_node(profile.liveliness_lease_duration_ns),
        "avoid_ros_namespace_conventions": profile.avoid_ros_namespace_conventions,
    }


def qos_profiles_to_yaml(profiles: Iterable[QosProfile]) -> str:
    """The ``offered_qos_profiles`` channel metadata string: a YAML sequence of profiles in
    block style (rosbag2 parses it with yaml-cpp, which reads any YAML layout)."""
    return yaml.safe_dump([qos_profile_node(p) for p in profiles], sort_keys=False)


def _policy(value: Any, names: Mapping[str, int], field: str) -> str:
    if isinstance(value, bool):
        raise QosFormatError(f"{field}: expected a policy, got {shown_value(value)}")
    if isinstance(value, int):
        by_value = {v: k for k, v in names.items()}
        if value not in by_value:
            raise QosFormatError(f"{field}: unknown policy value {value}")
        return by_value[value]
    if isinstance(value, str) and value.lower() in names:
        return value.lower()
    raise QosFormatError(f"{field}: unknown policy {shown_value(value)}")


def _duration_ns(value: Any, field: str) -> int:
    if not isinstance(value, Mapping):
        raise QosFormatError(f"{field}: expected {{sec, nsec}}, got {shown_value(value)}")
    try:
        sec, nsec = int(value["sec"]), int(value["nsec"])
    except (KeyError, TypeError, ValueError) as error:
        raise QosFormatError(
            f"{field}: expected {{sec, nsec}}, got {shown_value(value)}") from error
    if (sec, nsec) in _LEGACY_INFINITE:
        return DURATION_INFINITE_NS
    return min(sec * _NS_PER_S + nsec, DURATION_INFINITE_NS)


def qos_profile_from_node(node: Mapping[str, Any]) -> QosProfile:
    """Parse one profile mapping; policies may be names (v9) or rmw integers (v4..v8)."""
    if not isinstance(node, Mapping):
        raise QosFormatError(f"expected a QoS mapping, got {shown_value(node)}")
    try:
        return QosProfile(
            history=_policy(node["history"], HISTORY_VALUES, "history"),
            depth=int(node["depth"]),
            reliability=_policy(node["reliability"], RELIABILITY_VALUES, "reliability"),
            durability=_policy(node["durability"], DURABILITY_VALUES, "durability"),
            deadline_ns=_duration_ns(node["deadline"], "deadline"),
            lifespan_ns=_duration_ns(node["lifespan"], "lifespan"),
            liveliness=_policy(node["liveliness"], LIVELINESS_VALUES, "liveliness"),
            liveliness_lease_duration_ns=_duration_ns(
                node["liveliness_lease_duration"], "liveliness_lease_duration"),
            avoid_ros_namespace_conventions=bool(node["avoid_ros_namespace_conventions"]),
        )
    except KeyError as error:
        raise QosFormatError(f"QoS profile lacks {shown_value(error.args[0])}") from error
    except (TypeError, ValueError) as error:
        raise QosFormatError(f"bad QoS profile: {error}") from error


def qos_profiles_from_yaml(text: str) -> list[QosProfile]:
    """Parse an ``offered_qos_profiles`` string ("" means no profiles)."""
    if not text.strip():
        return []
    nodes = load_yaml(text, "offered_qos_profiles", QosFormatError)
    if not isinstance(nodes, list):
        raise QosFormatError("offered_qos_profiles is not a YAML sequence")
    return [qos_profile_from_node(node) for node in nodes]


def request_for_offers(offers: Sequence[QosProfile], depth: int) -> QosProfile:
    """Subscription QoS that connects to every offering publisher (rosbag2's recorder rule).

    Reliable only if every publisher is reliable, transient-local only if every publisher
    is; keep-last ``depth``; deadline, lifespan and liveliness left unspecified.
    """
    reliable = bool(offers) and all(p.reliability == RELIABLE for p in offers)
    latched = bool(offers) and all(p.durability == TRANSIENT_LOCAL for p in offers)
    return QosProfile(history=KEEP_LAST, depth=depth,
                      reliability=RELIABLE if reliable else BEST_EFFORT,
                      durability=TRANSIENT_LOCAL if latched else VOLATILE)


def _compatibility_key(profile: QosProfile) -> tuple:
    return (profile.reliability, profile.durability, profile.deadline_ns, profile.liveliness,
            profile.liveliness_lease_duration_ns)


def offer_for_playback(recorded: Sequence[QosProfile], depth: int) -> QosProfile:
    """Publisher QoS for replaying a topic (rosbag2's player rule).

    If all recorded publishers offered the same compatibility-relevant policies (history and
    lifespan aside), offer that profile with keep-last ``depth``; otherwise (or with no
    record) the default reliable, volatile profile.
    """
    if not recorded or len({_compatibility_key(p) for p in recorded}) > 1:
        return QosProfile(depth=depth)
    return replace(recorded[0], history=KEEP_LAST, depth=depth)
