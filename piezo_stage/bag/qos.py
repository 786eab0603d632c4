"""Offered QoS profiles as rosbag2 (metadata version 9) stores them.

A profile is a dict ``{history, depth, reliability, durability, deadline, lifespan, liveliness,
liveliness_lease_duration, avoid_ros_namespace_conventions}`` with policies as lower-case
names and durations as ``{sec, nsec}``. ``metadata.yaml`` holds the list itself; the MCAP
channel's ``offered_qos_profiles`` metadata holds the same list as a YAML string.
"""

from __future__ import annotations

from typing import Any, Iterable

import yaml

from . import yaml_emit
from .errors import InvalidQosError

#: RMW_DURATION_INFINITE split into seconds and nanoseconds, as rosbag2 writes it.
INFINITE_NS = 2**63 - 1
_POLICIES = {
    "history": ("keep_last", "keep_all", "system_default", "unknown"),
    "reliability": ("reliable", "best_effort", "system_default", "best_available", "unknown"),
    "durability": ("volatile", "transient_local", "system_default", "best_available", "unknown"),
    "liveliness": ("automatic", "manual_by_topic", "system_default", "best_available", "unknown"),
}
# Metadata version <= 8 stored the rmw enum values as integers.
_LEGACY_INTS = {
    "history": {0: "system_default", 1: "keep_last", 2: "keep_all", 3: "unknown"},
    "reliability": {0: "system_default", 1: "reliable", 2: "best_effort", 3: "unknown"},
    "durability": {0: "system_default", 1: "transient_local", 2: "volatile", 3: "unknown"},
    "liveliness": {0: "system_default", 1: "automatic", 3: "manual_by_topic", 4: "unknown"},
}
_DURATIONS = ("deadline", "lifespan", "liveliness_lease_duration")
FIELDS = (
    "history",
    "depth",
    "reliability",
    "durability",
    "deadline",
    "lifespan",
    "liveliness",
    "liveliness_lease_duration",
    "avoid_ros_namespace_conventions",
)


def duration(ns: int | None) -> dict[str, int]:
    """``{sec, nsec}`` of a duration in nanoseconds; None means infinite."""
    sec, nsec = divmod(INFINITE_NS if ns is None else min(int(ns), INFINITE_NS), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def qos_profile(
    *,
    history: str = "keep_last",
    depth: int = 10,
    reliability: str = "reliable",
    durability: str = "volatile",
    deadline_ns: int | None = None,
    lifespan_ns: int | None = None,
    liveliness: str = "automatic",
    liveliness_lease_duration_ns: int | None = None,
    avoid_ros_namespace_conventions: bool = False,
) -> dict[str, Any]:
    """One offered QoS profile (durations None = infinite)."""
    return normalize_profile(
        {
            "history": history,
            "depth": depth,
            "reliability": reliability,
            "durability": durability,
            "deadline": duration(deadline_ns),
            "lifespan": duration(lifespan_ns),
            "liveliness": liveliness,
            "liveliness_lease_duration": duration(liveliness_lease_duration_ns),
            "avoid_ros_namespace_conventions": avoid_ros_namespace_conventions,
        }
    )


def _policy(name: str, value: Any) -> str:
    if isinstance(value, int) and not isinstance(value, bool):
        if value in _LEGACY_INTS[name]:
            return _LEGACY_INTS[name][value]
    elif isinstance(value, str) and value.lower() in _POLICIES[name]:
        return value.lower()
    raise InvalidQosError(f"QoS {name} {value!r} is not one of {', '.join(_POLICIES[name])}")


def _duration(name: str, value: Any) -> dict[str, int]:
    try:
        return {"sec": int(value["sec"]), "nsec": int(value["nsec"])}
    except (TypeError, KeyError, ValueError):
        raise InvalidQosError(
            f"QoS {name} must be a mapping {{sec, nsec}}, got {value!r}"
        ) from None


def normalize_profile(profile: dict[str, Any]) -> dict[str, Any]:
    """Validated copy of one profile in version-9 form, keys in rosbag2's order."""
    if not isinstance(profile, dict):
        raise InvalidQosError(f"a QoS profile must be a mapping, got {profile!r}")
    missing = [f for f in FIELDS if f not in profile]
    if missing:
        raise InvalidQosError(f"QoS profile lacks {', '.join(missing)}")
    out: dict[str, Any] = {}
    for field in FIELDS:
        value = profile[field]
        if field in _POLICIES:
            out[field] = _policy(field, value)
        elif field in _DURATIONS:
            out[field] = _duration(field, value)
        elif field == "depth":
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise InvalidQosError(f"QoS depth must be a non-negative integer, got {value!r}")
            out[field] = value
        else:
            out[field] = bool(value)
    return out


#: Common offers: rclpy's default, SensorDataQoS and a latched (transient_local) publisher.
RELIABLE = qos_profile()
SENSOR_DATA = qos_profile(depth=5, reliability="best_effort")
LATCHED = qos_profile(depth=1, durability="transient_local")


def normalize_profiles(profiles: str | Iterable[dict[str, Any]] | None) -> list[dict[str, Any]]:
    """Profiles from a YAML string (any rosbag2 version), a list of dicts or None (none)."""
    if profiles is None:
        return []
    if isinstance(profiles, str):
        try:
            profiles = yaml.safe_load(profiles) if profiles.strip() else []
        except yaml.YAMLError as exc:
            raise InvalidQosError(f"offered_qos_profiles is not valid YAML: {exc}") from None
        if profiles is None:
            profiles = []
    if isinstance(profiles, dict) or not isinstance(profiles, (list, tuple)):
        raise InvalidQosError(f"offered_qos_profiles must be a list, got {profiles!r}")
    return [normalize_profile(p) for p in profiles]


def profiles_to_yaml(profiles: list[dict[str, Any]]) -> str:
    """The YAML string rosbag2 puts in the MCAP channel metadata."""
    return yaml_emit.dump(profiles)


def _enum_name(value: Any) -> Any:
    return value.name if hasattr(value, "name") else value


def _nanoseconds(value: Any) -> int:
    return int(value.nanoseconds) if hasattr(value, "nanoseconds") else int(value)


def qos_from_profile(profile: Any) -> dict[str, Any]:
    """Profile dict of an rclpy ``QoSProfile``-like object (duck typed: no rclpy import)."""
    return qos_profile(
        history=str(_enum_name(profile.history)).lower(),
        depth=int(profile.depth),
        reliability=str(_enum_name(profile.reliability)).lower(),
        durability=str(_enum_name(profile.durability)).lower(),
        deadline_ns=_nanoseconds(profile.deadline),
        lifespan_ns=_nanoseconds(profile.lifespan),
        liveliness=str(_enum_name(profile.liveliness)).lower(),
        liveliness_lease_duration_ns=_nanoseconds(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )
