"""Who may say what: one access policy, rendered for Mosquitto (ACL file) and Zenoh (``access_control``).

Usernames (the same on both links, docs/operations.md):

* an agent logs in as its robot id (``r1``); it writes only its own telemetry and reads only its
  own commands and UWB fixes, and every robot's pose (``PEER_READS``: its peers, planned around);
* an operator logs in as ``op-<name>``; it reads everything and writes commands to any robot, but
  only under its own name: ``fleetlink/v1/<robot>/<command>/op-<name>`` (``keys.SENDER_TOPICS``),
  and the agent refuses a command whose ``header.sender`` is not that name. So the agent knows who
  sent a command from the login, not from the payload (whether a robot *obeys* is the agent's
  business: allowed operators, the control lease);
* the positioning system logs in as ``uwb-gateway`` and writes only fixes;
* the simulated field logs in as ``sim`` and writes only ground truth (test sites only);
* another site's router logs in as ``router-<site>`` (Zenoh only) and may exchange everything.

Robot ids may therefore not start with ``op-`` or ``router-`` nor be ``uwb-gateway`` (``sim`` is
already reserved by ``shared.keys``); ``check_robot_username`` enforces it.

Mosquitto needs per-robot lines only for the peers' poses (a robot's own topics are ``pattern ...
%u``; a pattern with no ``%u`` would grant every user, the gateway and the simulator too); Zenoh's
ACL has no such substitution, so its rules list every robot. Both renderings come from the tables
below, so they cannot drift; ``python -m fleetlink.shared.access --robot r1 --robot r2 --operator
op-alice`` prints both.
Pure functions, no I/O (except under ``__main__``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from typing import Any

from fleetlink.shared.keys import (
    FLEET_MAP,
    PREFIX,
    SENDER_TOPICS,
    ZENOH_ALL_ALIVE,
    alive_key,
    check_id,
    check_robot_id,
)

__all__ = [
    "AGENT_READS",
    "AGENT_WRITES",
    "COMMAND_TOPICS",
    "GATEWAY_USER",
    "GATEWAY_WRITES_MQTT",
    "OPERATOR_PREFIX",
    "OPERATOR_WRITES",
    "ROUTER_PREFIX",
    "SIM_USER",
    "check_operator_username",
    "check_robot_username",
    "mosquitto_acl",
    "zenoh_access_control",
]

OPERATOR_PREFIX = "op-"
ROUTER_PREFIX = "router-"
GATEWAY_USER = "uwb-gateway"
SIM_USER = "sim"

AGENT_WRITES: tuple[str, ...] = ("state", "pose", "connection", "ack", "events", "board", "lease", "map", "dose")
"""Topics an agent publishes about itself (``map`` and ``dose`` include everything below them, e.g.
``map/updates``, ``dose/updates``)."""

SERVED: tuple[str, ...] = ("map", "dose")
"""What an agent answers queries on (Zenoh queryables): its map and its UV dose layer."""

COMMAND_TOPICS: tuple[str, ...] = ("order", "actions", "teleop", "lease/request", "zones")
"""Topics operators publish to a robot, each under the operator's name; the robot reads only its own."""

OPERATOR_WRITES: tuple[str, ...] = (*COMMAND_TOPICS, "marks", "marks/set", "alarms/ack")
"""Commands, and the marks operators share with each other (``fleetlink/v1/<robot>/marks/<op>``,
and each console's retained set ``fleetlink/v1/<robot>/marks/set/<op>``), and each console's
retained alarm acknowledgements (``fleetlink/v1/<robot>/alarms/ack/<op>``; agents never read them)."""

assert set(OPERATOR_WRITES) == SENDER_TOPICS  # what people write is keyed by their name

FIX_TOPICS: tuple[str, ...] = ("uwb", "uwb/ranges")
"""UWB fixes: written only by the positioning system, read by the robot they are about."""

AGENT_READS: tuple[str, ...] = COMMAND_TOPICS + FIX_TOPICS

PEER_READS: tuple[str, ...] = ("pose",)
"""What an agent reads of every other robot: its fused pose, to plan around it and not drive into it
(robot.toml's ``peers``, agent/peers.py). Read only: a robot still writes nothing but its own."""

