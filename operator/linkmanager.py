"""Primary/fallback link manager for the operator side: plain Python, no I/O, time passed in.

Every command to a robot goes over the robot's *active* link, the primary (Zenoh) while it is
healthy. The primary turns unhealthy when the robot has not been heard on it for
``state_window_s`` (three missed 10 Hz states) or when a command sent on it has gone unacked for
``ack_timeout_s``. Then, at the next ``poll``, the robot's commands move to the fallback (MQTT)
and every command still waiting for its ack is re-sent there, byte for byte: the agent dedupes on
(sender, topic, headerId) and orders on (orderId, orderUpdateId), so the copy is harmless. Once
the primary has been healthy again for ``holdoff_s`` the robot moves back.

The adapter (operator/links.py) feeds in what it hears (``heard``, ``acked``), asks where a new
command goes (``command``), and calls ``poll`` a few dozen times a second; the returned ``Send``
and ``Switch`` values are its instructions. Health per robot and link (age of the last message,
loss % from headerId gaps, round-trip time from acks) is exposed through ``health``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

__all__ = [
    "FALLBACK",
    "LINKS",
    "PRIMARY",
    "Failed",
    "LinkHealth",
    "LinkManager",
    "LinkPolicy",
    "Send",
    "Switch",
]

PRIMARY = "zenoh"
FALLBACK = "mqtt"
LINKS = (PRIMARY, FALLBACK)


@dataclass(frozen=True, slots=True)
class LinkPolicy:
    state_window_s: float = 0.35
    """Silence on a link longer than this makes it unhealthy (three missed 10 Hz states + jitter)."""
    ack_timeout_s: float = 0.25
    """A command unacked this long makes the link it went out on unhealthy."""
    holdoff_s: float = 2.0
    """The primary must stay healthy this long before commands move back to it."""
    max_attempts: int = 4
    """Sends per command (first send + re-sends) before it is reported as ``Failed``."""
    loss_window: int = 100
    """How many recent commands the loss percentage looks at."""
    max_pending: int = 256
    """Unacked commands kept per robot; the oldest are dropped (and reported) beyond this."""

    def __post_init__(self) -> None:
        for name in ("state_window_s", "ack_timeout_s", "holdoff_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if self.max_attempts < 1 or self.loss_window < 1 or self.max_pending < 1:
            raise ValueError("max_attempts, loss_window and max_pending must be >= 1")


@dataclass(frozen=True, slots=True)
class Send:
    """Put ``payload`` on ``link`` under ``fleetlink/v1/<robot>/<topic>``."""

    robot: str
    link: str
    topic: str
    header_id: int
    payload: bytes
    resend: bool = False


@dataclass(frozen=True, slots=True)
class LinkHealth:
    link: str
    healthy: bool
    age_s: float | None
    """Seconds since the last message from the robot on this link (None: never heard)."""
    loss_pct: float
    """Share of recent commands on this link that went unacked within the ack timeout."""
    rtt_s: float | None
    """Smoothed command-to-ack round trip on this link (None: no ack yet)."""
    reason: str
    """Why it is unhealthy ('' when healthy)."""

    def describe(self) -> str:
        age = "never" if self.age_s is None else f"{self.age_s * 1000:.0f} ms"
        rtt = "-" if self.rtt_s is None else f"{self.rtt_s * 1000:.1f} ms"
        state = "ok" if self.healthy else f"DOWN ({self.reason})"
        return f"{self.link} {state} age {age} loss {self.loss_pct:.0f}% rtt {rtt}"


@dataclass(frozen=True, slots=True)
class Switch:
    """The robot's commands now go over ``to_link``."""

    robot: str
    from_link: str
    to_link: str
    reason: str
    at: float
    health: tuple[LinkHealth, ...]

    def describe(self) -> str:
        links = "; ".join(h.describe() for h in self.health)
        return f"{self.robot}: commands {self.from_link} -> {self.to_link} ({self.reason}) [{links}]"


@dataclass(frozen=True, slots=True)
class Failed:
    """A command was never acked after ``max_attempts`` sends (or was pushed out of the queue)."""

    robot: str
    topic: str
    header_id: int
    reason: str


