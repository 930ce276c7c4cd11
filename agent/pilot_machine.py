"""The pilot's operating modes as one state machine: every state, trigger and transition declared here (pure).

``next_state(state, trigger)`` looks the pair up in ``TRANSITIONS``: either a ``Transition`` (the
target state and the effects the pilot carries out, in order) or a ``Refused`` (the status and
reason the command gets back; the state does not change). The table is total: every state has an
outcome for every trigger, checked when this module loads, so no mode change is left implicit.

What a state carries lives with it in the pilot: a teleop command exactly in ``MANUAL``, a route
(the go-to's destination and its planning) exactly in the four go-to states. Checks on a command's
own arguments (finite numbers, order idempotency, who is driving) come before the table: they do
not depend on the mode.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Final

__all__ = [
    "TRANSITIONS",
    "Announce",
    "Cancel",
    "CommandResult",
    "CommandStatus",
    "Do",
    "Effect",
    "EventKind",
    "OperatingMode",
    "Outcome",
    "PilotState",
    "Refused",
    "Transition",
    "Trigger",
    "next_state",
]


class OperatingMode(StrEnum):
    """The mode the pilot reports (coarser than ``PilotState``)."""

    IDLE = "IDLE"
    MANUAL = "MANUAL"
    AUTOMATIC = "AUTOMATIC"
    PAUSED = "PAUSED"
    ESTOP = "ESTOP"


class EventKind(StrEnum):
    GUARD_REFUSAL = "GUARD_REFUSAL"
    CLIFF = "CLIFF"
    BUMP = "BUMP"
    GOAL_REACHED = "GOAL_REACHED"
    GOAL_CANCELLED = "GOAL_CANCELLED"
    GOAL_FAILED = "GOAL_FAILED"
    DEADMAN_STOP = "DEADMAN_STOP"
    ESTOP_LATCHED = "ESTOP_LATCHED"
    ESTOP_RELEASED = "ESTOP_RELEASED"
    PAUSED = "PAUSED"
    RESUMED = "RESUMED"
    STOPPED = "STOPPED"
    FAULT = "FAULT"
    PATH_PLANNED = "PATH_PLANNED"  # a go-to follows a planned path (``waypoints``: how many)
    REPLANNED = "REPLANNED"  # the way was barred (or no progress): a new path from here
    WAITING = "WAITING"  # a go-to found no path: it stands (a far goal: nearer it first) until a newer map has one (``no_path_wait_s``)


class CommandStatus(StrEnum):
    ACCEPTED = "accepted"
    DUPLICATE = "duplicate"
    REJECTED = "rejected"


@dataclass(frozen=True, slots=True)
class CommandResult:
    status: CommandStatus
    reason: str = ""

    @property
    def accepted(self) -> bool:
        return self.status is CommandStatus.ACCEPTED


class PilotState(StrEnum):
    IDLE = "idle"  # still, nothing to do
    MANUAL = "manual"  # driven by teleop until its command lapses
    GOTO = "goto"  # driving to an order's goal
    GOTO_PAUSED = "goto_paused"  # an order held where it stands
    HOMING = "homing"  # driving home (return_home)
    HOMING_PAUSED = "homing_paused"  # the way home held
    ESTOP = "estop"  # latched: still until released

    @property
    def mode(self) -> OperatingMode:
        return _MODES[self]

    @property
    def has_route(self) -> bool:
        """An order or the way home is held in this state (driven or paused)."""
        return self in _ROUTE_STATES

    @property
    def driving_route(self) -> bool:
        """The route runs: the go-to steers the robot."""
        return self in (PilotState.GOTO, PilotState.HOMING)


_MODES: Final[Mapping[PilotState, OperatingMode]] = {
    PilotState.IDLE: OperatingMode.IDLE,
    PilotState.MANUAL: OperatingMode.MANUAL,
    PilotState.GOTO: OperatingMode.AUTOMATIC,
    PilotState.HOMING: OperatingMode.AUTOMATIC,
    PilotState.GOTO_PAUSED: OperatingMode.PAUSED,
    PilotState.HOMING_PAUSED: OperatingMode.PAUSED,
    PilotState.ESTOP: OperatingMode.ESTOP,
}
_ROUTE_STATES: Final = frozenset({PilotState.GOTO, PilotState.GOTO_PAUSED, PilotState.HOMING, PilotState.HOMING_PAUSED})


class Trigger(StrEnum):
    # Commands (from an operator or a fleet manager):
    TELEOP = "teleop"  # a velocity command (its arguments and who drives checked first)
    ORDER_NEW = "order_new"  # an order other than the one held (or none held)
    ORDER_UPDATE = "order_update"  # a higher update of the order held
    RETURN_HOME = "return_home"
    RETRACE = "retrace"  # out of contact (comms-loss policy): back along its own path, as return home
    PAUSE = "pause"
    RESUME = "resume"
    CANCEL = "cancel"
    STOP = "stop"
    HALT = "halt"  # a stop that leaves the payload as it is (the comms-loss policy, when configured so)
    ESTOP = "estop"
    ESTOP_RELEASE = "estop_release"
    PAYLOAD_ON = "payload_on"
    PAYLOAD_OFF = "payload_off"
    # From the pilot's own tick:
    TELEOP_LAPSED = "teleop_lapsed"  # no fresh teleop command within its time-to-live
    ROUTE_ENDED = "route_ended"  # the go-to reached its goal or failed
    HAZARD = "hazard"  # a cliff or a bump (rising edge): a go-to fails, nothing else changes


class Do(StrEnum):
    """Effects without parameters (the pilot takes what they need from the command)."""

    TAKE_TELEOP = "take_teleop"  # store the teleop command (the state's data)
    DROP_TELEOP = "drop_teleop"
    START_ROUTE = "start_route"  # a new route to the command's destination (an order or home)
    RESUME_ROUTE = "resume_route"  # the held leg starts afresh; a pause is not a lack of progress
    END_ROUTE = "end_route"  # report how the route ended (GOAL_REACHED / GOAL_FAILED) and drop it
    PASS_PAYLOAD = "pass_payload"  # a payload request for the runtime to send to the board
    CUT_PAYLOAD = "cut_payload"  # every payload off (e-stop, stop, the deadman of a moving robot)


@dataclass(frozen=True, slots=True)
class Cancel:
    """End the route held with GOAL_CANCELLED. ``text`` is formatted with the command's ``sender``
    and ``order_id``; the pilot puts the route's label in front."""

    reason: str
    text: str


