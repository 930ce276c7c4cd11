"""What a Control Bus master knows about its board, as one immutable value.

The agent's ``BoardSession`` replaces it whole on every change; displays (the operator's board
status, the field's live view) and the agent's core read it. No I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

from fleetlink.devices.controlbus import protocol as p

__all__ = ["BoardSnapshot"]


@dataclass(frozen=True, slots=True)
class BoardSnapshot:
    """Everything known about the board; replaced whole on every change (safe to share)."""

    connected: bool = False
    info: p.BaseInfo | None = None
    conf: p.BaseConf | None = None
    status: p.BaseStatus | None = None
    power: p.PowerData | None = None
    motor: p.MotorData | None = None
    sensors: p.SensorData | None = None
    bumpers: p.BumperData | None = None
    health: p.Health | None = None
    errors: tuple[p.HealthError, ...] = ()
    payload: p.PayloadStatus | None = None
    env: p.EnvData | None = None
    buttons: p.Buttons | None = None
    imu: p.ImuData | None = None
    # Dead reckoning integrated from SET_V_AND_GET_DEADRECKON deltas (odometry frame).
    odom: tuple[float, float, float] = (0.0, 0.0, 0.0)
    command: tuple[float, float] = (0.0, 0.0)  # vx m/s, omega rad/s being sent
    updated: float = 0.0  # clock time of the last successful poll
    connects: int = 0
    last_error: str = ""
    home_requests: int = 0  # go-home base commands the board raised (its home button), so far
