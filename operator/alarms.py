"""Alarms: what an operator must see, acknowledge and be reminded of. Pure: no I/O, time passed in.

``AlarmList`` keeps one alarm per (robot, kind) (``raise_alarm``, ``seen``, ``clear``,
``acknowledge``, ``due_renotifications``); every change yields an ``AuditRecord``
(``drain_audit``). ``derive`` turns what a robot says (``State``, ``BoardStatus``, ``Event``) into
``Observation``\\ s, and ``AlarmDesk`` -- one per console -- folds observations, presence (the
Zenoh liveliness token, the MQTT ``Connection``), the console's own view of the links and the
acknowledgements other consoles publish (``AlarmAck``) into its ``AlarmList``.

Times are seconds since the Unix epoch: the console's wall clock for first/last seen, renotifying
and acknowledging; an episode's ``since`` is the ``header.timestamp`` of the robot's message that
first showed it (the same on every console that heard it) or, for what only a console can see
(robot lost, its own view of the links), that console's clock.

Episodes. An alarm that clears and comes back is a new episode, and so is a worse one (a low
battery going critical): an acknowledgement covers one episode. An ``AlarmAck`` names the episode
by its ``since``; a console applies it to its current episode of that alarm when ``since`` is later
than the last time the console knew the alarm was off (``floor``: a clear it saw, the last
observation before a worse episode, the last event of a latching alarm's previous episode, or when
it first heard the robot). So an acknowledgement of an earlier episode never covers a later one,
and two consoles that saw the same episode start at slightly different messages still agree. A
console that started while an alarm was already on has no floor for it and takes any retained
acknowledgement of that kind as covering it (docs/console.md, "Alarms").

Latching alarms (cliff, bump) come from events and stay until acknowledged; the others clear when
their condition goes away (battery recovered, e-stop released, the token back). Thresholds are
the constants below, each with a hysteresis so a value hovering at a threshold does not flap.
"""

from __future__ import annotations

import enum
import math
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from fleetlink.shared import keys
from fleetlink.shared.messages import (
    UNKNOWN_SD_M,
    AckedAlarm,
    AlarmAck,
    BoardStatus,
    Connection,
    ConnectionState,
    EStop,
    Event,
    Pose,
    State,
)
from fleetlink.shared.wire import Message

__all__ = [
    "KINDS",
    "LINK_QUIET_S",
    "LOCALISATION_SCORE_CLEAR",
    "LOCALISATION_SCORE_MIN",
    "LOW_BATTERY_CRITICAL_PERCENT",
    "LOW_BATTERY_WARNING_PERCENT",
    "MAX_ACK_SOURCES",
    "MAX_PENDING_ROBOTS",
    "PERCENT_HYSTERESIS",
    "RENOTIFY_S",
    "TANK_LOW_PERCENT",
    "AckEntry",
    "AckOutcome",
    "Alarm",
    "AlarmDesk",
    "AlarmKind",
    "AlarmList",
    "AlarmSeverity",
    "AuditEvent",
    "AuditRecord",
    "KindSpec",
    "Observation",
    "derive",
    "links_quiet",
    "parse_kind",
]

# -- thresholds -------------------------------------------------------------------------------------

LOW_BATTERY_WARNING_PERCENT = 20.0
"""Battery at or below this: low_battery, warning."""
LOW_BATTERY_CRITICAL_PERCENT = 10.0
"""Battery at or below this: low_battery, critical."""
TANK_LOW_PERCENT = 15.0
"""Disinfectant at or below this: tank_low (info)."""
PERCENT_HYSTERESIS = 2.0
"""A battery or tank alarm clears (or steps down) only this many points above its threshold."""
LOCALISATION_SCORE_MIN = 0.5
"""``agvPosition.localizationScore`` below this (or UWB stale, or not initialised): localisation."""
LOCALISATION_SCORE_CLEAR = 0.6
"""... and it clears once the score is back at or above this (and the rest is fine)."""
LINK_QUIET_S = 3.0
"""A robot heard on neither link for this long: link_lost, as this console sees it (the fleet
table calls it lost after the same time)."""
RENOTIFY_S = 30.0
"""An unacknowledged critical alarm notifies again this often."""
MAX_PENDING_ROBOTS = 64
"""Robots never heard from whose acknowledgements are held (retained ones may come before the
robot's first message); one more is refused as an unknown robot."""
MAX_ACK_SOURCES = 4096
"""(robot, login) pairs whose acknowledgements are kept; beyond that new ones are refused."""


class AlarmSeverity(enum.StrEnum):
    CRITICAL = "critical"
    WARNING = "warning"
    INFO = "info"


RANK = {AlarmSeverity.INFO: 0, AlarmSeverity.WARNING: 1, AlarmSeverity.CRITICAL: 2}


