"""Key expressions (Zenoh) and topics (MQTT): one scheme, one builder.

Every message lives at ``fleetlink/v1/<robot>/<topic>``. The same string is a Zenoh key expression
and an MQTT topic, so a bridge between the two never rewrites names.

* ``<robot>`` is a robot id: 1-64 characters from ``[A-Za-z0-9_-]``. That excludes every
  character with a meaning in either system (``/``, ``*``, ``#``, ``+``, ``$``, ``?``).
* ``<topic>`` is one or more ``/``-separated segments, each following the same rule as a robot
  id (e.g. ``board``, ``map/updates``), at most ``MAX_TOPIC_SEGMENTS`` of them.
* What people publish -- commands and marks (``SENDER_TOPICS``) -- carries one more segment, the
  sender's login: ``fleetlink/v1/<robot>/<topic>/<sender>`` (``sender_key``). A broker or router
  lets each login write only under its own name (shared/access.py), so on a secured site the key
  says who sent a command and the payload cannot claim otherwise (``wire.decode_key`` refuses a
  ``header.sender`` that differs). Receivers subscribe ``sender_filter(robot, topic)``.
* The robot id ``sim`` is reserved: ``fleetlink/v1/sim/<robot>/truth`` carries the simulator's
  ground truth about ``<robot>``. So that the all-robots wildcards never match a truth key, no
  ordinary topic may end in the segment ``truth``.
* Presence is not under the robots' key tree: each robot's Zenoh liveliness token is at
  ``fleetlink/alive/v1/<robot>`` (``alive_key``), watched with ``ZENOH_ALL_ALIVE``. Under
  ``fleetlink/v1/<robot>/alive``, next to the data keys, zenoh 1.10's routers spent 4-6 times the
  CPU per routed sample (docs/operations.md, "Scale"); nothing matching ``fleetlink/v1/**`` may
  hold a token.

Pure functions, no I/O. Every validator raises ``ValueError`` with a message naming the bad part.
"""

from __future__ import annotations

import functools
import re

__all__ = [
    "ALIVE_PREFIX",
    "ID_PATTERN",
    "INDEXED_TOPICS",
    "MAX_TOPIC_SEGMENTS",
    "MQTT_ALL",
    "MQTT_ALL_TRUTH",
    "PREFIX",
    "RESERVED_ROBOT_IDS",
    "SENDER_TOPICS",
    "SIM",
    "TRUTH_TOPIC",
    "ZENOH_ALL",
    "ZENOH_ALL_ALIVE",
    "ZENOH_ALL_TRUTH",
    "alive_key",
    "check_id",
    "check_robot_id",
    "check_topic",
    "indexed_key",
    "is_truth_key",
    "is_valid_id",
    "key",
    "mqtt_all_robots",
    "mqtt_robot",
    "parse_alive_key",
    "parse_key",
    "parse_truth_key",
    "sender_filter",
    "sender_key",
    "split_index",
    "split_sender",
    "topic_of",
    "truth_key",
    "zenoh_all_robots",
    "zenoh_robot",
]

PREFIX = "fleetlink/v1"
"""Interface name and major version of the key scheme; every key starts with it."""

ID_PATTERN = r"[A-Za-z0-9_-]{1,64}"
"""What a robot id, a sender id and each topic segment must match (in full)."""

SIM = "sim"
"""Reserved robot id: the simulation namespace ``fleetlink/v1/sim/<robot>/truth``."""

TRUTH_TOPIC = "truth"
"""The only topic in the simulation namespace (ground truth about one robot)."""

RESERVED_ROBOT_IDS = frozenset({SIM})

FLEET_MAP = "fleet"
"""The fleet map's place among the robots' maps: ``fleetlink/v1/fleet/map`` (site/fleetmap.py).
Not a robot: consoles draw it as the site's map and never drive it."""

MAX_TOPIC_SEGMENTS = 8

SENDER_TOPICS = frozenset({"order", "actions", "teleop", "lease/request", "zones", "marks", "marks/set", "alarms/ack"})
"""Topics people publish (commands, lease requests, marks and each console's retained set of
marks, alarm acknowledgements): their keys end in the sender's login, ``fleetlink/v1/<robot>/<topic>/<sender>``, so the
transport's access control vouches for it."""

