"""The VDA 5050 bridge's shell without a broker: a flood of fleetlink ``State`` under ever new robot
ids does not grow the bridge without bound (capped, counted, logged once; it keeps serving)."""

from __future__ import annotations

import logging
from typing import Any

import pytest

from fleetlink.operator.vda5050 import bridge as bridge_module
from fleetlink.operator.vda5050.bridge import Vda5050Bridge
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import (
    AgvPosition,
    BatteryState,
    CommsPolicy,
    Contact,
    EStop,
    LinkStatus,
    OperatingMode,
    SafetyState,
    State,
    Velocity,
)
from fleetlink.shared.mqtt import MqttSettings


class FakeEndpoint:
    """Stands in for ``links.mqtt.MqttEndpoint``: records what the vehicle would publish."""

    made = 0

    def __init__(self, settings: Any, **kwargs: Any) -> None:
        FakeEndpoint.made += 1
        self.published: list[tuple[str, bytes]] = []

    def subscribe(self, topic: str, handler: Any) -> None:
        pass

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def publish(self, topic: str, payload: bytes, **kwargs: Any) -> None:
        self.published.append((topic, payload))


class FakeLink:
    sender = "vda5050"

    def add_sink(self, sink: Any) -> None:
        pass

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass


def state(robot: str) -> State:
    counter = wire.HeaderCounter(SimClock(), robot=robot, sender=f"agent-{robot}")
    return counter.make(
        State,
        agvPosition=AgvPosition(x=0.0, y=0.0, theta=0.0, mapId="", positionInitialized=True, localizationScore=1.0),
        velocity=Velocity(vx=0.0, omega=0.0),
        batteryState=BatteryState(batteryCharge=80.0, charging=False),
        errors=(),
        operatingMode=OperatingMode.AUTOMATIC,
        safetyState=SafetyState(eStop=EStop.NONE, fieldViolation=False),
        driveMode="idle",
        links=LinkStatus(zenoh=True, mqtt=True),
        uwbStale=False,
        payloadOn=False,
        boardConnected=True,
        orderId="",
        orderUpdateId=0,
        goal=None,
        driving=False,
        paused=False,
        home=None,
        contact=Contact(policy=CommsPolicy.STOP, lost=False, action="", silent_s=0.0),
        progress=None,
    )


def test_a_flood_of_new_robot_ids_is_capped_counted_and_logged_once(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(bridge_module, "MqttEndpoint", FakeEndpoint)
    FakeEndpoint.made = 0
    clock = SimClock()
    b = Vda5050Bridge(clock, FakeLink(), MqttSettings("127.0.0.1", 1), max_vehicles=4)  # type: ignore[arg-type]
    caplog.set_level(logging.WARNING, logger=bridge_module.__name__)
    for i in range(200):
        b._fleet(state(f"r{i}"), "zenoh", clock.now())
    assert len(b.vehicles) == 4 and FakeEndpoint.made == 4
    assert b.refused_vehicles == 196
    warnings = [r for r in caplog.records if "not served" in r.getMessage()]
    assert len(warnings) == 1 and "max_vehicles" in warnings[0].getMessage()
    # The robots served keep being served: their state still goes out.
    before = len(b.vehicles["r0"].endpoint.published)  # type: ignore[attr-defined]
    b._fleet(state("r0"), "zenoh", clock.now())
    b.vehicles["r0"].core._next_state = float("-inf")
    b._fleet(state("r0"), "zenoh", clock.now())
    assert len(b.vehicles["r0"].endpoint.published) > before  # type: ignore[attr-defined]
    assert set(b.stats()) == {"r0", "r1", "r2", "r3"}