class AlarmKind(enum.StrEnum):
    LOW_BATTERY = "low_battery"
    ROBOT_LOST = "robot_lost"
    BOARD_FAULT = "board_fault"
    CLIFF = "cliff"
    BUMP = "bump"
    ESTOP = "estop"
    LINK_LOST = "link_lost"
    LINK_DEGRADED = "link_degraded"
    TANK_LOW = "tank_low"
    LOCALISATION = "localisation"


@dataclass(frozen=True, slots=True)
class KindSpec:
    severity: AlarmSeverity
    """Its severity (low_battery: warning, critical at ``LOW_BATTERY_CRITICAL_PERCENT``)."""
    latching: bool
    """Stays until acknowledged (events), instead of clearing when its condition goes away."""
    label: str


KINDS: dict[AlarmKind, KindSpec] = {
    AlarmKind.ROBOT_LOST: KindSpec(AlarmSeverity.CRITICAL, False, "robot lost"),
    AlarmKind.ESTOP: KindSpec(AlarmSeverity.CRITICAL, False, "e-stop"),
    AlarmKind.LINK_LOST: KindSpec(AlarmSeverity.CRITICAL, False, "link lost"),
    AlarmKind.CLIFF: KindSpec(AlarmSeverity.CRITICAL, True, "cliff"),
    AlarmKind.LOW_BATTERY: KindSpec(AlarmSeverity.WARNING, False, "low battery"),
    AlarmKind.BOARD_FAULT: KindSpec(AlarmSeverity.WARNING, False, "board fault"),
    AlarmKind.BUMP: KindSpec(AlarmSeverity.WARNING, True, "bump"),
    AlarmKind.LOCALISATION: KindSpec(AlarmSeverity.WARNING, False, "localisation degraded"),
    AlarmKind.LINK_DEGRADED: KindSpec(AlarmSeverity.WARNING, False, "link degraded"),
    AlarmKind.TANK_LOW: KindSpec(AlarmSeverity.INFO, False, "tank low"),
}


def parse_kind(text: str) -> AlarmKind | None:
    """``low_battery``, ``low-battery`` or ``e-stop`` -> the kind; None if there is no such kind."""
    word = text.strip().lower().replace("-", "_")
    aliases = {"e_stop": "estop", "battery": "low_battery", "lost": "robot_lost", "localization": "localisation"}
    try:
        return AlarmKind(aliases.get(word, word))
    except ValueError:
        return None


# -- records ----------------------------------------------------------------------------------------


class AuditEvent(enum.StrEnum):
    RAISED = "raised"
    ESCALATED = "escalated"
    """The alarm got worse (a new episode: earlier acknowledgements do not cover it)."""
    RENOTIFIED = "renotified"
    CLEARED = "cleared"
    ACKNOWLEDGED = "acknowledged"
    REFUSED = "refused"
    """An acknowledgement refused (bad or unknown); recorded once per reason."""


@dataclass(frozen=True, slots=True)
class AuditRecord:
    """One line of the audit log."""

    at: float
    event: AuditEvent
    robot: str
    kind: str
    severity: str
    text: str
    by: str | None = None
    """Who acknowledged (acknowledged), or who sent what was refused (refused)."""
    since: float | None = None
    """The episode (see the module docstring)."""
    count: int = 0

    def as_dict(self) -> dict[str, object]:
        return {
            "at": self.at,
            "event": self.event.value,
            "robot": self.robot,
            "kind": self.kind,
            "severity": self.severity,
            "text": self.text,
            "by": self.by,
            "since": self.since,
            "count": self.count,
        }


@dataclass(slots=True)
class Alarm:
    robot: str
    kind: AlarmKind
    severity: AlarmSeverity
    text: str
    first_seen: float
    last_seen: float
    since: float
    """The episode's start (see the module docstring)."""
    observed: float
    """The source time of the latest observation of it."""
    notified_at: float
    """When it was last raised or renotified (``due_renotifications``)."""
    count: int = 1
    """Occurrences in this episode: every event of a latching alarm, every time it got worse."""
    active: bool = True
    acked_by: str | None = None
    acked_at: float | None = None

    @property
    def latching(self) -> bool:
        return KINDS[self.kind].latching

    @property
    def label(self) -> str:
        return KINDS[self.kind].label


@dataclass(frozen=True, slots=True)
class AckEntry:
    """One acknowledged episode, as an ``AlarmAck`` carries it."""

    kind: AlarmKind
    since: float
    at: float

    def wire(self) -> AckedAlarm:
        return AckedAlarm(kind=self.kind.value, since=self.since, at=self.at)


@dataclass(frozen=True, slots=True)
class AckOutcome:
    """What an operator's acknowledgement did: the alarms it acknowledged, or why none."""

    acked: tuple[Alarm, ...] = ()
    reason: str = ""