INDEXED_TOPICS = frozenset({"map/submap"})
"""Topics with one key per item: ``fleetlink/v1/<robot>/<topic>/<n>`` (``indexed_key``), ``n`` the
message's ``index`` in decimal. A query on ``<topic>/*`` asks for every item, on ``<topic>/<n>``
for one (a robot's submaps: a console fetches only those it lacks)."""

MAX_INDEX = 999_999_999
"""The largest item index a key may carry (nine digits)."""

ZENOH_ALL = f"{PREFIX}/**"
"""Zenoh key expression matching every fleetlink key (including the sim namespace)."""

MQTT_ALL = f"{PREFIX}/#"
"""MQTT topic filter matching every fleetlink topic (including the sim namespace)."""

ZENOH_ALL_TRUTH = f"{PREFIX}/{SIM}/*/{TRUTH_TOPIC}"

ALIVE_PREFIX = "fleetlink/alive/v1"
"""Where the robots' Zenoh liveliness tokens live, one per robot: ``fleetlink/alive/v1/<robot>``.
Outside ``PREFIX`` on purpose (no ``fleetlink/v1/**`` expression matches a token); versioned
with the key scheme. Zenoh only: MQTT's presence is the retained ``connection`` message."""

ZENOH_ALL_ALIVE = f"{ALIVE_PREFIX}/*"
"""Zenoh key expression matching every robot's liveliness token (consoles and recorders watch it)."""
MQTT_ALL_TRUTH = f"{PREFIX}/{SIM}/+/{TRUTH_TOPIC}"

_ID_RE = re.compile(ID_PATTERN)
_PREFIX_SLASH = PREFIX + "/"
_SIM_PREFIX = f"{PREFIX}/{SIM}/"
_ALIVE_SLASH = ALIVE_PREFIX + "/"
_MAX_SHOWN = 80


def _show(value: object) -> str:
    text = repr(value)
    return text if len(text) <= _MAX_SHOWN else text[: _MAX_SHOWN - 3] + "..."


def is_valid_id(value: object) -> bool:
    """True if ``value`` is a string matching ``ID_PATTERN`` (robot ids, sender ids, segments)."""
    return isinstance(value, str) and _ID_RE.fullmatch(value) is not None


def check_id(value: object, what: str = "id") -> str:
    """Return ``value`` if it is a valid id (charset only, no reserved names), else ValueError."""
    if not isinstance(value, str):
        raise ValueError(f"invalid {what} {_show(value)}: expected a string, got {type(value).__name__}")
    if _ID_RE.fullmatch(value) is None:
        raise ValueError(f"invalid {what} {_show(value)}: must be 1-64 characters from [A-Za-z0-9_-]")
    return value


def check_robot_id(robot: object) -> str:
    """Return ``robot`` if it is a valid, unreserved robot id, else raise ValueError."""
    value = check_id(robot, "robot id")
    if value in RESERVED_ROBOT_IDS:
        raise ValueError(f"invalid robot id {value!r}: reserved for the simulation namespace")
    return value


def check_topic(topic: object) -> str:
    """Return ``topic`` if it is a valid ordinary topic name, else raise ValueError.

    A topic is 1-``MAX_TOPIC_SEGMENTS`` segments joined by ``/``, each a valid id. Its last
    segment may not be ``truth`` (reserved for the simulation namespace).
    """
    if not isinstance(topic, str):
        raise ValueError(f"invalid topic {_show(topic)}: expected a string, got {type(topic).__name__}")
    segments = topic.split("/")
    if len(segments) > MAX_TOPIC_SEGMENTS:
        raise ValueError(f"invalid topic {_show(topic)}: more than {MAX_TOPIC_SEGMENTS} segments")
    for segment in segments:
        if _ID_RE.fullmatch(segment) is None:
            raise ValueError(
                f"invalid topic {_show(topic)}: segment {_show(segment)} must be 1-64 characters from [A-Za-z0-9_-]"
            )
    if segments[-1] == TRUTH_TOPIC:
        raise ValueError(
            f"invalid topic {_show(topic)}: a final segment {TRUTH_TOPIC!r} is reserved for the "
            "simulation namespace (use truth_key())"
        )
    return topic


