"""The operator's link to a fleet, assembled in one place: Zenoh (primary) and MQTT (fallback).

Every console (the field's own, ``fleetlink console`` joining a fleet, a secured site's) gets its
``OperatorLink`` from ``open_operator_link``, so logins, TLS and client ids are set one way.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from fleetlink.shared.clock import Clock
from fleetlink.shared.mqtt import MqttSettings

if TYPE_CHECKING:
    from fleetlink.operator.linkmanager import LinkPolicy
    from fleetlink.operator.links import OperatorLink

__all__ = ["open_operator_link"]


def open_operator_link(
    clock: Clock,
    operator: str,
    *,
    mqtt_url: str,
    mqtt: MqttSettings | None = None,
    zenoh_listen: Sequence[str] = (),
    zenoh_connect: Sequence[str] = (),
    zenoh_auth: Mapping[str, Any] | None = None,
    client_id: str | None = None,
    policy: LinkPolicy | None = None,
) -> OperatorLink:
    """An ``OperatorLink`` (not started) sending as ``operator``.

    ``zenoh_auth``: ``peer_config``'s ``mode``, ``username``, ``password``, ``root_ca`` (a secured
    router). ``mqtt``: credentials and TLS for the broker, winning over ``mqtt_url``. ``client_id``
    (default: the operator id) must be unique on the broker. ``policy``: the link manager's
    (default: its defaults with redundant sending on -- every command on both links).
    """
    from fleetlink.links.mqtt import MqttEndpoint
    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.operator.linkmanager import LinkPolicy
    from fleetlink.operator.links import OperatorLink, mqtt_settings_for

    primary = ZenohEndpoint(listen=zenoh_listen, connect=zenoh_connect, label="zenoh-console", **dict(zenoh_auth or {}))
    fallback = MqttEndpoint(mqtt or mqtt_settings_for(mqtt_url), client_id=client_id or operator, label="mqtt-console")
    return OperatorLink(clock, operator, primary, fallback, policy=policy or LinkPolicy(redundant=True))