Key = tuple[str, AlarmKind]

# -- the alarm list ---------------------------------------------------------------------------------


class AlarmList:
    """One alarm per (robot, kind), its episodes, acknowledgements and their audit records."""

    def __init__(self, *, renotify_s: float = RENOTIFY_S) -> None:
        if not renotify_s > 0:
            raise ValueError(f"renotify_s must be > 0, got {renotify_s!r}")
        self.renotify_s = renotify_s
        self.version = 0
        """Bumped on every change (views redraw when it moved)."""
        self._alarms: dict[Key, Alarm] = {}
        self._floor: dict[Key, float] = {}
        self._acks: dict[str, dict[str, dict[AlarmKind, AckEntry]]] = {}
        """robot -> login -> kind -> the episode that login acknowledged."""
        self._audit: list[AuditRecord] = []

    # -- views ----------------------------------------------------------------------------------

    def get(self, robot: str, kind: AlarmKind) -> Alarm | None:
        """The active alarm of ``kind`` on ``robot`` (None when there is none)."""
        alarm = self._alarms.get((robot, kind))
        return alarm if alarm is not None and alarm.active else None

    def active(self, robot: str | None = None) -> list[Alarm]:
        """Active alarms (of ``robot``), unacknowledged first, then most severe, then by robot and kind."""
        alarms = [a for a in self._alarms.values() if a.active and (robot is None or a.robot == robot)]
        return sorted(alarms, key=lambda a: (a.acked_by is not None, -RANK[a.severity], a.robot, a.kind.value))

    def floor(self, robot: str, kind: AlarmKind) -> float:
        """The last source time at which this alarm is known to have been off (-inf: never seen off)."""
        return self._floor.get((robot, kind), -math.inf)

    def acks_of(self, robot: str, by: str) -> tuple[AckEntry, ...]:
        """The episodes ``by`` acknowledged on ``robot`` that have not ended here, by kind."""
        entries = self._acks.get(robot, {}).get(by, {})
        return tuple(entries[k] for k in sorted(entries))

    def drain_audit(self) -> list[AuditRecord]:
        out, self._audit = self._audit, []
        return out

    # -- changes --------------------------------------------------------------------------------

    def raise_alarm(
        self,
        robot: str,
        kind: AlarmKind,
        text: str,
        now: float,
        *,
        severity: AlarmSeverity | None = None,
        since: float | None = None,
    ) -> Alarm:
        """The alarm is on (observed at ``since``, default ``now``). A new episode if it was off;
        if it is on, one more occurrence (``count``, ``last_seen``), a new episode if ``severity``
        is worse. (Copies of a message from the other link never come here: the fleet model
        keeps the first.)"""
        sev = severity if severity is not None else KINDS[kind].severity
        at = now if since is None else since
        key = (robot, kind)
        alarm = self._alarms.get(key)
        if alarm is not None and alarm.active:
            alarm.count += 1
            alarm.last_seen = max(alarm.last_seen, now)
            alarm.text = text
            if RANK[sev] > RANK[alarm.severity]:
                before = alarm.observed if alarm.observed < at else math.nextafter(at, -math.inf)
                self._raise_floor(key, before)
                alarm.severity, alarm.since, alarm.notified_at = sev, at, now
                alarm.acked_by = alarm.acked_at = None
                self._record(now, AuditEvent.ESCALATED, alarm)
                self._apply_held(alarm, now)
            alarm.observed = max(alarm.observed, at)
            self.version += 1
            return alarm
        if alarm is not None:  # the previous episode (a latching one ends only here)
            self._raise_floor(key, alarm.observed)
        # After the last time it was seen off, whatever the clocks say (another source's clock
        # may lag): acknowledgements of the earlier episodes stay out.
        at = max(at, math.nextafter(self.floor(robot, kind), math.inf))
        alarm = Alarm(robot, kind, sev, text, first_seen=now, last_seen=now, since=at, observed=at, notified_at=now)
        self._alarms[key] = alarm
        self.version += 1
        self._record(now, AuditEvent.RAISED, alarm)
        self._apply_held(alarm, now)
        return alarm

    def seen(
        self, robot: str, kind: AlarmKind, now: float, *, text: str | None = None, since: float | None = None
    ) -> None:
        """The active alarm is still on (its condition observed again): ``last_seen`` only."""
        alarm = self.get(robot, kind)
        if alarm is None:
            return
        alarm.last_seen = max(alarm.last_seen, now)
        alarm.observed = max(alarm.observed, now if since is None else since)
        if text is not None and text != alarm.text:
            alarm.text = text
            self.version += 1

    def clear(self, robot: str, kind: AlarmKind, now: float, *, since: float | None = None) -> bool:
        """The alarm's condition is gone (observed at ``since``, default ``now``). True if that
        ended an episode."""
        at = now if since is None else since
        key = (robot, kind)
        alarm = self.get(robot, kind)
        self._raise_floor(key, at if alarm is None else max(at, alarm.observed))
        if alarm is None:
            return False
        alarm.active = False
        alarm.last_seen = max(alarm.last_seen, now)
        self.version += 1
        self._record(now, AuditEvent.CLEARED, alarm)
        return True

    def acknowledge(self, robot: str, kind: AlarmKind, by: str, at: float) -> Alarm | str:
        """``by`` acknowledges the active alarm (at ``at``): the alarm, or why not. A latching alarm
        ends with its acknowledgement."""
        alarm = self.get(robot, kind)
        if alarm is None:
            return f"{robot}: no {KINDS[kind].label} alarm"
        if alarm.acked_by is not None:
            return f"{robot}: {alarm.label} already acknowledged by {alarm.acked_by}"
        self._acks.setdefault(robot, {}).setdefault(by, {})[kind] = AckEntry(kind, alarm.since, at)
        self._acked(alarm, by, at, at)
        return alarm

    def record_acks(
        self, robot: str, by: str, entries: Iterable[AckEntry], now: float, *, merge: bool = False
    ) -> list[Alarm]:
        """What ``by`` says it acknowledged on ``robot`` (its whole list: it replaces the previous
        one, or with ``merge`` adds to it); the active alarms it covers are acknowledged (returned)."""
        table = self._acks.setdefault(robot, {})
        held = table.setdefault(by, {}) if merge else {}
        for entry in entries:
            if entry.since > self.floor(robot, entry.kind):  # an episode that ended here: forgotten
                held[entry.kind] = entry
        if held:
            table[by] = held
        else:
            table.pop(by, None)
        acked: list[Alarm] = []
        for entry in held.values():
            alarm = self.get(robot, entry.kind)
            if alarm is not None and alarm.acked_by is None and entry.since > self.floor(robot, entry.kind):
                self._acked(alarm, by, entry.at, now)
                acked.append(alarm)
        if not table:
            del self._acks[robot]
        return acked

    def due_renotifications(self, now: float) -> list[Alarm]:
        """Unacknowledged critical alarms last notified ``renotify_s`` or more ago: notified again
        now (their ``notified_at`` moves on)."""
        due: list[Alarm] = []
        for alarm in self._alarms.values():
            if (
                alarm.active
                and alarm.acked_by is None
                and alarm.severity is AlarmSeverity.CRITICAL
                and now - alarm.notified_at >= self.renotify_s
            ):
                alarm.notified_at = now
                self._record(now, AuditEvent.RENOTIFIED, alarm)
                due.append(alarm)
        return due

    def refused(self, now: float, robot: str, kind: str, by: str, reason: str) -> None:
        """Record a refused acknowledgement in the audit (the caller does so once per reason)."""
        self._audit.append(AuditRecord(now, AuditEvent.REFUSED, robot, kind, "", reason, by=by))

    def sources(self) -> int:
        """(robot, login) pairs whose acknowledgements are held."""
        return sum(len(logins) for logins in self._acks.values())

    def holds(self, robot: str, by: str) -> bool:
        return by in self._acks.get(robot, {})

    def acked_robots(self) -> set[str]:
        """Robots with acknowledgements held."""
        return set(self._acks)

    # -- internals ------------------------------------------------------------------------------

    def _acked(self, alarm: Alarm, by: str, at: float, now: float) -> None:
        alarm.acked_by, alarm.acked_at = by, at
        self.version += 1
        self._record(now, AuditEvent.ACKNOWLEDGED, alarm, by=by)
        if alarm.latching:  # it was waiting for exactly this; its floor rises with the next event
            alarm.active = False
            self._record(now, AuditEvent.CLEARED, alarm, by=by)

    def _apply_held(self, alarm: Alarm, now: float) -> None:
        """Acknowledgements held for this alarm's kind that cover the new episode (the earliest)."""
        floor = self.floor(alarm.robot, alarm.kind)
        covering = [
            (entry.at, by)
            for by, entries in self._acks.get(alarm.robot, {}).items()
            if (entry := entries.get(alarm.kind)) is not None and entry.since > floor
        ]
        if covering:
            at, by = min(covering)
            self._acked(alarm, by, at, now)

    def _raise_floor(self, key: Key, at: float) -> None:
        if at <= self._floor.get(key, -math.inf):
            return
        self._floor[key] = at
        robot, kind = key
        for entries in self._acks.get(robot, {}).values():  # acknowledgements of ended episodes
            entry = entries.get(kind)
            if entry is not None and entry.since <= at:
                del entries[kind]

    def _record(self, now: float, event: AuditEvent, alarm: Alarm, *, by: str | None = None) -> None:
        self._audit.append(
            AuditRecord(
                now,
                event,
                alarm.robot,
                alarm.kind.value,
                alarm.severity.value,
                alarm.text,
                by,
                alarm.since,
                alarm.count,
            )
        )


