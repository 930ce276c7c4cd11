"""Primary/fallback link manager for the operator side: plain Python, no I/O, time passed in.

Two ways to send. **Redundant** (``LinkPolicy.redundant``, the consoles' default): every command
goes out on both links at once, same bytes, same header (IEC 62439-3 PRP's idea); the agent runs
the first copy to arrive and acks each copy on the link it came by (agent/links/gate.py), so the
loss of either link costs no time at all. Unacked commands are re-sent on both links. **Failover**
(sites with a metered link, and the fall-back): every command goes over the robot's *active* link, the primary (Zenoh) while it is
healthy. The primary turns unhealthy when the robot has not been heard on it for
``state_window_s`` (three missed 10 Hz states) or when a command sent on it has gone unacked for
``ack_timeout_s``. Then, at the next ``poll``, the robot's commands move to the fallback (MQTT)
-- if the fallback itself has been heard within ``state_window_s``: a move to a link as silent as
the one left gains nothing -- and every command still waiting for its ack is re-sent there, byte
for byte: the agent dedupes on (sender, topic, headerId) and orders on (orderId, orderUpdateId),
so the copy is harmless. Once
the primary has been healthy again for ``holdoff_s`` the robot moves back (at once if the
fallback has gone silent meanwhile).

The adapter (operator/links.py) feeds in what it hears (``heard``, ``acked``), asks where a new
command goes (``command``), and calls ``poll`` a few dozen times a second; the returned ``Send``
and ``Switch`` values are its instructions (no ``Switch`` in redundant mode: nothing moves).

Health per robot and link (``health``), from each command's copies and their acks (teleops'
too: followed, never re-sent): round-trip
time p50/p95 over the last ``rtt_window`` acks, loss (copies unacked within ``ack_timeout_s`` over
the last ``loss_window``), age of the last message heard, and -- when both copies of a command were
acked -- which link's ack came first and by how much. A link heard before is *degraded*
(``LinkHealth.degraded`` says why) when its loss, its RTT p95 or its silence passes the policy's
thresholds; the console raises an alarm for it (operator/alarms.py, ``link_degraded``).
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

__all__ = [
    "BOTH",
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
BOTH = "both"
"""What ``route`` says in redundant mode: every command goes on both links."""


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
    redundant: bool = False
    """Every command on both links at once (the consoles' default: ``[links] redundant``); False:
    on the active link only, failing over (the lockstep sortie and replays use this default)."""
    rtt_window: int = 200
    """How many recent acks per link the RTT percentiles look at."""
    track_s: float = 2.0
    """How long a command's copies are followed: an ack later than ``ack_timeout_s`` (a copy
    counted lost) still gives its RTT until then."""
    degraded_rtt_s: float = 0.1
    """A link whose RTT p95 is over this is degraded."""
    degraded_loss_pct: float = 5.0
    """A link losing more than this share of its copies is degraded."""
    degraded_silence_s: float = 1.0
    """A link heard before and silent this long is degraded."""
    min_samples: int = 5
    """Acks (for RTT) or judged copies (for loss) needed before a link can be called degraded."""

    def __post_init__(self) -> None:
        for name in ("state_window_s", "ack_timeout_s", "holdoff_s", "track_s", "degraded_rtt_s", "degraded_silence_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if self.max_attempts < 1 or self.loss_window < 1 or self.max_pending < 1 or self.rtt_window < 1:
            raise ValueError("max_attempts, loss_window, max_pending and rtt_window must be >= 1")
        if not 0.0 <= self.degraded_loss_pct <= 100.0 or self.min_samples < 1:
            raise ValueError("degraded_loss_pct must be in [0, 100] and min_samples >= 1")


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
    """Command-to-ack round trip on this link, median of the window (None: no ack yet)."""
    reason: str
    """Why it is unhealthy ('' when healthy)."""
    rtt_p95_s: float | None = None
    """95th percentile of the same window."""
    first_pct: float | None = None
    """Of the commands acked on both links, the share whose ack came first on this one (None: none yet)."""
    lead_s: float | None = None
    """When this link's ack came first: by how much, the median (None: it never came first)."""
    degraded: str = ""
    """Why this link is degraded (loss, RTT or silence over the policy's thresholds); '' when not."""

    def describe(self) -> str:
        age = "never" if self.age_s is None else f"{self.age_s * 1000:.0f} ms"
        rtt = "-" if self.rtt_s is None else f"{self.rtt_s * 1000:.1f} ms"
        if self.rtt_s is not None and self.rtt_p95_s is not None and self.rtt_p95_s != self.rtt_s:
            rtt = f"{self.rtt_s * 1000:.1f}/{self.rtt_p95_s * 1000:.1f} ms"  # p50/p95
        state = "ok" if self.healthy else f"DOWN ({self.reason})"
        if self.healthy and self.degraded:
            state = f"DEGRADED ({self.degraded})"
        first = ""
        if self.first_pct is not None:
            lead = "" if self.lead_s is None else f" by {self.lead_s * 1000:.1f} ms"
            first = f" first {self.first_pct:.0f}%{lead}"
        return f"{self.link} {state} age {age} loss {self.loss_pct:.0f}% rtt {rtt}{first}"


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
class _Copies:
    """One command's copies: when each went out on its link, when each ack came back."""

    first_sent: float
    sent: dict[str, float] = field(default_factory=dict)
    acked: dict[str, float] = field(default_factory=dict)
    judged: set[str] = field(default_factory=set)
    """Links whose copy is counted (acked in time, or lost)."""
    together: bool = True
    """Both copies went out at once (their acks can be compared: which link delivered first)."""


