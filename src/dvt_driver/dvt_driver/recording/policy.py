"""What ``dvt-recorder`` subscribes to, and with which QoS (pure: no rclpy).

The recorder takes topic types and publishers from the ROS graph; these functions decide from
that plain data which topics to record (:func:`match_topics`), which reliability/durability a
subscription needs to match every publisher (:func:`choose_qos`) and when an existing
subscription must be re-created with a weaker QoS (:func:`needs_weaker`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from fnmatch import fnmatchcase

from dvt_model.contract import DEFAULT_RECORD_TOPICS

DEFAULT_TOPICS: tuple[str, ...] = DEFAULT_RECORD_TOPICS
"""Topic names and patterns recorded by default: the contract's sample and model topics,
``/dvt/cmd/*`` and ``/diagnostics``."""

Qos = tuple[str, str]
"""``(reliability, durability)`` in lower case: ``reliable``/``best_effort``,
``volatile``/``transient_local``."""


def match_topics(patterns: Sequence[str], graph: Iterable[tuple[str, Sequence[str]]]
                 ) -> tuple[dict[str, str], list[str]]:
    """Select topics of the ROS graph to record.

    Args:
        patterns: topic names or shell-style patterns (``/dvt/cmd/*``).
        graph: ``(topic, [msgtype, ...])`` as ``Node.get_topic_names_and_types()`` returns.

    Returns:
        ``({topic: msgtype}, problems)``: every matching topic with exactly one type, and a
        message for each matching topic that has several types (not recorded).
    """
    chosen: dict[str, str] = {}
    problems: list[str] = []
    for topic, types in graph:
        if not any(fnmatchcase(topic, p) for p in patterns):
            continue
        if len(types) != 1:
            problems.append(f"topic {topic} has {len(types)} types {list(types)}; not recorded")
            continue
        chosen[topic] = types[0]
    return chosen, problems


def choose_qos(offered: Sequence[Qos]) -> Qos | None:
    """Subscription ``(reliability, durability)`` that matches every offered publisher.

    ``offered``: ``(reliability, durability)`` of each publisher, lower-case names
    (``reliable``/``best_effort``, ``volatile``/``transient_local``). A RELIABLE subscription
    does not match a BEST_EFFORT publisher, so RELIABLE is chosen only if every publisher
    offers it (the same rule as ``ros2 bag record``); likewise TRANSIENT_LOCAL. ``None`` when
    there is no publisher yet.
    """
    if not offered:
        return None
    reliability = "reliable" if all(r == "reliable" for r, _ in offered) else "best_effort"
    durability = ("transient_local" if all(d == "transient_local" for _, d in offered)
                  else "volatile")
    return reliability, durability


def needs_weaker(new: Qos, old: Qos) -> bool:
    """Whether QoS ``new`` is needed and weaker than ``old`` (so the subscription must change)."""
    return (new[0] == "best_effort" and old[0] == "reliable") or \
        (new[1] == "volatile" and old[1] == "transient_local")