# -- what robots say, as alarm conditions -----------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Observation:
    """One source's view of one alarm condition: on (``severity``) or off (None). ``event``: an
    occurrence of a latching alarm (never an "off")."""

    kind: AlarmKind
    source: str
    severity: AlarmSeverity | None
    text: str = ""
    event: bool = False


_QUIET_TEXT = f"nothing heard on any link for over {LINK_QUIET_S:.0f} s"
_LINK_QUIET = Observation(AlarmKind.LINK_LOST, "console", AlarmSeverity.CRITICAL, _QUIET_TEXT)
_LINK_HEARD = Observation(AlarmKind.LINK_LOST, "console", None, _QUIET_TEXT)
_LINKS_FINE = Observation(AlarmKind.LINK_DEGRADED, "console", None, "")
"""The console's own link observations that every robot gets twice a second, made once."""

Prior = Callable[[AlarmKind, str], AlarmSeverity | None]
"""(kind, source) -> what that source said last (for hysteresis)."""


def _percent_level(
    percent: float, prior: AlarmSeverity | None, warning: float, critical: float | None
) -> AlarmSeverity | None:
    if critical is not None and percent <= critical + (PERCENT_HYSTERESIS if prior is AlarmSeverity.CRITICAL else 0):
        return AlarmSeverity.CRITICAL
    if percent <= warning + (PERCENT_HYSTERESIS if prior is not None else 0):
        return AlarmSeverity.WARNING
    return None


