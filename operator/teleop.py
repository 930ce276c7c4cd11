"""Direct-drive keys, teleop_twist_keyboard style. Pure: keys and time in, twists out.

Terminals send no key-up events, so a held key is a stream of repeats: the first press drives at
once, repeats keep the drive alive and ``tick`` re-sends it at ``rate_hz``; when no repeat has come
for ``repeat_timeout_s`` (a little above the terminal's initial repeat delay) ``tick`` says stop,
once. The robot's own deadman (Teleop.ttl_s) backs this up if the console dies.

Layout (teleop_twist_keyboard)::

    u i o        forward-left  forward  forward-right        arrows and w a s d drive too
    j k l        turn left     stop     turn right           space or k: stop
    m , .        back-right    back     back-left            Esc: stop every robot

Speed steps: q/z all speeds +-10 %, W/x linear only (``w`` drives forward in WASD, so the linear
step up is shift-W), e/c angular only.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["DRIVE_KEYS", "STOP_KEYS", "DriveKeys", "Twist"]

DRIVE_KEYS: dict[str, tuple[int, int]] = {
    "u": (1, 1),
    "i": (1, 0),
    "o": (1, -1),
    "j": (0, 1),
    "l": (0, -1),
    "m": (-1, -1),
    "comma": (-1, 0),
    ",": (-1, 0),
    "full_stop": (-1, 1),
    ".": (-1, 1),
    "up": (1, 0),
    "down": (-1, 0),
    "left": (0, 1),
    "right": (0, -1),
    "w": (1, 0),
    "s": (-1, 0),
    "a": (0, 1),
    "d": (0, -1),
}
STOP_KEYS = frozenset({"k", "space"})
SPEED_KEYS: dict[str, tuple[float, float]] = {
    "q": (1.1, 1.1),
    "z": (0.9, 0.9),
    "W": (1.1, 1.0),
    "x": (0.9, 1.0),
    "e": (1.0, 1.1),
    "c": (1.0, 0.9),
}


@dataclass(frozen=True, slots=True)
class Twist:
    v: float
    omega: float

    @property
    def is_stop(self) -> bool:
        return self.v == 0.0 and self.omega == 0.0


STOP = Twist(0.0, 0.0)


class DriveKeys:
    def __init__(
        self,
        speed: float = 0.3,
        turn: float = 1.0,
        *,
        rate_hz: float = 10.0,
        repeat_timeout_s: float = 0.6,
        max_speed: float = 1.0,
        max_turn: float = 3.0,
    ) -> None:
        self.speed = speed
        self.turn = turn
        self.period = 1.0 / rate_hz
        self.repeat_timeout_s = repeat_timeout_s
        self.max_speed = max_speed
        self.max_turn = max_turn
        self.current: Twist | None = None
        self._last_key = 0.0
        self._last_sent = -1e9

    def handles(self, key: str) -> bool:
        return key in DRIVE_KEYS or key in STOP_KEYS or key in SPEED_KEYS

    def press(self, key: str, now: float) -> Twist | None:
        """A key (or a repeat of it). Returns a twist to send now, or None (rate limit / not ours)."""
        if key in SPEED_KEYS:
            fs, ft = SPEED_KEYS[key]
            self.speed = min(self.max_speed, self.speed * fs)
            self.turn = min(self.max_turn, self.turn * ft)
            return None
        if key in STOP_KEYS:
            return self.stop(now)
        if key not in DRIVE_KEYS:
            return None
        lin, ang = DRIVE_KEYS[key]
        twist = Twist(lin * self.speed, ang * self.turn)
        self._last_key = now
        changed = twist != self.current
        self.current = twist
        if changed or now - self._last_sent >= self.period:
            self._last_sent = now
            return twist
        return None

    def stop(self, now: float) -> Twist:
        self.current = None
        self._last_sent = now
        return STOP

    def tick(self, now: float) -> Twist | None:
        """Called often (>= rate_hz): the drive to re-send, STOP once when repeats stopped, or None."""
        if self.current is None:
            return None
        if now - self._last_key > self.repeat_timeout_s:
            return self.stop(now)
        if now - self._last_sent >= self.period:
            self._last_sent = now
            return self.current
        return None
