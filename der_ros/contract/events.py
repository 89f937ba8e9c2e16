"""The key/values of the ``episode`` and ``agent/metrics`` topics (diagnostic_msgs/DiagnosticArray).

An episode event is one status named :data:`~der_ros.contract.topics.EPISODE_STATUS` whose message is
the event (start, success, collision, time_limit) and whose key/values are :func:`episode_values`;
metrics are one status of numeric key/values. Values are text: ``repr`` of floats (exact round
trip), ``str`` otherwise (:func:`format_value`, read back by :func:`parse_key_values`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

from der_ros.contract.cdr import header_ns
from der_ros.contract.topics import EPISODE_STATUS, SAFETY_STATUS

__all__ = [
    "format_value",
    "episode_values",
    "parse_key_values",
    "parse_episode_events",
    "diagnostics_to_metrics",
    "parse_safety_record",
]



def format_value(value: object) -> str:
    """A ``diagnostic_msgs/KeyValue`` value: ``repr`` of floats (exact round trip), ``str`` otherwise."""
    return repr(value) if isinstance(value, float) else str(value)


def _parse_value(text: str) -> int | float | str:
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def episode_values(episode: int, steps: int, ret: float | None = 0.0, lane_changes: int = 0,
                   mean_speed: float = 0.0, **extra: object) -> dict[str, object]:
    """The key/values of an ``episode`` event, in the order the bridge writes them (start events
    carry only ``episode`` and ``steps``: pass ``ret=None``)."""
    out: dict[str, object] = {"episode": int(episode), "steps": int(steps)}
    if ret is not None:
        out.update({"return": float(ret), "lane_changes": int(lane_changes), "mean_speed": float(mean_speed)})
    out.update(extra)
    return out


def parse_key_values(values: Iterable[Any]) -> dict[str, int | float | str]:
    """``diagnostic_msgs/KeyValue`` items -> key -> int, float or text (inverse of :func:`format_value`)."""
    return {str(kv.key): _parse_value(str(kv.value)) for kv in values}


def parse_episode_events(msg: Any) -> list[tuple[int, str, dict[str, int | float | str]]]:
    """Every ``episode`` status of a DiagnosticArray as (stamp_ns, event, values)."""
    stamp = header_ns(msg)
    return [
        (stamp, str(s.message), parse_key_values(s.values))
        for s in msg.status
        if s.name == EPISODE_STATUS
    ]


def diagnostics_to_metrics(msg: Any, names: Sequence[str] | None = None) -> dict[str, float]:
    """Every numeric key/value of the statuses (optionally only those named ``names``) as floats."""
    out: dict[str, float] = {}
    for s in msg.status:
        if names is not None and s.name not in names:
            continue
        for kv in s.values:
            try:
                out[str(kv.key)] = float(kv.value)
            except ValueError:
                continue
    return out


def parse_safety_record(msg: Any) -> tuple[int, str, int, int, int] | None:
    """A ``safety/interventions`` DiagnosticArray -> (stamp_ns, verdict, proposed, applied, interventions),
    None when it holds no safety status."""
    for status in msg.status:
        if status.name == SAFETY_STATUS:
            values = parse_key_values(status.values)
            return (header_ns(msg), str(status.message), int(float(values.get("proposed", -1))),
                    int(float(values.get("applied", 0))), int(float(values.get("interventions", 0))))  # fmt: skip
    return None