def _battery(percent: float, source: str, prior: Prior) -> Observation:
    level = _percent_level(
        percent, prior(AlarmKind.LOW_BATTERY, source), LOW_BATTERY_WARNING_PERCENT, LOW_BATTERY_CRITICAL_PERCENT
    )
    return Observation(AlarmKind.LOW_BATTERY, source, level, f"battery {percent:.0f} %")


def _state(s: State, prior: Prior, heading_known: bool = True) -> list[Observation]:
    estop = s.safetyState.eStop
    p = s.agvPosition
    degraded = prior(AlarmKind.LOCALISATION, "state") is not None
    minimum = LOCALISATION_SCORE_CLEAR if degraded else LOCALISATION_SCORE_MIN
    # Placed by UWB but not yet driven: the heading is found from the fixes along its first half
    # metre or so (agent/fusion.py), and until then the score is 0 whatever the fixes say.
    unheaded = p.positionInitialized and not heading_known
    why = [
        text
        for bad, text in (
            (not p.positionInitialized, "position not initialised"),
            (unheaded, "heading not found yet: it is found as the robot drives"),
            (s.uwbStale, "UWB stale"),
            (p.localizationScore < minimum and not unheaded, f"score {p.localizationScore:.2f}"),
        )
        if bad
    ]
    c = s.contact
    doing = f", {c.action}" if c.action else ""
    return [
        Observation(
            AlarmKind.ESTOP,
            "state",
            AlarmSeverity.CRITICAL if estop is not EStop.NONE else None,
            f"e-stop {estop.value.lower()}",
        ),
        Observation(
            AlarmKind.LOCALISATION,
            "state",
            AlarmSeverity.WARNING if why else None,
            "localisation: " + ", ".join(why),
        ),
        Observation(
            AlarmKind.LINK_LOST,
            "contact",
            AlarmSeverity.CRITICAL if c.lost else None,
            f"robot hears no operator for {c.silent_s:.0f} s ({c.policy.value}{doing})",
        ),
        Observation(
            AlarmKind.BOARD_FAULT,
            "state",
            AlarmSeverity.WARNING if not s.boardConnected else None,
            "board not connected",
        ),
    ]


def _board(b: BoardStatus, prior: Prior) -> list[Observation]:
    faults = "; ".join(f"{f.code}: {f.text}" for f in b.faults)
    fault = faults or ("" if b.connected else "board link down")
    # The battery from the board's own report only (a State's batteryCharge is 0 until the
    # board's first status poll), and only while the agent hears the board.
    out = [_battery(b.battery_percent, "board", prior)] if b.connected else []
    out += [
        Observation(AlarmKind.BOARD_FAULT, "board", AlarmSeverity.WARNING if fault else None, f"board fault {fault}"),
        Observation(
            AlarmKind.ESTOP, "board", AlarmSeverity.CRITICAL if b.estop_button else None, "e-stop button pressed"
        ),
    ]
    if b.tank_percent is not None:
        level = _percent_level(b.tank_percent, prior(AlarmKind.TANK_LOW, "board"), TANK_LOW_PERCENT, None)
        sev = AlarmSeverity.INFO if level is not None else None
        out.append(Observation(AlarmKind.TANK_LOW, "board", sev, f"tank {b.tank_percent:.0f} %"))
    return out