@dataclass(frozen=True, slots=True)
class Announce:
    """Emit an event. ``text`` is formatted with the command's ``sender`` (and ``ttl`` for the deadman)."""

    kind: EventKind
    reason: str
    text: str


Effect = Do | Cancel | Announce


@dataclass(frozen=True, slots=True)
class Transition:
    target: PilotState
    effects: tuple[Effect, ...] = ()


@dataclass(frozen=True, slots=True)
class Refused:
    status: CommandStatus
    reason: str

    @property
    def result(self) -> CommandResult:
        return CommandResult(self.status, self.reason)


Outcome = Transition | Refused

# -- the table ----------------------------------------------------------------------------------

S = PilotState
_ALL: Final = tuple(PilotState)
_ROUTES: Final = (S.GOTO, S.GOTO_PAUSED, S.HOMING, S.HOMING_PAUSED)
_ORDERS: Final = (S.GOTO, S.GOTO_PAUSED)
_HOMES: Final = (S.HOMING, S.HOMING_PAUSED)
_NOT_ESTOP: Final = tuple(s for s in _ALL if s is not S.ESTOP)

_LATCHED: Final = Refused(CommandStatus.REJECTED, "e-stop latched")


def _to(target: PilotState, *effects: Effect) -> Transition:
    return Transition(target, effects)


_stay = _to  # (reads better where the state does not change)


def _nothing_to(verb: str, state: PilotState) -> Refused:
    return Refused(CommandStatus.REJECTED, f"nothing to {verb} in mode {state.mode.value}")


def _no(reason: str) -> Refused:
    return Refused(CommandStatus.REJECTED, reason)


_STOPPED = Announce(EventKind.STOPPED, "stop", "stopped by {sender}")
_LATCH = Announce(EventKind.ESTOP_LATCHED, "estop", "e-stop latched by {sender}")
_PAUSE = Announce(EventKind.PAUSED, "pause", "go-to paused by {sender}")
_RESUME = Announce(EventKind.RESUMED, "resume", "go-to resumed by {sender}")

