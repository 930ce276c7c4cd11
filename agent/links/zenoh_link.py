"""The agent's primary link: a ``ZenohEndpoint`` with the agent's presence token.

``agent_zenoh_link(robot, settings)`` opens (on ``start``) a session as ``settings`` say (listen,
connect, mode, login, TLS), declares the liveliness token ``fleetlink/v1/<robot>/alive`` while it
is open, and, given ``on_input``, subscribes the agent's input keys and hands every sample to
``on_input(LinkName.ZENOH, key, payload)`` in arrival order (links/zenoh.py says why that needs
one delivery thread). Per-key QoS (commands and acks express, telemetry DROP) is the endpoint's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from fleetlink.links.zenoh import URGENT_TOPICS, ZenohEndpoint
from fleetlink.shared import keys
from fleetlink.shared.messages import LinkName

if TYPE_CHECKING:
    from fleetlink.agent.config import ZenohSettings

__all__ = ["ALIVE_TOPIC", "URGENT_TOPICS", "agent_zenoh_link"]

ALIVE_TOPIC = "alive"

OnInput = Callable[[LinkName, str, bytes], None]


def agent_zenoh_link(
    robot: str,
    settings: ZenohSettings,
    *,
    on_input: OnInput | None = None,
    inputs: Sequence[str] = ("order", "actions", "teleop"),
    extra_keys: Sequence[str] = (),
) -> ZenohEndpoint:
    """The agent's Zenoh endpoint (not started). ``on_input``: subscribe ``inputs`` (topics of
    ``robot``) and ``extra_keys`` (full keys) to it; without it the caller subscribes."""
    keys.check_robot_id(robot)
    link = ZenohEndpoint(
        listen=settings.listen,
        connect=settings.connect,
        alive_key=keys.key(robot, ALIVE_TOPIC),
        label=f"zenoh-{robot}",
        mode=settings.mode,
        username=settings.username,
        password=settings.password,
        root_ca=settings.root_ca,
        tls_cert=settings.tls_cert,
        tls_key=settings.tls_key,
    )
    if on_input is not None:

        def receive(key: str, payload: bytes) -> None:
            on_input(LinkName.ZENOH, key, payload)

        for k in [keys.key(robot, t) for t in inputs] + list(extra_keys):
            link.subscribe(k, receive)
    return link