EVENT_KINDS = {"cliff": AlarmKind.CLIFF, "bump": AlarmKind.BUMP}
"""``Event.kind`` -> the latching alarm it raises."""


def derive(
    msg: Message, prior: Prior = lambda _kind, _source: None, *, heading_known: bool = True
) -> list[Observation]:
    """The alarm conditions one message from a robot shows ([] for a message that shows none).
    ``prior`` says what each source said last (for hysteresis; ``AlarmDesk`` keeps it);
    ``heading_known``: what the robot's last ``Pose`` said of its heading (a ``State`` has no word
    for it)."""
    if isinstance(msg, State):
        return _state(msg, prior, heading_known)
    if isinstance(msg, BoardStatus):
        return _board(msg, prior)
    if isinstance(msg, Event):
        kind = EVENT_KINDS.get(msg.kind)
        if kind is None:
            return []
        return [Observation(kind, "event", KINDS[kind].severity, msg.text or msg.kind, event=True)]
    return []


def links_quiet(ages: Sequence[float | None], quiet_s: float = LINK_QUIET_S) -> bool:
    """Whether a robot heard before is silent on every link (ages of its last message per link, None:
    never heard on that link) for longer than ``quiet_s``."""
    heard = [a for a in ages if a is not None]
    return bool(heard) and all(a > quiet_s for a in heard)


# -- one console's alarms ---------------------------------------------------------------------------

PRESENCE_SOURCE = "presence"