@dataclass(slots=True)
class _Pending:
    topic: str
    header_id: int
    payload: bytes
    link: str
    sent_at: float
    first_sent: float
    attempts: int = 1


@dataclass(slots=True)
class _LinkState:
    last_heard: float | None = None
    rtt_s: float | None = None
    window: deque[bool] = field(default_factory=deque)
    ack_timeout_at: float | None = None
    """When an ack timeout last made this link unhealthy (cleared by the next message heard)."""


@dataclass(slots=True)
class _Robot:
    first_seen: float
    active: str = PRIMARY
    links: dict[str, _LinkState] = field(default_factory=lambda: {name: _LinkState() for name in LINKS})
    pending: dict[tuple[str, int], _Pending] = field(default_factory=dict)
    primary_healthy_since: float | None = None
    switches: int = 0


_RTT_ALPHA = 0.25


class LinkManager:
    """Link choice, health and re-sends for many robots. Not thread-safe: the adapter locks."""

    def __init__(self, policy: LinkPolicy | None = None) -> None:
        self.policy = policy or LinkPolicy()
        self._robots: dict[str, _Robot] = {}

    # -- inputs ---------------------------------------------------------------------------------

    def _robot(self, robot: str, now: float) -> _Robot:
        state = self._robots.get(robot)
        if state is None:
            state = self._robots[robot] = _Robot(first_seen=now)
        return state

    def heard(self, robot: str, link: str, now: float) -> None:
        """Any message from ``robot`` arrived on ``link``."""
        ls = self._robot(robot, now).links[_check_link(link)]
        ls.last_heard = now
        ls.ack_timeout_at = None

    def _outcome(self, ls: _LinkState, acked: bool) -> None:
        ls.window.append(acked)
        while len(ls.window) > self.policy.loss_window:
            ls.window.popleft()

    def acked(self, robot: str, link: str, topic: str, header_id: int, now: float) -> bool:
        """The robot acked command (topic, headerId) on ``link``. True if it was still pending."""
        state = self._robot(robot, now)
        ls = state.links[_check_link(link)]
        ls.last_heard = now
        ls.ack_timeout_at = None
        pending = state.pending.pop((topic, header_id), None)
        if pending is None:
            return False
        if pending.link == link:
            self._outcome(ls, now - pending.sent_at < self.policy.ack_timeout_s)
            rtt = max(0.0, now - pending.sent_at)
            ls.rtt_s = rtt if ls.rtt_s is None else ls.rtt_s + _RTT_ALPHA * (rtt - ls.rtt_s)
        return True

    def command(
        self, robot: str, topic: str, header_id: int, payload: bytes, now: float, *, expect_ack: bool = True
    ) -> tuple[list[Send], list[Failed]]:
        """Where a new command goes: one ``Send`` on the robot's active link.

        With ``expect_ack`` the command is kept until acked and re-sent on a switch; without it
        (drive commands at 10 Hz, superseded by the next one anyway) it is sent once.
        """
        state = self._robot(robot, now)
        send = Send(robot, state.active, topic, header_id, payload)
        failed: list[Failed] = []
        if expect_ack:
            state.pending[(topic, header_id)] = _Pending(topic, header_id, payload, state.active, now, now)
            while len(state.pending) > self.policy.max_pending:
                oldest = next(iter(state.pending))
                dropped = state.pending.pop(oldest)
                failed.append(Failed(robot, dropped.topic, dropped.header_id, "too many unacked commands"))
        return [send], failed

    def forget(self, robot: str) -> None:
        self._robots.pop(robot, None)

    # -- time -----------------------------------------------------------------------------------

    def poll(self, now: float) -> list[Send | Switch | Failed]:
        """Switch links where health demands it, re-send unacked commands, give up on dead ones."""
        out: list[Send | Switch | Failed] = []
        for robot, state in self._robots.items():
            self._expire_acks(state, now)
            primary_ok, reason = self._link_ok(state, PRIMARY, now)
            if primary_ok:
                if state.primary_healthy_since is None:
                    state.primary_healthy_since = now
            else:
                state.primary_healthy_since = None
            if state.active == PRIMARY and not primary_ok:
                out.append(self._switch(robot, state, FALLBACK, f"primary {reason}", now))
                out.extend(self._resend_all(robot, state, now))
            elif (
                state.active == FALLBACK
                and state.primary_healthy_since is not None
                and now - state.primary_healthy_since >= self.policy.holdoff_s
            ):
                out.append(self._switch(robot, state, PRIMARY, f"primary healthy for {self.policy.holdoff_s:g} s", now))
                out.extend(self._resend_all(robot, state, now))
            out.extend(self._retry(robot, state, now))
        return out

    def _expire_acks(self, state: _Robot, now: float) -> None:
        for p in state.pending.values():
            if now - p.sent_at >= self.policy.ack_timeout_s:
                ls = state.links[p.link]
                # Only silence *since* the send counts: an ack timeout older than the last message
                # heard on the link has already been answered by that message.
                if ls.last_heard is None or ls.last_heard <= p.sent_at + self.policy.ack_timeout_s:
                    ls.ack_timeout_at = now if ls.ack_timeout_at is None else ls.ack_timeout_at

    def _link_ok(self, state: _Robot, link: str, now: float) -> tuple[bool, str]:
        ls = state.links[link]
        reference = ls.last_heard if ls.last_heard is not None else state.first_seen
        if now - reference > self.policy.state_window_s:
            what = "never heard" if ls.last_heard is None else "silent"
            return False, f"{what} for {(now - reference) * 1000:.0f} ms"
        if ls.ack_timeout_at is not None and link == state.active:
            return False, f"ack timeout ({self.policy.ack_timeout_s * 1000:.0f} ms)"
        return True, ""

    def _switch(self, robot: str, state: _Robot, to: str, reason: str, now: float) -> Switch:
        frm, state.active = state.active, to
        state.switches += 1
        state.links[to].ack_timeout_at = None
        return Switch(robot, frm, to, reason, now, self._health(state, now))

    def _resend_all(self, robot: str, state: _Robot, now: float) -> list[Send]:
        sends = []
        for p in state.pending.values():
            if now - p.sent_at >= self.policy.ack_timeout_s:
                self._outcome(state.links[p.link], False)
            p.link, p.sent_at, p.attempts = state.active, now, p.attempts + 1
            sends.append(Send(robot, state.active, p.topic, p.header_id, p.payload, resend=True))
        return sends

    def _retry(self, robot: str, state: _Robot, now: float) -> list[Send | Failed]:
        out: list[Send | Failed] = []
        for slot, p in list(state.pending.items()):
            if now - p.sent_at < self.policy.ack_timeout_s:
                continue
            self._outcome(state.links[p.link], False)
            if p.attempts >= self.policy.max_attempts:
                del state.pending[slot]
                out.append(Failed(robot, p.topic, p.header_id, f"no ack after {p.attempts} sends"))
                continue
            p.link, p.sent_at, p.attempts = state.active, now, p.attempts + 1
            out.append(Send(robot, state.active, p.topic, p.header_id, p.payload, resend=True))
        return out

    # -- outputs --------------------------------------------------------------------------------

    def robots(self) -> list[str]:
        return list(self._robots)

    def active(self, robot: str) -> str:
        state = self._robots.get(robot)
        return PRIMARY if state is None else state.active

    def pending(self, robot: str) -> int:
        state = self._robots.get(robot)
        return 0 if state is None else len(state.pending)

    def switches(self, robot: str) -> int:
        state = self._robots.get(robot)
        return 0 if state is None else state.switches

    def health(self, robot: str, now: float) -> tuple[LinkHealth, ...]:
        state = self._robots.get(robot)
        if state is None:
            return tuple(LinkHealth(name, False, None, 0.0, None, "never heard") for name in LINKS)
        return self._health(state, now)

    def _health(self, state: _Robot, now: float) -> tuple[LinkHealth, ...]:
        out = []
        for name in LINKS:
            ls = state.links[name]
            ok, reason = self._link_ok(state, name, now)
            age = None if ls.last_heard is None else max(0.0, now - ls.last_heard)
            loss = 100.0 * ls.window.count(False) / len(ls.window) if ls.window else 0.0
            out.append(LinkHealth(name, ok, age, loss, ls.rtt_s, reason))
        return tuple(out)


def _check_link(link: str) -> str:
    if link not in LINKS:
        raise ValueError(f"unknown link {link!r} (expected one of {', '.join(LINKS)})")
    return link
