"""The agent's fallback link: an ``MqttEndpoint`` that says whether the robot is online.

``agent_mqtt_link(robot, settings, connection_payload)`` connects as ``settings`` say
(credentials, TLS, jittered backoff: links/mqtt.py) with the retained ``Connection`` at QoS 1 on
``fleetlink/v1/<robot>/connection`` as its voice: CONNECTIONBROKEN is the last will, ONLINE is
published after every (re)connect (the broker forgets nothing retained, but a will may have
replaced it while we were away), OFFLINE on a clean close. The node subscribes its inputs
(``AgentNode.subscribe``). Commands, acks, the lease and the connection travel at QoS 1,
telemetry at QoS 0 (the endpoint's ``QOS1_TOPICS``).
"""

from __future__ import annotations

from collections.abc import Callable

from fleetlink.links.mqtt import QOS1_TOPICS, MqttEndpoint, MqttMessage
from fleetlink.shared import keys
from fleetlink.shared.messages import ConnectionState
from fleetlink.shared.mqtt import MqttSettings

__all__ = ["QOS1_TOPICS", "agent_mqtt_link"]


def agent_mqtt_link(
    robot: str,
    settings: MqttSettings,
    connection_payload: Callable[[ConnectionState], bytes],
    *,
    client_id: str | None = None,
    seed: int | None = None,
) -> MqttEndpoint:
    """The agent's MQTT endpoint (not started); ``connection_payload(state)`` encodes a ``Connection``."""
    connection = keys.key(robot, "connection")

    def say(state: ConnectionState) -> Callable[[MqttEndpoint], None]:
        def publish(link: MqttEndpoint) -> None:
            link.publish(connection, connection_payload(state), qos=1, retain=True)

        return publish

    return MqttEndpoint(
        settings,
        client_id=client_id or f"agent-{robot}",
        will=MqttMessage(connection, connection_payload(ConnectionState.CONNECTIONBROKEN), qos=1, retain=True),
        on_connect=say(ConnectionState.ONLINE),
        on_close=say(ConnectionState.OFFLINE),
        seed=seed,
        label=f"mqtt-{robot}",
    )