def key(robot: str, topic: str) -> str:
    """``fleetlink/v1/<robot>/<topic>``; the same string serves Zenoh and MQTT."""
    return f"{_PREFIX_SLASH}{check_robot_id(robot)}/{check_topic(topic)}"


def parse_key(key_expr: str) -> tuple[str, str]:
    """Split ``fleetlink/v1/<robot>/<topic>`` into ``(robot, topic)``; ValueError if malformed.

    Truth keys (``fleetlink/v1/sim/<robot>/truth``) are rejected here: check ``is_truth_key``
    first and use ``parse_truth_key`` for them.
    """
    if not isinstance(key_expr, str):
        raise ValueError(f"invalid key {_show(key_expr)}: expected a string, got {type(key_expr).__name__}")
    return _parse_key(key_expr)


@functools.lru_cache(maxsize=4096)
def _parse_key(key_expr: str) -> tuple[str, str]:
    # Cached: a subscriber sees the same few hundred keys over and over.
    if not key_expr.startswith(_PREFIX_SLASH):
        raise ValueError(f"invalid key {_show(key_expr)}: must start with {_PREFIX_SLASH!r}")
    robot, sep, topic = key_expr[len(_PREFIX_SLASH) :].partition("/")
    if not sep:
        raise ValueError(f"invalid key {_show(key_expr)}: expected {PREFIX}/<robot>/<topic>")
    if robot == SIM:
        raise ValueError(f"invalid key {_show(key_expr)}: {SIM!r} is the simulation namespace (use parse_truth_key())")
    try:
        check_robot_id(robot)
        check_topic(topic)
    except ValueError as exc:
        raise ValueError(f"invalid key {_show(key_expr)}: {exc}") from None
    return robot, topic


def sender_key(robot: str, topic: str, sender: str) -> str:
    """``fleetlink/v1/<robot>/<topic>/<sender>``: where ``sender`` publishes a ``SENDER_TOPICS`` message."""
    if topic not in SENDER_TOPICS:
        raise ValueError(f"topic {_show(topic)} is not published under its sender's name")
    return f"{key(robot, topic)}/{check_id(sender, 'sender id')}"


def sender_filter(robot: str, topic: str, sender: str = "*") -> str:
    """``fleetlink/v1/<robot>/<topic>/<sender>`` as a key expression: ``robot`` and ``sender`` may
    be ``*`` (any one); Zenoh syntax, which the MQTT link translates (``+``)."""
    if topic not in SENDER_TOPICS:
        raise ValueError(f"topic {_show(topic)} is not published under its sender's name")
    robot_part = robot if robot == "*" else check_robot_id(robot)
    sender_part = sender if sender == "*" else check_id(sender, "sender id")
    return f"{_PREFIX_SLASH}{robot_part}/{topic}/{sender_part}"


def split_sender(topic: str) -> tuple[str, str | None]:
    """A parsed key's topic as (message topic, sender): ``teleop/op-a`` -> (``teleop``, ``op-a``).

    Topics outside ``SENDER_TOPICS`` come back whole with sender None -- and so does a
    ``SENDER_TOPICS`` topic that lacks its sender segment (the caller refuses it).
    """
    head, sep, tail = topic.rpartition("/")
    if sep and head in SENDER_TOPICS:
        return head, tail
    return topic, None


def indexed_key(robot: str, topic: str, index: int | str) -> str:
    """``fleetlink/v1/<robot>/<topic>/<index>`` for an ``INDEXED_TOPICS`` topic; ``index`` may be
    ``*`` (every item, as a key expression to ask for)."""
    if topic not in INDEXED_TOPICS:
        raise ValueError(f"topic {_show(topic)} is not keyed by item")
    if index != "*" and not (isinstance(index, int) and not isinstance(index, bool) and 0 <= index <= MAX_INDEX):
        raise ValueError(f"invalid item index {_show(index)}: expected 0-{MAX_INDEX} or '*'")
    return f"{key(robot, topic)}/{index}"


