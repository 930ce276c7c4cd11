"""What a robot's agent says, for tests that speak for one: a ``State`` and a ``BoardStatus`` with
every field at a plain default, overridden by keyword (one place to follow the wire contract)."""

from __future__ import annotations

from typing import Any

from fleetlink.shared import wire
from fleetlink.shared.messages import (
    AgvPosition,
    BatteryState,
    BoardStatus,
    CommsPolicy,
    Contact,
    EStop,
    LinkStatus,
    OperatingMode,
    SafetyState,
    State,
    Velocity,
)

__all__ = ["board_fields", "board_status", "state", "state_fields"]


def state_fields(**over: Any) -> dict[str, Any]:
    """An idle, localised robot with both links up, at (0, 0); ``over`` replaces any field."""
    fields: dict[str, Any] = {
        "agvPosition": AgvPosition(x=0.0, y=0.0, theta=0.0, mapId="m", positionInitialized=True, localizationScore=0.9),
        "velocity": Velocity(vx=0.0, omega=0.0),
        "batteryState": BatteryState(batteryCharge=80.0, charging=False),
        "errors": (),
        "operatingMode": OperatingMode.SEMIAUTOMATIC,
        "safetyState": SafetyState(eStop=EStop.NONE, fieldViolation=False),
        "driveMode": "idle",
        "links": LinkStatus(zenoh=True, mqtt=True),
        "uwbStale": False,
        "payloadOn": False,
        "boardConnected": True,
        "orderId": "",
        "orderUpdateId": 0,
        "goal": None,
        "driving": False,
        "paused": False,
        "home": None,
        "contact": Contact(policy=CommsPolicy.STOP, lost=False, action="", silent_s=0.0),
    }
    fields.update(over)
    return fields


def state(counter: wire.HeaderCounter, **over: Any) -> State:
    return counter.make(State, **state_fields(**over))


def board_fields(**over: Any) -> dict[str, Any]:
    """A connected board at 80 % with an 80 % tank, nothing on, no fault; ``over`` replaces any field."""
    fields: dict[str, Any] = {
        "connected": True, "model": "sim", "firmware": "1.2", "battery_percent": 80.0, "battery_voltage_v": None,
        "battery_current_a": None, "charging": False, "on_dock": False, "temperature_c": None,
        "humidity_percent": None, "pm2_5_ug_m3": None, "tvoc_ppb": None, "uv_lamp": False, "atomiser_level": 0,
        "fan_level": 0, "has_payload": True, "tank_percent": 80.0, "estop_button": False, "health_flags": 0, "faults": (), "bumpers": 0,
        "sensors_m": (), "watchdog_trips": 0,
    }  # fmt: skip
    fields.update(over)
    return fields


def board_status(counter: wire.HeaderCounter, **over: Any) -> BoardStatus:
    return counter.make(BoardStatus, **board_fields(**over))
