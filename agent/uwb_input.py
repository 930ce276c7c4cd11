"""UWB fixes in, ``FixObservation`` out: the native ``UwbFix`` message and Qorvo DWM1001 PANS JSON.

Pure. Malformed input raises ``ValueError`` with the reason (the caller counts it and logs it once);
nothing here crashes on bytes from the network.

Time: a fix carries the sender's *wall* time of the ranging (``measured_at``, PANS ``timestamp``);
the agent's fusion runs on its ``Clock.now()`` (monotonic). Every parser takes
``wall_minus_monotonic`` = ``clock.wall() - clock.now()`` sampled by the receiver, and this is the one
place where the conversion happens: ``t_measured = measured_at - wall_minus_monotonic``. A sender
whose clock is off by some amount shifts its fixes by that amount (keep clocks NTP-synced; the fusion
rejects fixes from the future and ones older than its history).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from typing import Any, Protocol

__all__ = [
    "FixObservation",
    "UwbFixLike",
    "fix_from_pans",
    "fix_from_uwb",
    "pans_node_id",
    "quality_to_sd",
]

MAX_PANS_BYTES = 4096  # a PANS location payload is ~120 bytes
MAX_COORD_M = 10_000.0  # anything farther is nonsense for an indoor RTLS
_PANS_TOPIC = re.compile(r"^(?:.+/)?node/([0-9A-Za-z_-]{1,64})/uplink/location$")


@dataclass(frozen=True, slots=True)
class FixObservation:
    """One position fix, on the agent's monotonic clock, in the UWB/map frame (metres)."""

    t_measured: float
    x: float
    y: float
    sd_x: float
    sd_y: float
    quality: int  # 0-100 %
    source: str  # "native" or "pans"
    tag: str = ""


class UwbFixLike(Protocol):
    """What ``fix_from_uwb`` reads of ``fleetlink.shared.messages.UwbFix``."""

    @property
    def tag(self) -> str: ...
    @property
    def x(self) -> float: ...
    @property
    def y(self) -> float: ...
    @property
    def sd_x(self) -> float: ...
    @property
    def sd_y(self) -> float: ...
    @property
    def quality(self) -> int: ...
    @property
    def status(self) -> str: ...
    @property
    def measured_at(self) -> float: ...


def quality_to_sd(quality: float) -> float:
    """A standard deviation (m) for a fix that only has a 0-100 quality (PANS).

    The inverse of the native fix's own quality rule (100 % when sd <= 0.1 m, falling as 1/sd):
    sd = 0.1 m * 100 / quality, capped at 5 m for quality 0-2.
    """
    q = max(0.0, min(100.0, float(quality)))
    return min(5.0, 0.1 * 100.0 / max(q, 2.0))


def _finite(name: str, v: object) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{name} is not a number: {v!r:.40}")
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"{name} is not finite: {f}")
    return f


def _coord(name: str, v: object) -> float:
    f = _finite(name, v)
    if abs(f) > MAX_COORD_M:
        raise ValueError(f"{name} = {f:.1f} m is out of range (|{name}| <= {MAX_COORD_M:g} m)")
    return f


def fix_from_uwb(msg: UwbFixLike, wall_minus_monotonic: float) -> FixObservation:
    """The native ``UwbFix`` message (already decoded and validated by the wire codec)."""
    status = str(msg.status)
    if status != "ok":
        raise ValueError(f"fix status is {status!r}, not 'ok'")
    x, y = _coord("x", msg.x), _coord("y", msg.y)
    sd_x, sd_y = _finite("sd_x", msg.sd_x), _finite("sd_y", msg.sd_y)
    if sd_x < 0 or sd_y < 0:
        raise ValueError(f"negative standard deviation ({sd_x}, {sd_y})")
    q = _finite("quality", msg.quality)
    if not 0 <= q <= 100:
        raise ValueError(f"quality {q} is outside 0-100")
    if sd_x == 0 and sd_y == 0:
        # No covariance from the solver: fall back on the quality.
        sd_x = sd_y = quality_to_sd(q)
    t = _finite("measured_at", msg.measured_at) - _finite("wall_minus_monotonic", wall_minus_monotonic)
    return FixObservation(t, x, y, sd_x, sd_y, int(q), "native", str(msg.tag))


def pans_node_id(topic: str) -> str:
    """The node id of a PANS location topic ``{prefix}/node/{id}/uplink/location``."""
    m = _PANS_TOPIC.match(topic)
    if m is None:
        raise ValueError(f"not a PANS location topic: {topic[:120]!r}")
    return m.group(1)


def fix_from_pans(
    topic: str,
    payload: bytes | str,
    wall_minus_monotonic: float,
    received_at: float | None = None,
) -> FixObservation:
    """A DWM1001 PANS location message (``dwm/node/<id>/uplink/location``).

    ``{"position":{"x":3.25,"y":-0.009,"z":0.425,"quality":21},"superFrameNumber":1144,
    "timestamp":"1679495047880989"}``: metres, quality 0-100 %, timestamp a string of microseconds
    since the Unix epoch (wall time). The newer LEAPS API adds ``sd_x``/``sd_y`` to ``position``; when
    present they are used, otherwise the quality gives the sd (``quality_to_sd``). Without a
    timestamp the fix is placed at ``received_at`` (monotonic) if given.
    """
    node = pans_node_id(topic)
    if len(payload) > MAX_PANS_BYTES:
        raise ValueError(f"payload of {len(payload)} bytes is over {MAX_PANS_BYTES}")
    try:
        doc: Any = json.loads(payload)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"not JSON: {exc}") from None
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None
    if not isinstance(doc, dict):
        raise ValueError(f"payload is a JSON {type(doc).__name__}, not an object")
    pos = doc.get("position")
    if not isinstance(pos, dict):
        raise ValueError("no 'position' object")
    missing = [k for k in ("x", "y", "quality") if k not in pos]
    if missing:
        raise ValueError(f"position lacks {', '.join(missing)}")
    x, y = _coord("position.x", pos["x"]), _coord("position.y", pos["y"])
    q = _finite("position.quality", pos["quality"])
    if not 0 <= q <= 100:
        raise ValueError(f"position.quality {q} is outside 0-100")
    if "sd_x" in pos or "sd_y" in pos:
        sd_x, sd_y = _finite("position.sd_x", pos.get("sd_x")), _finite("position.sd_y", pos.get("sd_y"))
        if sd_x < 0 or sd_y < 0:
            raise ValueError(f"negative standard deviation ({sd_x}, {sd_y})")
    else:
        sd_x = sd_y = quality_to_sd(q)
    stamp = doc.get("timestamp")
    if stamp is None:
        if received_at is None:
            raise ValueError("no 'timestamp' and no receive time")
        t = _finite("received_at", received_at)
    else:
        if isinstance(stamp, str):
            if not stamp.isdigit() or len(stamp) > 20:
                raise ValueError(f"timestamp is not a string of microseconds: {stamp[:40]!r}")
            micros = int(stamp)
        elif isinstance(stamp, int) and not isinstance(stamp, bool) and stamp >= 0:
            micros = stamp
        else:
            raise ValueError(f"timestamp is not microseconds: {stamp!r:.40}")
        t = micros / 1e6 - _finite("wall_minus_monotonic", wall_minus_monotonic)
    return FixObservation(t, x, y, sd_x, sd_y, int(q), "pans", node)