class AlarmDesk:
    """One console's alarms: observations, presence and link quiet in; acknowledgements (this
    console's and the other consoles') both ways. See the module docstring.

    ``operator`` is this console's login: ``acknowledge`` acknowledges as it, and ``outgoing`` gives
    the ``AlarmAck`` lists to publish under it."""

    def __init__(self, operator: str, *, renotify_s: float = RENOTIFY_S) -> None:
        self.operator = operator
        self.alarms = AlarmList(renotify_s=renotify_s)
        self.known: set[str] = set()
        """Robots heard from (a message, a presence token)."""
        self.refused: Counter[str] = Counter()
        """Acknowledgements refused, by reason."""
        self._said: dict[Key, dict[str, Observation]] = {}
        self._presence: dict[str, dict[str, bool]] = {}
        self._ack_stamp: dict[tuple[str, str], tuple[float, int]] = {}
        self._published: dict[str, tuple[AckEntry, ...]] = {}
        self._pending: set[str] = set()
        self._unheaded: set[str] = set()
        """Robots whose last ``Pose`` said their heading is not known (``UNKNOWN_SD_M``)."""
        self._own_frame: dict[str, str | None] = {}
        """Robots mapping in their own frame (no UWB): None once the fleet map has placed that frame,
        else why it has not (``own_frame``)."""

    def forget(self) -> None:
        """Back to a desk that has heard nothing (a replay seeking back: operator/feed.py
        ``FleetFeed.forget``): a fresh desk's state, kept in this object (the alarm keeper holds
        it), the alarms' version moved on (views key their caches on it)."""
        fresh = AlarmDesk(self.operator, renotify_s=self.alarms.renotify_s)
        fresh.alarms.version = self.alarms.version + 1
        vars(self).update(vars(fresh))

    # -- inputs ---------------------------------------------------------------------------------

    def observe(self, msg: Message, now: float) -> str | None:
        """Fold in one message heard (new, not a copy from the other link). An ``AlarmAck`` that
        is refused returns the reason (counted); everything else None."""
        if isinstance(msg, AlarmAck):
            return self.receive_ack(msg, now)
        if msg.TOPIC in keys.SENDER_TOPICS:
            return None  # what consoles say (commands, marks) proves no robot is there
        robot = msg.header.robot
        self._know(robot, msg.header.timestamp, now)
        if isinstance(msg, Connection):
            alive = msg.connectionState is ConnectionState.ONLINE
            self.presence(robot, "mqtt", alive, now)
            return None
        if isinstance(msg, Pose):
            if msg.sd_theta_rad >= UNKNOWN_SD_M:
                self._unheaded.add(robot)
            else:
                self._unheaded.discard(robot)

        def prior(kind: AlarmKind, source: str) -> AlarmSeverity | None:
            return self._prior(robot, kind, source)

        for obs in derive(msg, prior, heading_known=robot not in self._unheaded):
            if obs.kind is AlarmKind.LOCALISATION and isinstance(msg, State):
                obs = self._own_frame_localisation(robot, msg, obs)
            self._apply(robot, obs, now, msg.header.timestamp)
        return None

    def own_frame(self, robot: str, unplaced_why: str | None, *, mapping: bool = True) -> None:
        """The fleet map's word on a robot that maps in its own frame (no UWB position): placed on the
        fleet map (``unplaced_why`` None) or not yet, and why not. Such a robot never has a site
        position, so "position not initialised" would stand for as long as it runs; while it is
        placed, its localisation is its own map's on the fleet map and raises nothing, and until then
        the warning says the fleet map has not found it. ``mapping`` False: no longer such a robot.
        Applied with the robot's next ``State``."""
        if mapping:
            self._own_frame[robot] = unplaced_why
        else:
            self._own_frame.pop(robot, None)

    def _own_frame_localisation(self, robot: str, msg: State, obs: Observation) -> Observation:
        if robot not in self._own_frame or msg.agvPosition.positionInitialized:
            return obs
        why = self._own_frame[robot]
        if why is None:
            return Observation(obs.kind, obs.source, None, "localisation: its own map, placed on the fleet map")
        text = "localisation: its own map, not on the fleet map yet" + (f" ({why})" if why else "")
        return Observation(obs.kind, obs.source, AlarmSeverity.WARNING, text)

    def presence(self, robot: str, source: str, alive: bool, now: float) -> None:
        """``source`` (``zenoh``: the liveliness token; ``mqtt``: the retained ``Connection``) says
        whether the robot is there. Robot lost: some source says gone and none says there."""
        self._know(robot, now, now)
        sources = self._presence.setdefault(robot, {})
        sources[source] = alive
        lost = not any(sources.values())
        text = "gone: " + ", ".join(f"{s} {'token' if s == 'zenoh' else 'connection'}" for s in sorted(sources))
        obs = Observation(AlarmKind.ROBOT_LOST, PRESENCE_SOURCE, AlarmSeverity.CRITICAL if lost else None, text)
        self._apply(robot, obs, now, self._fresh(robot, obs.kind, now))

    def present(self, robot: str) -> bool | None:
        """True if some presence source says the robot is there, False if one says it is gone and
        none that it is there, None if none has said."""
        sources = self._presence.get(robot)
        if not sources:
            return None
        return any(sources.values())

    def link_quiet(self, robot: str, quiet: bool, now: float) -> None:
        """This console's view: the robot was heard on neither link for ``LINK_QUIET_S``."""
        obs = _LINK_QUIET if quiet else _LINK_HEARD
        self._apply(robot, obs, now, self._fresh(robot, obs.kind, now))

    def link_degraded(self, robot: str, degraded: Sequence[tuple[str, str]], now: float) -> None:
        """This console's view of one robot's links: [(link, why it is degraded)] (the link
        manager's ``LinkHealth.degraded``: loss, RTT p95 or silence over the thresholds); an empty
        list clears the alarm. (A robot silent on every link is ``link_lost``, not this.)"""
        if degraded:
            text = "; ".join(f"{link} {why}" for link, why in degraded)
            obs = Observation(AlarmKind.LINK_DEGRADED, "console", AlarmSeverity.WARNING, text)
        else:
            obs = _LINKS_FINE
        self._apply(robot, obs, now, self._fresh(robot, obs.kind, now))

    def receive_ack(self, msg: AlarmAck, now: float) -> str | None:
        """Another console's acknowledgements (or this login's own, retained from before a
        restart). The reason if refused (counted; the caller logs it once), else None. Entries of
        an unknown kind are refused alone; the rest still apply."""
        robot, by = msg.header.robot, msg.header.sender
        stamp = (msg.header.timestamp, msg.header.headerId)
        last = self._ack_stamp.get((robot, by))
        if last is not None and stamp <= last:
            return None  # the same list again (both links, the retained copy) or an older one
        if robot not in self.known and robot not in self._pending:
            if len(self._pending) >= MAX_PENDING_ROBOTS:
                return self._refuse(now, robot, "", by, f"unknown robot {robot!r}")
            self._pending.add(robot)
        if not self.alarms.holds(robot, by) and self.alarms.sources() >= MAX_ACK_SOURCES:
            return self._refuse(now, robot, "", by, f"too many acknowledging consoles (over {MAX_ACK_SOURCES})")
        kinds = [a.kind for a in msg.acks]
        if len(set(kinds)) != len(kinds):
            return self._refuse(now, robot, "", by, "an alarm kind is listed twice")
        self._ack_stamp[(robot, by)] = stamp
        entries: list[AckEntry] = []
        reason: str | None = None
        for acked in msg.acks:
            try:
                kind = AlarmKind(acked.kind)
            except ValueError:  # a newer console's kind, or garbage: the other entries still count
                reason = self._refuse(now, robot, acked.kind, by, f"unknown alarm kind {acked.kind!r}")
                continue
            entries.append(AckEntry(kind, acked.since, acked.at))
        mine = by == self.operator
        self.alarms.record_acks(robot, by, entries, now, merge=mine)
        if mine:  # restored from the broker: no need to publish it again
            self._published[robot] = tuple(sorted(entries, key=lambda e: e.kind.value))
        return reason

    def tick(self, now: float) -> list[Alarm]:
        """The unacknowledged critical alarms to notify again now."""
        return self.alarms.due_renotifications(now)

    # -- the operator ---------------------------------------------------------------------------

    def acknowledge(self, robot: str, kind: AlarmKind | None, at: float, *, every: bool = False) -> AckOutcome:
        """This console's operator acknowledges ``robot``'s alarm of ``kind``, or (None) its most
        severe unacknowledged one, or (``every``) all of them."""
        if robot not in self.known:
            return AckOutcome(reason=f"unknown robot {robot!r}")
        waiting = [a for a in self.alarms.active(robot) if a.acked_by is None]
        if kind is not None:
            done = self.alarms.acknowledge(robot, kind, self.operator, at)
            return AckOutcome(reason=done) if isinstance(done, str) else AckOutcome(acked=(done,))
        if not waiting:
            return AckOutcome(reason=f"{robot}: no unacknowledged alarm")
        acked: list[Alarm] = []
        for alarm in waiting if every else waiting[:1]:
            done = self.alarms.acknowledge(robot, alarm.kind, self.operator, at)
            if not isinstance(done, str):
                acked.append(done)
        return AckOutcome(acked=tuple(acked))

    def outgoing(self) -> list[tuple[str, tuple[AckEntry, ...]]]:
        """(robot, this console's acknowledgements on it) for every robot whose list changed since
        it was last handed out: publish each as an ``AlarmAck`` (an empty list withdraws them)."""
        out: list[tuple[str, tuple[AckEntry, ...]]] = []
        robots = set(self._published) | self.alarms.acked_robots()
        for robot in sorted(robots):
            now = self.alarms.acks_of(robot, self.operator)
            if now != self._published.get(robot, ()):
                self._published[robot] = now
                out.append((robot, now))
        return out

    def published(self) -> list[tuple[str, tuple[AckEntry, ...]]]:
        """Every list handed out so far (to publish again after a broker restart)."""
        return sorted(self._published.items())

    def rows(self) -> list[Alarm]:
        return self.alarms.active()

    def drain_audit(self) -> list[AuditRecord]:
        return self.alarms.drain_audit()

    # -- internals ------------------------------------------------------------------------------

    def _know(self, robot: str, source_time: float, now: float) -> None:
        if robot in self.known:
            return
        self.known.add(robot)
        self._pending.discard(robot)
        for kind, spec in KINDS.items():  # events before this were never heard here
            if spec.latching:
                self.alarms.clear(robot, kind, now, since=source_time)

    def _fresh(self, robot: str, kind: AlarmKind, now: float) -> float:
        """The source time of what this console sees itself (in order, so never stale): ``now``,
        or just after the alarm's latest known time when the clock has not moved since."""
        alarm = self.alarms.get(robot, kind)
        latest = max(self.alarms.floor(robot, kind), alarm.observed if alarm is not None else -math.inf)
        return now if now > latest else math.nextafter(latest, math.inf)

    def _prior(self, robot: str, kind: AlarmKind, source: str) -> AlarmSeverity | None:
        said = self._said.get((robot, kind), {}).get(source)
        return None if said is None else said.severity

    def _apply(self, robot: str, obs: Observation, now: float, since: float) -> None:
        if obs.event:
            self.alarms.raise_alarm(robot, obs.kind, obs.text, now, severity=obs.severity, since=since)
            return
        said = self._said.setdefault((robot, obs.kind), {})
        said[obs.source] = obs
        on = [(RANK[o.severity], o.text, o.severity) for o in said.values() if o.severity is not None]
        if not on:
            self.alarms.clear(robot, obs.kind, now, since=since)
            return
        rank, text, severity = max(on)
        alarm = self.alarms.get(robot, obs.kind)
        if alarm is None or rank > RANK[alarm.severity]:
            self.alarms.raise_alarm(robot, obs.kind, text, now, severity=severity, since=since)
        else:
            self.alarms.seen(robot, obs.kind, now, text=text, since=since)

    def _refuse(self, now: float, robot: str, kind: str, by: str, reason: str) -> str:
        first = reason not in self.refused
        if first and len(self.refused) >= 256:
            reason = "(other reasons)"
            first = reason not in self.refused
        self.refused[reason] += 1
        if first:
            self.alarms.refused(now, robot, kind, by, reason)
        return reason