def split_index(topic: str) -> tuple[str, int | None]:
    """A parsed key's topic as (message topic, item index): ``map/submap/12`` -> (``map/submap``, 12).

    Other topics come back whole with index None -- and so does an ``INDEXED_TOPICS`` topic without
    a decimal index (no sign, no leading zero, at most nine digits; the caller refuses it)."""
    head, sep, tail = topic.rpartition("/")
    if (
        sep
        and head in INDEXED_TOPICS
        and 0 < len(tail) <= 9
        and tail.isascii()
        and tail.isdigit()
        and (tail == "0" or tail[0] != "0")
    ):
        return head, int(tail)
    return topic, None


def topic_of(key_expr: str) -> str:
    """The message topic of ``fleetlink/v1/<robot>/<topic>[/<sender>]`` ("" for any other key);
    cheap (no validation): the links pick a quality of service by it for every message."""
    parts = key_expr.split("/", 3)
    if len(parts) != 4 or not key_expr.startswith(_PREFIX_SLASH):
        return ""
    topic, sender = split_sender(parts[3])
    return topic if sender is not None else split_index(topic)[0]


def truth_key(robot: str) -> str:
    """``fleetlink/v1/sim/<robot>/truth``: the simulator's ground truth about ``robot``."""
    return f"{_SIM_PREFIX}{check_robot_id(robot)}/{TRUTH_TOPIC}"


def is_truth_key(key_expr: str) -> bool:
    """True if ``key_expr`` is in the simulation namespace (well-formed or not)."""
    return isinstance(key_expr, str) and key_expr.startswith(_SIM_PREFIX)


def parse_truth_key(key_expr: str) -> str:
    """The robot id of a truth key ``fleetlink/v1/sim/<robot>/truth``; ValueError if malformed."""
    if not is_truth_key(key_expr):
        raise ValueError(f"invalid truth key {_show(key_expr)}: must start with {_SIM_PREFIX!r}")
    robot, sep, topic = key_expr[len(_SIM_PREFIX) :].partition("/")
    if not sep or topic != TRUTH_TOPIC:
        raise ValueError(f"invalid truth key {_show(key_expr)}: expected {_SIM_PREFIX}<robot>/{TRUTH_TOPIC}")
    try:
        return check_robot_id(robot)
    except ValueError as exc:
        raise ValueError(f"invalid truth key {_show(key_expr)}: {exc}") from None


def alive_key(robot: str) -> str:
    """``fleetlink/alive/v1/<robot>``: the key of ``robot``'s liveliness token (its presence on Zenoh)."""
    return f"{_ALIVE_SLASH}{check_robot_id(robot)}"


def parse_alive_key(key_expr: object) -> str:
    """The robot id of a liveliness token key ``fleetlink/alive/v1/<robot>``; ValueError naming the
    bad part for anything else (another prefix, an extra segment, an invalid or reserved id)."""
    if not isinstance(key_expr, str):
        raise ValueError(f"invalid token key {_show(key_expr)}: expected a string, got {type(key_expr).__name__}")
    if not key_expr.startswith(_ALIVE_SLASH):
        raise ValueError(f"invalid token key {_show(key_expr)}: must start with {_ALIVE_SLASH!r}")
    try:
        return check_robot_id(key_expr[len(_ALIVE_SLASH) :])
    except ValueError as exc:
        raise ValueError(f"invalid token key {_show(key_expr)}: {exc}") from None


def zenoh_all_robots(topic: str) -> str:
    """Zenoh key expression for ``topic`` from every robot: ``fleetlink/v1/*/<topic>``."""
    return f"{_PREFIX_SLASH}*/{check_topic(topic)}"


def mqtt_all_robots(topic: str) -> str:
    """MQTT topic filter for ``topic`` from every robot: ``fleetlink/v1/+/<topic>``."""
    return f"{_PREFIX_SLASH}+/{check_topic(topic)}"


def zenoh_robot(robot: str) -> str:
    """Zenoh key expression for every topic of one robot: ``fleetlink/v1/<robot>/**``."""
    return f"{_PREFIX_SLASH}{check_robot_id(robot)}/**"


def mqtt_robot(robot: str) -> str:
    """MQTT topic filter for every topic of one robot: ``fleetlink/v1/<robot>/#``."""
    return f"{_PREFIX_SLASH}{check_robot_id(robot)}/#"
