"""Plain-text rendering of a robot's board status, for the terminal demo and logs.

Pure: a ``BoardSnapshot`` in, lines of text out. The Textual console reuses it for its detail pane.
"""

from __future__ import annotations

import math

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.snapshot import BoardSnapshot


def render(robot: str, snap: BoardSnapshot, now: float) -> list[str]:
    """Lines describing the board; ``now`` is the same clock that stamped ``snap.updated``."""
    if not snap.connected:
        reason = snap.last_error or "connecting"
        return [f"{robot}: board DISCONNECTED ({reason})"]
    info = snap.info
    lines = [
        f"{robot}: {info.model if info else '?'} firmware {info.firmware_text if info else '?'}"
        f"   link up (connects: {snap.connects}, last poll {max(0.0, now - snap.updated) * 1000:.0f} ms ago)"
    ]
    x, y, th = snap.odom
    vx, w = snap.command
    lines.append(
        f"  odometry   x {x:+7.3f} m  y {y:+7.3f} m  heading {math.degrees(th):+6.1f}°   command {vx:+.2f} m/s {w:+.2f} rad/s"
    )
    if snap.motor:
        m = snap.motor
        stall = "  STALL" if m.status & p.MotorStatus.STALL else ""
        lines.append(f"  wheels     left {m.left:8.3f} m   right {m.right:8.3f} m{stall}")
    if snap.status:
        s = snap.status
        volts = f" {snap.power.voltage:.2f} V" if snap.power else ""
        charging = "  charging" if s.charging else ""
        lines.append(f"  battery    {s.battery_percent:3d} %{volts}{charging}")
    if snap.sensors:
        front = snap.sensors.distances[0]
        lines.append(f"  ultrasonic {'no echo' if front <= 0 else f'{front:.2f} m'}")
    if snap.bumpers:
        b = snap.bumpers
        hits = [
            name for bit, name in ((0, "bumper L"), (1, "bumper R"), (2, "cliff L"), (3, "cliff R")) if b.triggered(bit)
        ]
        lines.append(f"  contacts   {', '.join(hits) if hits else 'clear'}")
    if snap.payload:
        pl = snap.payload
        lines.append(
            f"  payload    UV-C {'ON' if pl.uv_lamp else 'off'}  atomiser {pl.atomiser_level}  fan {pl.fan_level}  tank {pl.tank_percent} %"
        )
    if snap.env:
        e = snap.env
        lines.append(
            f"  air        {e.temperature_c:.1f} °C  {e.humidity_percent:.0f} % RH  PM2.5 {e.pm2_5:.1f}  TVOC {e.tvoc_ppb} ppb"
        )
    health = "ok" if not snap.errors else "; ".join(f"0x{e.code:04X} {e.message}" for e in snap.errors)
    lines.append(f"  health     {health}")
    return lines