@dataclass(slots=True)
class _LinkState:
    last_heard: float | None = None
    rtts: deque[float] = field(default_factory=deque)
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
    copies: dict[tuple[str, int], _Copies] = field(default_factory=dict)
    """Commands whose copies are followed (acked, lost, late), oldest first."""
    first: Counter[str] = field(default_factory=Counter)
    """Commands acked on both links, by the link whose ack came first."""
    leads: dict[str, deque[float]] = field(default_factory=lambda: {name: deque() for name in LINKS})
    """By how much each link's ack came first (seconds), the last ``rtt_window``."""


MAX_FOLLOWED = 1024
"""Commands whose copies are followed per robot; the oldest are forgotten first beyond this."""


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
        self._ack_copy(state, link, (topic, header_id), now)
        return state.pending.pop((topic, header_id), None) is not None

    def _ack_copy(self, state: _Robot, link: str, slot: tuple[str, int], now: float) -> None:
        copies = state.copies.get(slot)
        if copies is None or link not in copies.sent or link in copies.acked:
            return
        ls = state.links[link]
        copies.acked[link] = now
        rtt = max(0.0, now - copies.sent[link])
        ls.rtts.append(rtt)
        while len(ls.rtts) > self.policy.rtt_window:
            ls.rtts.popleft()
        if link not in copies.judged:
            copies.judged.add(link)
            self._outcome(ls, rtt < self.policy.ack_timeout_s)
        if len(copies.acked) == len(LINKS) and copies.together:
            (win, t_win), (_, t_other) = sorted(copies.acked.items(), key=lambda kv: kv[1])
            state.first[win] += 1
            leads = state.leads[win]
            leads.append(t_other - t_win)
            while len(leads) > self.policy.rtt_window:
                leads.popleft()
        if len(copies.acked) == len(copies.sent):
            del state.copies[slot]

    def _sent(self, state: _Robot, slot: tuple[str, int], links: tuple[str, ...], now: float) -> None:
        """Copies of ``slot`` went out on ``links`` now (a first send, or a re-send)."""
        copies = state.copies.pop(slot, None)
        if copies is None:
            copies = _Copies(first_sent=now)
        else:
            copies.together = False  # a re-send: its acks race nothing sent at the same time
        for link in links:
            copies.sent[link] = now
            copies.acked.pop(link, None)
            copies.judged.discard(link)
        state.copies[slot] = copies  # (re)inserted last: the dict stays oldest first
        while len(state.copies) > MAX_FOLLOWED:
            del state.copies[next(iter(state.copies))]

    def _judge(self, state: _Robot, now: float) -> None:
        """Count copies unacked for ``ack_timeout_s`` as lost; forget commands older than ``track_s``."""
        timeout = self.policy.ack_timeout_s
        done = []
        for slot, copies in state.copies.items():
            for link, at in copies.sent.items():
                if link in copies.judged or now - at < timeout:
                    continue
                copies.judged.add(link)
                ls = state.links[link]
                self._outcome(ls, False)
                if ls.last_heard is None or ls.last_heard <= at + timeout:
                    ls.ack_timeout_at = now if ls.ack_timeout_at is None else ls.ack_timeout_at
            if now - max(copies.sent.values()) >= self.policy.track_s:
                done.append(slot)
        for slot in done:
            del state.copies[slot]

    def command(
        self, robot: str, topic: str, header_id: int, payload: bytes, now: float, *, expect_ack: bool = True
    ) -> tuple[list[Send], list[Failed]]:
        """Where a new command goes: a ``Send`` on each link (redundant), or one on the robot's
        active link (failover).

        With ``expect_ack`` the command is kept until acked and re-sent (on a switch, or after the
        ack timeout). Without it (drive commands at the key's repeat rate, superseded by the next
        one anyway) it is sent once, never re-sent. Either way its copies are followed: the agent
        acks a teleop like any command, so a held key's stream feeds the link health (RTT, loss,
        which link delivered first) as goals do -- the commands a driver notices a slow link by.
        """
        state = self._robot(robot, now)
        links = LINKS if self.policy.redundant else (state.active,)
        sends = [Send(robot, link, topic, header_id, payload) for link in links]
        failed: list[Failed] = []
        self._sent(state, (topic, header_id), links, now)
        if expect_ack:
            state.pending[(topic, header_id)] = _Pending(topic, header_id, payload, state.active, now, now)
            while len(state.pending) > self.policy.max_pending:
                oldest = next(iter(state.pending))
                dropped = state.pending.pop(oldest)
                failed.append(Failed(robot, dropped.topic, dropped.header_id, "too many unacked commands"))
        return sends, failed

    def forget(self, robot: str) -> None:
        self._robots.pop(robot, None)

    # -- time -----------------------------------------------------------------------------------

    def poll(self, now: float) -> list[Send | Switch | Failed]:
        """Switch links where health demands it, re-send unacked commands, give up on dead ones."""
        out: list[Send | Switch | Failed] = []
        for robot, state in self._robots.items():
            self._judge(state, now)
            if self.policy.redundant:  # nothing to move: every command already goes on both
                out.extend(self._retry(robot, state, now))
                continue
            self._expire_acks(state, now)
            primary_ok, reason = self._link_ok(state, PRIMARY, now)
            if primary_ok:
                if state.primary_healthy_since is None:
                    state.primary_healthy_since = now
            else:
                state.primary_healthy_since = None
            # A move needs somewhere better to go: with the fallback silent too (or never heard)
            # commands stay where they are, so re-sends keep going on the link that comes back first.
            fallback_ok, fallback_reason = self._link_ok(state, FALLBACK, now)
            if state.active == PRIMARY and not primary_ok and fallback_ok:
                out.append(self._switch(robot, state, FALLBACK, f"primary {reason}", now))
                out.extend(self._resend_all(robot, state, now))
            elif state.active == FALLBACK and primary_ok and not fallback_ok:
                out.append(self._switch(robot, state, PRIMARY, f"fallback {fallback_reason}", now))
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
        if ls.ack_timeout_at is not None and (link == state.active or self.policy.redundant):
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
            p.link, p.sent_at, p.attempts = state.active, now, p.attempts + 1
            self._sent(state, (p.topic, p.header_id), (state.active,), now)
            sends.append(Send(robot, state.active, p.topic, p.header_id, p.payload, resend=True))
        return sends

    def _retry(self, robot: str, state: _Robot, now: float) -> list[Send | Failed]:
        out: list[Send | Failed] = []
        for slot, p in list(state.pending.items()):
            if now - p.sent_at < self.policy.ack_timeout_s:
                continue
            if p.attempts >= self.policy.max_attempts:
                del state.pending[slot]
                out.append(Failed(robot, p.topic, p.header_id, f"no ack after {p.attempts} sends"))
                continue
            links = LINKS if self.policy.redundant else (state.active,)
            p.link, p.sent_at, p.attempts = state.active, now, p.attempts + 1
            self._sent(state, slot, links, now)
            out.extend(Send(robot, link, p.topic, p.header_id, p.payload, resend=True) for link in links)
        return out

    # -- outputs --------------------------------------------------------------------------------

    def robots(self) -> list[str]:
        return list(self._robots)

    def active(self, robot: str) -> str:
        """The link failover would use (in redundant mode it never moves from the primary)."""
        state = self._robots.get(robot)
        return PRIMARY if state is None else state.active

    def route(self, robot: str) -> str:
        """Where commands go: ``both`` (redundant), else the active link."""
        return BOTH if self.policy.redundant else self.active(robot)

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

    def link_states(self, robot: str, now: float) -> tuple[tuple[str, float | None, str], ...]:
        """Each link's (name, ``age_s``, ``degraded``) as ``health`` says them, and nothing else
        (no RTT median, first-arrival shares or health reasons): what the link alarms look at for
        every robot twice a second (operator/alarm_panel.py), at a third of ``health``'s cost."""
        state = self._robots.get(robot)
        if state is None:
            return tuple((name, None, "") for name in LINKS)
        out: list[tuple[str, float | None, str]] = []
        samples = self.policy.min_samples
        for name in LINKS:
            ls = state.links[name]
            if ls.last_heard is None:
                out.append((name, None, ""))
                continue
            age = max(0.0, now - ls.last_heard)
            # Loss and RTT count only from min_samples on (``_degraded``): worked out only then.
            window = ls.window
            loss = 100.0 * window.count(False) / len(window) if len(window) >= samples else 0.0
            p95 = _pct(sorted(ls.rtts), 0.95) if len(ls.rtts) >= samples else None
            out.append((name, age, self._degraded(ls, age, loss, p95, len(ls.rtts))))
        return tuple(out)

    def _health(self, state: _Robot, now: float) -> tuple[LinkHealth, ...]:
        out = []
        both = sum(state.first.values())
        for name in LINKS:
            ls = state.links[name]
            ok, reason = self._link_ok(state, name, now)
            age = None if ls.last_heard is None else max(0.0, now - ls.last_heard)
            loss = 100.0 * ls.window.count(False) / len(ls.window) if ls.window else 0.0
            rtts = sorted(ls.rtts)
            p50 = _pct(rtts, 0.5)
            p95 = _pct(rtts, 0.95)
            first = 100.0 * state.first[name] / both if both else None
            lead = _pct(sorted(state.leads[name]), 0.5)
            degraded = self._degraded(ls, age, loss, p95, len(rtts))
            out.append(LinkHealth(name, ok, age, loss, p50, reason, p95, first, lead, degraded))
        return tuple(out)

    def _degraded(self, ls: _LinkState, age: float | None, loss: float, p95: float | None, samples: int) -> str:
        """Why a link heard before is degraded ('' if it is not)."""
        p = self.policy
        if age is None:
            return ""  # never heard here (a one-link site): nothing to compare with
        if age > p.degraded_silence_s:
            return f"silent {age:.1f} s"
        if len(ls.window) >= p.min_samples and loss > p.degraded_loss_pct:
            return f"loss {loss:.0f}% > {p.degraded_loss_pct:g}%"
        if p95 is not None and samples >= p.min_samples and p95 > p.degraded_rtt_s:
            return f"rtt p95 {p95 * 1000:.0f} ms > {p.degraded_rtt_s * 1000:.0f} ms"
        return ""


def _pct(ordered: list[float], q: float) -> float | None:
    """The ``q`` quantile of an ascending list (nearest rank); None if empty."""
    if not ordered:
        return None
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def _check_link(link: str) -> str:
    if link not in LINKS:
        raise ValueError(f"unknown link {link!r} (expected one of {', '.join(LINKS)})")
    return link