_ROWS: Final[Mapping[Trigger, Mapping[PilotState, Outcome]]] = {
    # Teleop overrides a go-to (precedence: e-stop > guard > the latest command).
    Trigger.TELEOP: {
        S.IDLE: _to(S.MANUAL, Do.TAKE_TELEOP),
        S.MANUAL: _stay(S.MANUAL, Do.TAKE_TELEOP),
        **{
            s: _to(S.MANUAL, Cancel("teleop_override", "cancelled: {sender} took manual control"), Do.TAKE_TELEOP)
            for s in _ROUTES
        },
        S.ESTOP: _LATCHED,
    },
    Trigger.ORDER_NEW: {
        S.IDLE: _to(S.GOTO, Do.START_ROUTE),
        S.MANUAL: _to(S.GOTO, Do.DROP_TELEOP, Do.START_ROUTE),
        **{s: _to(S.GOTO, Cancel("replaced", "replaced by order {order_id}"), Do.START_ROUTE) for s in _ROUTES},
        S.ESTOP: _LATCHED,
    },
    # A higher update of the order held replaces its goal; a paused order stays paused.
    Trigger.ORDER_UPDATE: {
        S.IDLE: _no("no order to update"),
        S.MANUAL: _no("no order to update"),
        S.GOTO: _stay(S.GOTO, Do.START_ROUTE),
        S.GOTO_PAUSED: _stay(S.GOTO_PAUSED, Do.START_ROUTE),
        **{s: _no("no order to update") for s in _HOMES},
        S.ESTOP: _LATCHED,
    },
    Trigger.RETURN_HOME: {
        S.IDLE: _to(S.HOMING, Do.START_ROUTE),
        S.MANUAL: _to(S.HOMING, Do.DROP_TELEOP, Do.START_ROUTE),
        **{s: _to(S.HOMING, Cancel("replaced", "replaced by return home"), Do.START_ROUTE) for s in _ORDERS},
        **{s: _to(S.HOMING, Do.START_ROUTE) for s in _HOMES},  # home again: afresh, nothing cancelled
        S.ESTOP: _LATCHED,
    },
    # Retracing is a way home of another kind (to where the robot last heard an operator).
    Trigger.RETRACE: {
        S.IDLE: _to(S.HOMING, Do.START_ROUTE),
        S.MANUAL: _to(S.HOMING, Do.DROP_TELEOP, Do.START_ROUTE),
        **{
            s: _to(S.HOMING, Cancel("comms_lost", "cancelled: out of contact, retracing"), Do.START_ROUTE)
            for s in _ORDERS
        },
        **{s: _to(S.HOMING, Do.START_ROUTE) for s in _HOMES},
        S.ESTOP: _LATCHED,
    },
    Trigger.PAUSE: {
        S.GOTO: _to(S.GOTO_PAUSED, _PAUSE),
        S.HOMING: _to(S.HOMING_PAUSED, _PAUSE),
        **{s: _nothing_to("pause", s) for s in (S.IDLE, S.MANUAL, S.GOTO_PAUSED, S.HOMING_PAUSED)},
        S.ESTOP: _LATCHED,
    },
    Trigger.RESUME: {
        S.GOTO_PAUSED: _to(S.GOTO, Do.RESUME_ROUTE, _RESUME),
        S.HOMING_PAUSED: _to(S.HOMING, Do.RESUME_ROUTE, _RESUME),
        **{s: _nothing_to("resume", s) for s in (S.IDLE, S.MANUAL, S.GOTO, S.HOMING)},
        S.ESTOP: _LATCHED,
    },
    Trigger.CANCEL: {
        S.IDLE: _no("no order to cancel"),
        S.MANUAL: _no("no order to cancel"),
        **{s: _to(S.IDLE, Cancel("cancel", "cancelled by {sender}")) for s in _ROUTES},
        S.ESTOP: _LATCHED,
    },
    # Anyone may stop the robot, in every state; under e-stop it stays latched.
    # Stop and e-stop also switch every payload off (a UV lamp must not stay on over a stopped robot).
    Trigger.STOP: {
        S.IDLE: _stay(S.IDLE, Do.CUT_PAYLOAD, _STOPPED),
        S.MANUAL: _to(S.IDLE, Do.DROP_TELEOP, Do.CUT_PAYLOAD, _STOPPED),
        **{s: _to(S.IDLE, Cancel("stop", "stopped by {sender}"), Do.CUT_PAYLOAD, _STOPPED) for s in _ROUTES},
        S.ESTOP: _stay(S.ESTOP, Do.CUT_PAYLOAD, _STOPPED),
    },
    Trigger.HALT: {
        S.IDLE: _stay(S.IDLE, _STOPPED),
        S.MANUAL: _to(S.IDLE, Do.DROP_TELEOP, _STOPPED),
        **{s: _to(S.IDLE, Cancel("stop", "stopped by {sender}"), _STOPPED) for s in _ROUTES},
        S.ESTOP: _stay(S.ESTOP, _STOPPED),
    },
    Trigger.ESTOP: {
        S.IDLE: _to(S.ESTOP, Do.CUT_PAYLOAD, _LATCH),
        S.MANUAL: _to(S.ESTOP, Do.DROP_TELEOP, Do.CUT_PAYLOAD, _LATCH),
        **{s: _to(S.ESTOP, Cancel("estop", "cancelled by e-stop"), Do.CUT_PAYLOAD, _LATCH) for s in _ROUTES},
        S.ESTOP: Refused(CommandStatus.DUPLICATE, "e-stop already latched"),
    },
    # Released is not moving: nothing resumes by itself.
    Trigger.ESTOP_RELEASE: {
        **{s: _no("e-stop is not latched") for s in _NOT_ESTOP},
        S.ESTOP: _to(S.IDLE, Announce(EventKind.ESTOP_RELEASED, "estop_release", "e-stop released by {sender}")),
    },
    Trigger.PAYLOAD_ON: {
        **{s: _stay(s, Do.PASS_PAYLOAD) for s in _NOT_ESTOP},
        S.ESTOP: _LATCHED,
    },
    # Turning things off is always allowed.
    Trigger.PAYLOAD_OFF: {s: _stay(s, Do.PASS_PAYLOAD) for s in _ALL},
    Trigger.TELEOP_LAPSED: {
        **{s: _no("no teleop command to lapse") for s in _ALL if s is not S.MANUAL},
        # The payload goes off only if the lapsed command was moving the robot (the pilot checks):
        # a zero twist running out is an operator who stopped driving, not a lost link.
        S.MANUAL: _to(
            S.IDLE,
            Announce(EventKind.DEADMAN_STOP, "deadman", "no teleop command from {sender} for {ttl:.2f} s: stopped"),
            Do.CUT_PAYLOAD,
            Do.DROP_TELEOP,
        ),
    },
    Trigger.ROUTE_ENDED: {
        **{s: _no("no go-to under way") for s in _ALL if not s.driving_route},
        S.GOTO: _to(S.IDLE, Do.END_ROUTE),
        S.HOMING: _to(S.IDLE, Do.END_ROUTE),
    },
    # The guard stops the robot on a cliff or a bump in every state; a go-to under way also ends
    # (a paused one stays paused: it was not moving).
    Trigger.HAZARD: {
        **{s: _stay(s) for s in _ALL if not s.driving_route},
        S.GOTO: _to(S.IDLE, Do.END_ROUTE),
        S.HOMING: _to(S.IDLE, Do.END_ROUTE),
    },
}


def _total(rows: Mapping[Trigger, Mapping[PilotState, Outcome]]) -> dict[tuple[PilotState, Trigger], Outcome]:
    table = {(s, t): row[s] for t, row in rows.items() for s in row}
    missing = [f"{s.value} x {t.value}" for t in Trigger for s in PilotState if (s, t) not in table]
    if missing:
        raise AssertionError(f"pilot transition table has no outcome for: {', '.join(missing)}")
    return table


TRANSITIONS: Final[Mapping[tuple[PilotState, Trigger], Outcome]] = _total(_ROWS)


def next_state(state: PilotState, trigger: Trigger) -> Outcome:
    return TRANSITIONS[(state, trigger)]
