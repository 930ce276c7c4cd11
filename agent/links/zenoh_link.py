"""The agent's primary link: a ``ZenohEndpoint`` with the agent's presence token.

``agent_zenoh_link(robot, settings)`` opens (on ``start``) a session as ``settings`` say (listen,
connect, mode, login, TLS), declares the liveliness token ``fleetlink/alive/v1/<robot>``
(``keys.alive_key``: outside the robots' key tree, docs/wire-contract.md) while it is open. The
node subscribes its inputs (``AgentNode.subscribe``); samples reach it in arrival order
(links/zenoh.py says why that needs one delivery thread); the lease holder's command that finds
nothing queued is delivered on zenoh's own thread (``direct``: the node's input handler is short,
and the driver's command then reaches the board without a thread hop). Per-key QoS (commands and
acks express, telemetry DROP) is the endpoint's.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from fleetlink.links.zenoh import URGENT_TOPICS, ZenohEndpoint
from fleetlink.shared import keys

if TYPE_CHECKING:
    from fleetlink.agent.config import ZenohSettings

__all__ = ["URGENT_TOPICS", "agent_zenoh_link"]


def agent_zenoh_link(robot: str, settings: ZenohSettings) -> ZenohEndpoint:
    """The agent's Zenoh endpoint (not started)."""
    keys.check_robot_id(robot)
    return ZenohEndpoint(
        listen=settings.listen,
        connect=settings.connect,
        alive_key=keys.alive_key(robot),
        label=f"zenoh-{robot}",
        direct=True,
        mode=settings.mode,
        username=settings.username,
        password=settings.password,
        root_ca=settings.root_ca,
        tls_cert=settings.tls_cert,
        tls_key=settings.tls_key,
    )