DWM_FIX_TOPICS: tuple[str, ...] = ("dwm/node/+/uplink/location", "dwm/node/+/uplink/status")
"""Decawave PANS gateway topics (MQTT only) the positioning system may also write."""

GATEWAY_STATUS_MQTT = "fleetlink/uwb/+/status"
"""The gateway's own retained status and last will (positioning/gateway.py ``status_topic``)."""

GATEWAY_WRITES_MQTT: tuple[str, ...] = (
    *(f"{PREFIX}/+/{t}" for t in FIX_TOPICS),
    *DWM_FIX_TOPICS,
    GATEWAY_STATUS_MQTT,
)

_SUBTREE = frozenset({"map", "dose"})  # topics that own a subtree of keys
FLEET_FRAMES = "frames"
"""The fleet map service's ``FleetFrames`` topic (under the id ``fleet``)."""


def check_robot_username(robot: str) -> str:
    """A robot id that is also safe as a broker username (not an operator, router or the gateway)."""
    check_robot_id(robot)
    if robot.startswith((OPERATOR_PREFIX, ROUTER_PREFIX)) or robot == GATEWAY_USER:
        raise ValueError(
            f"invalid robot id {robot!r}: ids starting with {OPERATOR_PREFIX!r} or {ROUTER_PREFIX!r} "
            f"and {GATEWAY_USER!r} are broker usernames of other roles"
        )
    if robot == FLEET_MAP:
        raise ValueError(f"invalid robot id {robot!r}: the consoles share the fleet map under it")
    return robot


def check_operator_username(name: str) -> str:
    check_id(name, "operator username")
    if not name.startswith(OPERATOR_PREFIX) or len(name) == len(OPERATOR_PREFIX):
        raise ValueError(f"invalid operator username {name!r}: must be {OPERATOR_PREFIX}<name>")
    return name


def _mqtt(robot: str, topic: str, sender: str = "+") -> str:
    if topic in SENDER_TOPICS:
        return f"{PREFIX}/{robot}/{topic}/{sender}"
    return f"{PREFIX}/{robot}/{topic}/#" if topic in _SUBTREE else f"{PREFIX}/{robot}/{topic}"


def _zenoh(robot: str, topic: str, sender: str = "*") -> str:
    if topic in SENDER_TOPICS:
        return f"{PREFIX}/{robot}/{topic}/{sender}"
    return f"{PREFIX}/{robot}/{topic}/**" if topic in _SUBTREE else f"{PREFIX}/{robot}/{topic}"


def mosquitto_acl(operators: Iterable[str] = (), robots: Iterable[str] = ()) -> str:
    """The Mosquitto ``acl_file`` text. A robot's own topics need no lines of its own (``%u`` is the
    robot id); the ``robots`` named here may also read every robot's pose (``PEER_READS``)."""
    ops = [check_operator_username(o) for o in operators]
    bots = [check_robot_username(r) for r in robots]
    lines = [
        "# fleetlink Mosquitto ACL. Generated from shared/access.py (python -m fleetlink.shared.access);",
        "# regenerate rather than edit. Anything not granted here is denied: unauthorised publishes are",
        "# dropped by the broker, unauthorised subscriptions receive nothing.",
        "#",
        "# Agents log in with their robot id as username: they write only their own telemetry and read",
        "# only their own commands and fixes. Patterns apply to every user; the role prefixes (op-,",
        "# router-, uwb-gateway, sim) are not valid robot ids, so they grant other roles nothing useful.",
    ]
    lines += [f"pattern write {_mqtt('%u', t)}" for t in AGENT_WRITES]
    lines += [f"pattern read {_mqtt('%u', t)}" for t in AGENT_READS]
    lines += [
        "# PANS tag locations straight from a DWM1001 gateway: tag ids are not robot ids, so every",
        "# user may read every tag's location (read only; only uwb-gateway writes them).",
    ]
    lines += [f"pattern read {DWM_FIX_TOPICS[0]}"]
    lines += ["", "# The positioning system writes fixes and nothing else; it may read the simulator's truth."]
    lines += [f"user {GATEWAY_USER}"]
    lines += [f"topic write {t}" for t in GATEWAY_WRITES_MQTT]
    lines += [f"topic read {PREFIX}/{SIM_USER}/+/truth", "topic read dwm/#"]
    lines += ["", "# The simulated field (test sites only) writes ground truth."]
    lines += [f"user {SIM_USER}", f"topic write {PREFIX}/{SIM_USER}/+/truth"]
    lines += ["", "# Robots read every robot's pose (their peers: agent/peers.py), read only. One block per robot."]
    for robot in bots:
        lines += [f"user {robot}"]
        lines += [f"topic read {_mqtt('+', t)}" for t in PEER_READS]
    lines += [
        "",
        "# Operators: read everything, write commands to any robot, each only under its own name (the",
        "# last segment), which the agent checks against header.sender. One block per operator.",
    ]
    for op in ops:
        lines += [f"user {op}"]
        lines += [f"topic write {_mqtt('+', t, op)}" for t in OPERATOR_WRITES]
        lines += [f"topic read {PREFIX}/#", f"topic read {GATEWAY_STATUS_MQTT}", "topic read dwm/#"]
    return "\n".join(lines) + "\n"


_ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]


def _rule(rule_id: str, flows: Sequence[str], messages: Sequence[str], key_exprs: Sequence[str]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "permission": "allow",
        "flows": list(flows),
        "messages": list(messages),
        "key_exprs": list(key_exprs),
    }


def zenoh_access_control(
    robots: Iterable[str], operators: Iterable[str] = (), routers: Iterable[str] = (), *, simulator: bool = False
) -> dict[str, Any]:
    """The router's ``access_control`` section: default deny, one subject per username.

    Flows are seen from the router: ``ingress`` is what a client sends it (its puts, its
    subscriptions), ``egress`` what the router forwards to the client. Each grant is given in
    both directions where it applies, so a client can neither send nor receive what it may not.
    """
    robot_ids = [check_robot_username(r) for r in robots]
    ops = [check_operator_username(o) for o in operators]
    peers = [check_id(r, "router username") for r in routers]
    for r in peers:
        if not r.startswith(ROUTER_PREFIX):
            raise ValueError(f"invalid router username {r!r}: must be {ROUTER_PREFIX}<site>")
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def grant(
        subject: str, usernames: list[str], subject_rules: list[dict[str, Any]], shared: Sequence[str] = ()
    ) -> None:
        """``subject_rules`` are new rules; ``shared`` names rules granted already (to another subject)."""
        if not usernames:
            return
        rules.extend(subject_rules)
        subjects.append({"id": subject, "usernames": usernames})
        ids = [*shared, *(r["id"] for r in subject_rules if r["id"] not in shared)]
        policies.append({"id": subject, "rules": ids, "subjects": [subject]})

    # ... and where the fleet map service found the robots in their own frames (no UWB), which puts
    # such a peer in its frame (agent/peers.py). Zenoh only: the service shares on the console's link.
    peer_reads = [*(_zenoh("*", t) for t in PEER_READS), _zenoh(FLEET_MAP, FLEET_FRAMES)]
    for robot in robot_ids:
        writes = [_zenoh(robot, t) for t in AGENT_WRITES]
        reads = [_zenoh(robot, t) for t in AGENT_READS]
        own = f"{PREFIX}/{robot}/**"
        grant(
            f"robot-{robot}",
            [robot],
            [
                _rule(f"{robot}-publish", ["ingress"], ["put", "delete"], writes),
                # Subscribing anywhere in its own subtree is allowed (the agent may declare one
                # wildcard subscriber); what it receives is limited on egress to its inputs.
                _rule(f"{robot}-subscribe", ["ingress"], ["declare_subscriber"], [own]),
                _rule(f"{robot}-commands-in", ["egress"], ["put", "delete"], reads),
                # The other robots' poses (its peers), read only.
                _rule(f"{robot}-peers-subscribe", ["ingress"], ["declare_subscriber"], peer_reads),
                _rule(f"{robot}-peers-in", ["egress"], ["put"], peer_reads),
                # Its presence: one liveliness token, its own (keys.alive_key), outside its key tree.
                _rule(f"{robot}-presence", ["ingress"], ["liveliness_token"], [alive_key(robot)]),
                _rule(
                    f"{robot}-serve", ["ingress"], ["declare_queryable", "reply"], [_zenoh(robot, t) for t in SERVED]
                ),
                _rule(f"{robot}-queries", ["egress"], ["query"], [_zenoh(robot, t) for t in SERVED]),
            ],
        )
    fixes = [f"{PREFIX}/*/{t}" for t in FIX_TOPICS]
    truth = [f"{PREFIX}/{SIM_USER}/*/truth"]
    grant(
        "uwb-gateway",
        [GATEWAY_USER],
        [
            _rule("gateway-fixes", ["ingress"], ["put", "delete"], [*fixes, "fleetlink/uwb/*/status"]),
            _rule("gateway-truth", ["ingress"], ["declare_subscriber"], truth),
            _rule("gateway-truth-in", ["egress"], ["put"], truth),
        ],
    )
    if simulator:
        grant("simulator", [SIM_USER], [_rule("sim-truth", ["ingress"], ["put"], truth)])
    everything = [f"{PREFIX}/**"]
    presence = [ZENOH_ALL_ALIVE]  # every robot's liveliness token
    watch = [
        _rule(
            "operator-watch",
            ["ingress"],
            ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"],
            [*everything, *presence, "fleetlink/uwb/*/status"],
        ),
        _rule(
            "operator-watch-in",
            ["egress"],
            ["put", "delete", "reply", "liveliness_token"],
            [*everything, *presence, "fleetlink/uwb/*/status"],
        ),
        # Consoles that start late ask every console for its marks (operator/links.py MARKS_QUERY).
        _rule("operator-marks-queries", ["egress"], ["query"], [_zenoh("*", "marks")]),
        # Each console builds the fleet map (site/fleetmap.py) and shares it as a robot shares its
        # map, under the id ``fleet``, with where the robots in their own frames lie on it.
        _rule(
            "operator-fleet-map",
            ["ingress"],
            ["put", "delete"],
            [_zenoh(FLEET_MAP, "map"), _zenoh(FLEET_MAP, FLEET_FRAMES)],
        ),
        _rule("operator-serve-fleet-map", ["ingress"], ["declare_queryable", "reply"], [_zenoh(FLEET_MAP, "map")]),
        _rule("operator-fleet-map-queries", ["egress"], ["query"], [_zenoh(FLEET_MAP, "map")]),
    ]
    for i, op in enumerate(ops):
        # One subject per operator: it writes commands and marks only under its own name, and
        # answers marks queries only with its own marks.
        mine = [
            _rule(f"{op}-commands", ["ingress"], ["put"], [_zenoh("*", t, op) for t in OPERATOR_WRITES]),
            _rule(f"{op}-serve-marks", ["ingress"], ["declare_queryable", "reply"], [_zenoh("*", "marks", op)]),
        ]
        grant(f"operator-{op}", [op], (watch if i == 0 else []) + mine, shared=[r["id"] for r in watch])
    grant("routers", peers, [_rule("router-link", ["ingress", "egress"], _ALL_MESSAGES, [*everything, *presence])])
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="Print the Mosquitto ACL and the Zenoh access_control section.")
    parser.add_argument("--robot", action="append", default=[], help="robot id (both list every robot)")
    parser.add_argument("--operator", action="append", default=[], help="op-<name>")
    parser.add_argument("--router", action="append", default=[], help="router-<site> (linked site routers)")
    parser.add_argument("--simulator", action="store_true", help="let the simulated field (user sim) publish truth")
    parser.add_argument("--what", choices=("mosquitto", "zenoh"), default="mosquitto")
    args = parser.parse_args()
    if args.what == "mosquitto":
        print(mosquitto_acl(args.operator, args.robot), end="")
    else:
        section = zenoh_access_control(args.robot, args.operator, args.router, simulator=args.simulator)
        print(json.dumps({"access_control": section}, indent=2))
