"""The VDA 5050 bridge assembled: the operator link (``open_operator_link``: Zenoh primary, MQTT
fallback) sending as the bridge's login, and the VDA 5050 broker's settings (docs/vda5050.md)."""

from __future__ import annotations

from collections.abc import Sequence

from fleetlink.operator.links import mqtt_settings_for
from fleetlink.operator.vda5050.bridge import MAX_VEHICLES, Vda5050Bridge
from fleetlink.shared.clock import Clock
from fleetlink.site.operator import open_operator_link

__all__ = ["DEFAULT_SENDER", "open_bridge"]

DEFAULT_SENDER = "vda5050"
"""The bridge's login (sender id): list it in the robots' allowed ``operators`` on a secured site."""


def open_bridge(
    clock: Clock,
    *,
    mqtt_url: str,
    vda_mqtt_url: str | None = None,
    zenoh_connect: Sequence[str] = (),
    zenoh_listen: Sequence[str] = (),
    sender: str = DEFAULT_SENDER,
    manufacturer: str = "fleetlink",
    interface: str = "uagv",
    map_id: str = "site",
    robots: Sequence[str] = (),
    state_period_s: float = 5.0,
    visualization_period_s: float = 1.0,
    max_vehicles: int = MAX_VEHICLES,
) -> Vda5050Bridge:
    """A bridge (not started). ``mqtt_url``: the fleet's broker (the operator link's fallback) and,
    unless ``vda_mqtt_url`` names another, the broker the master control speaks VDA 5050 on."""
    link = open_operator_link(
        clock,
        sender,
        mqtt_url=mqtt_url,
        zenoh_connect=zenoh_connect,
        zenoh_listen=zenoh_listen,
        client_id=f"{sender}-fleet",
    )
    return Vda5050Bridge(
        clock,
        link,
        mqtt_settings_for(vda_mqtt_url or mqtt_url),
        manufacturer=manufacturer,
        interface=interface,
        map_id=map_id,
        robots=robots,
        state_period_s=state_period_s,
        visualization_period_s=visualization_period_s,
        max_vehicles=max_vehicles,
    )
