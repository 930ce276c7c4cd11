"""The console's typed commands (what follows ':'), parsed. Pure: text in, a command value out.

    goal X Y [THETA_DEG]     send the selected robot to (X, Y) m, facing THETA degrees if given
    mark KIND X Y [LABEL]    place a mark (casualty, hazard, note, ...) at (X, Y) m
    mark here [KIND] [LABEL] place a mark at the selected robot's fused pose (kind casualty if none)
    mark edit ID [KIND] [LABEL]   change a mark's kind and/or label (ID: the id or its tail, "3")
    mark rm ID, unmark ID    remove a mark
    marks                    list the marks in the notices
    marks export PATH        write the marks to PATH (.csv or .geojson, site frame)
    home                     return home
    home set | home X Y      the selected robot's home: where it stands, or at (X, Y) m
    estop [all]              latch the e-stop on the selected robot (or on every robot)
    release                  release the selected robot's e-stop (asks for a confirmation)
    policy stop|retrace|home what the selected robot does when it loses contact
    payload on|off           switch the UV lamp
    payload uv|atomiser|fan on|off|LEVEL   one payload; the atomiser and the fan take a level 0-3
    ack [ROBOT] [KIND|all]   acknowledge alarms: the robot's (default: the selected one's) most
                             severe unacknowledged alarm, the one of KIND, or all of them
    stop                     stop every robot
    zone add NAME X1 Y1 X2 Y2 X3 Y3 ...   a people-present zone: no robot's UV lamp may reach into it
    zone rm NAME, zones      remove one; list them
    dose [X1 Y1 X2 Y2] [target D]   the fleet's UV dose: area at the target (the robots', or D
                             mJ/cm²), below it, and where (on the robots' mapped floor, or within the rectangle)
    dose save DIR [X1 Y1 X2 Y2]   the dose report files into DIR (docs/payload.md, "Dose layer")
    disinfect room X Y | rect X0 Y0 X1 Y1 | poly X1 Y1 X2 Y2 X3 Y3 ... [dose MJ_CM2] [with ROBOT,ROBOT]
                             a UV round of an area (the target dose in mJ/cm², default the console's)
                             by the selected robot, or shared between the robots named
    sweep room X Y | rect X0 Y0 X1 Y1 | poly X1 Y1 ... [with ROBOT]   a sweeping round
    pause, resume, cancel    the selected robot's round (or goal): hold it, carry on, end it
    seek S | seek +S | seek -S   a replay (``fleetlink replay``): jump to S seconds after the
                             recording's start, or S seconds on, or S seconds back
    speed X                  a replay: play at X times real time from now on

``parse_command(line)`` gives one of the command classes below, ``None`` for a blank line, or a
``CommandError`` whose ``text`` is the notice to show. Nothing here sends anything: the app does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fleetlink.operator.alarms import KINDS, AlarmKind, parse_kind
from fleetlink.operator.marks import DEFAULT_KIND, MARK_KINDS, MAX_KIND, MAX_LABEL
from fleetlink.operator.rounds import MAX_AREA_CORNERS, AreaSpec, PolyArea, RectArea, RoomArea
from fleetlink.shared.keys import is_valid_id

__all__ = [
    "USAGE",
    "AckAlarm",
    "Command",
    "CommandError",
    "CommsPolicySet",
    "Dose",
    "DoseSave",
    "EStop",
    "EStopRelease",
    "Goal",
    "Home",
    "HomeSet",
    "MarkAt",
    "MarkEdit",
    "MarkHere",
    "MarkRemove",
    "MarksExport",
    "MarksList",
    "Payload",
    "RoundAction",
    "Seek",
    "Speed",
    "StartRound",
    "StopAll",
    "ZoneAdd",
    "ZoneRemove",
    "ZonesList",
    "parse_command",
]

USAGE = "goal X Y [THETA_DEG] | mark KIND X Y [LABEL] | mark here|edit|rm ... | marks [export PATH] | home [set|X Y] | estop [all] | release | policy stop|retrace|home | payload [uv|atomiser|fan] on|off|LEVEL | disinfect|sweep room|rect|poly ... | pause | resume | cancel | stop | ack [ROBOT] [KIND|all] | dose [save DIR] [X1 Y1 X2 Y2] | seek [+|-]S | speed X (a replay)"
POLICIES = ("stop", "retrace", "home")
PAYLOAD_DEVICES = ("uv", "atomiser", "fan")
MARK_USAGE = "mark KIND X Y [LABEL] | mark here [KIND] [LABEL] | mark edit ID [KIND] [LABEL] | mark rm ID"
ROUND_USAGE = {
    "disinfect": "disinfect room X Y | rect X0 Y0 X1 Y1 | poly X1 Y1 X2 Y2 X3 Y3 ... [dose MJ_CM2] [with ROBOT,ROBOT]",
    "sweep": "sweep room X Y | rect X0 Y0 X1 Y1 | poly X1 Y1 X2 Y2 X3 Y3 ... [with ROBOT]",
}
ROUND_ACTIONS = ("pause", "resume", "cancel")


@dataclass(frozen=True, slots=True)
class Goal:
    x: float
    y: float
    theta: float | None
    """Radians in (-pi, pi], or None: the robot keeps the heading it arrives with."""


@dataclass(frozen=True, slots=True)
class MarkAt:
    kind: str
    x: float
    y: float
    label: str
    """The rest of the line, spaces kept as single spaces; '' when none was typed."""


@dataclass(frozen=True, slots=True)
class MarkHere:
    """A mark at the selected robot's current fused pose."""

    kind: str
    label: str


@dataclass(frozen=True, slots=True)
class MarkEdit:
    ref: str
    """The mark's id, or a unique tail of it after a '-'."""
    kind: str | None
    label: str | None
    """None: unchanged."""


@dataclass(frozen=True, slots=True)
class MarkRemove:
    ref: str


@dataclass(frozen=True, slots=True)
class MarksList:
    pass


@dataclass(frozen=True, slots=True)
class MarksExport:
    path: str


@dataclass(frozen=True, slots=True)
class Home:
    pass


@dataclass(frozen=True, slots=True)
class HomeSet:
    at: tuple[float, float] | None
    """None: where the robot stands."""


@dataclass(frozen=True, slots=True)
class EStop:
    every_robot: bool


@dataclass(frozen=True, slots=True)
class EStopRelease:
    pass


@dataclass(frozen=True, slots=True)
class CommsPolicySet:
    policy: str


@dataclass(frozen=True, slots=True)
class Payload:
    on: bool
    device: str = "uv"
    """uv (the lamp), atomiser or fan."""
    level: int | None = None
    """0-3 for the atomiser and the fan (None: on is level 1)."""


@dataclass(frozen=True, slots=True)
class StopAll:
    pass


@dataclass(frozen=True, slots=True)
class StartRound:
    """A UV round (``uv``) or a sweep of ``area`` by ``robots`` (empty: the selected robot)."""

    kind: str
    """uv or sweep."""
    area: AreaSpec
    target_mj_cm2: float | None = None
    """The target dose (UV), mJ/cm²; None: the console's default."""
    robots: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class RoundAction:
    """pause, resume or cancel the selected robot's round (instant actions)."""

    action: str


@dataclass(frozen=True, slots=True)
class Seek:
    """A replay jumps to ``seconds`` after the recording's start, or ``seconds`` on from where it
    plays (``relative``; back if negative)."""

    seconds: float
    relative: bool


@dataclass(frozen=True, slots=True)
class Speed:
    """A replay plays at ``factor`` times real time from now on."""

    factor: float


MAX_SPEED = 1000.0
"""The fastest replay ``speed`` takes (a day's recording in a minute and a half)."""


@dataclass(frozen=True, slots=True)
class ZoneAdd:
    """A people-present zone (no UV light may reach into it), sent to every robot."""

    name: str
    corners: tuple[tuple[float, float], ...]


@dataclass(frozen=True, slots=True)
class ZoneRemove:
    name: str


@dataclass(frozen=True, slots=True)
class ZonesList:
    pass


@dataclass(frozen=True, slots=True)
class Dose:
    """Summarise the fleet's dose layer on the mapped floor (or within ``box``: x1, y1, x2, y2)."""

    box: tuple[float, float, float, float] | None = None
    target_mj_cm2: float | None = None
    """Judge against this dose (``target D``, mJ/cm², as ``:disinfect ... dose D``) instead of the
    robots' configured target: the check after a round run at its own dose."""


@dataclass(frozen=True, slots=True)
class DoseSave:
    """Write the dose report files into folder ``path``."""

    path: str
    box: tuple[float, float, float, float] | None = None
    target_mj_cm2: float | None = None


@dataclass(frozen=True, slots=True)
class AckAlarm:
    """Acknowledge alarms on ``robot`` (None: the selected robot): the one of ``kind``, or (None)
    the most severe unacknowledged one, or with ``every`` all of them."""

    robot: str | None
    kind: AlarmKind | None
    every: bool = False


Command = (
    ZoneAdd
    | ZoneRemove
    | ZonesList
    | Goal
    | MarkAt
    | MarkHere
    | MarkEdit
    | MarkRemove
    | MarksList
    | MarksExport
    | Home
    | HomeSet
    | EStop
    | EStopRelease
    | CommsPolicySet
    | Payload
    | StartRound
    | RoundAction
    | StopAll
    | AckAlarm
    | Dose
    | DoseSave
    | Seek
    | Speed
)


@dataclass(frozen=True, slots=True)
class CommandError:
    """A line that is not a command: ``text`` says why (shown as a warning notice)."""

    line: str
    text: str


def _numbers(line: str, words: list[str]) -> list[float] | CommandError:
    try:
        values = [float(w) for w in words]
    except ValueError as exc:  # float's own message names the word: "could not convert ... 'x'"
        return CommandError(line, f"bad command {line!r}: {exc}")
    if not all(math.isfinite(v) for v in values):
        return CommandError(line, f"bad command {line!r}: coordinates must be finite numbers")
    return values


def parse_command(line: str) -> Command | CommandError | None:
    """The command on ``line``; None if it is blank. The verb is case-insensitive, ``g`` is goal."""
    words = line.split()
    if not words:
        return None
    verb, args = words[0].lower(), words[1:]
    if verb in ("goal", "g") and len(args) in (2, 3):
        nums = _numbers(line, args)
        if isinstance(nums, CommandError):
            return nums
        theta = None
        if len(nums) == 3:
            theta = math.radians(nums[2])
            theta = math.atan2(math.sin(theta), math.cos(theta))
        return Goal(nums[0], nums[1], theta)
    if verb == "mark" and args and args[0].lower() in ("here", "edit", "rm"):
        return _mark_verb(line, args[0].lower(), args[1:])
    if verb == "unmark" and len(args) == 1:
        return MarkRemove(args[0])
    if verb == "mark" and len(args) >= 3:
        nums = _numbers(line, args[1:3])
        if isinstance(nums, CommandError):
            return nums
        return _checked(line, MarkAt(args[0], nums[0], nums[1], " ".join(args[3:])))
    if verb == "marks" and not args:
        return MarksList()
    if verb == "marks" and len(args) == 2 and args[0].lower() == "export":
        return MarksExport(args[1])
    if verb == "home" and not args:
        return Home()
    if verb == "home" and args == ["set"]:
        return HomeSet(None)
    if verb == "home" and len(args) == 2:
        nums = _numbers(line, args)
        if isinstance(nums, CommandError):
            return nums
        return HomeSet((nums[0], nums[1]))
    if verb in ("estop", "e-stop") and args in ([], ["all"]):
        return EStop(every_robot=bool(args))
    if verb == "release" and not args:
        return EStopRelease()
    if verb == "policy" and len(args) == 1 and args[0].lower() in POLICIES:
        return CommsPolicySet(args[0].lower())
    if verb == "payload" and args in (["on"], ["off"]):
        return Payload(args[0] == "on")
    if verb == "payload" and len(args) == 2 and args[0].lower() in PAYLOAD_DEVICES:
        device, what = args[0].lower(), args[1].lower()
        if what in ("on", "off"):
            return Payload(what == "on", device)
        if device != "uv" and what in ("0", "1", "2", "3"):
            return Payload(what != "0", device, int(what))
        return CommandError(
            line,
            f"bad command {line!r}: payload {device} takes on, off" + (", or a level 0-3" if device != "uv" else ""),
        )
    if verb == "stop" and not args:
        return StopAll()
    if verb in ("disinfect", "sweep"):
        return _round(line, verb, args)
    if verb in ROUND_ACTIONS and not args:
        return RoundAction(verb)
    if verb == "zones" and not args:
        return ZonesList()
    if verb == "zone" and len(args) == 2 and args[0].lower() in ("rm", "remove"):
        return ZoneRemove(args[1])
    if verb == "zone" and len(args) >= 2 and args[0].lower() == "add":
        name, numbers = args[1], args[2:]
        if len(numbers) < 6 or len(numbers) % 2 or len(numbers) > 64:
            return CommandError(line, f"bad command {line!r}: zone add NAME X1 Y1 X2 Y2 X3 Y3 ... (3 to 32 corners)")
        if len(name) > 32:
            return CommandError(line, f"bad command {line!r}: a zone's name is at most 32 characters")
        nums = _numbers(line, numbers)
        if isinstance(nums, CommandError):
            return nums
        return ZoneAdd(name, tuple(zip(nums[0::2], nums[1::2], strict=True)))
    if verb == "ack" and len(args) <= 2:
        return _ack(line, args)
    if verb == "dose":
        return _dose(line, args)
    if verb == "seek" and len(args) == 1:
        sign = args[0][:1] if args[0][:1] in ("+", "-") else ""
        number = args[0][len(sign) :]
        try:
            seconds = float(number) if number[:1] not in ("+", "-") else math.nan
        except ValueError:
            seconds = math.nan
        if not (math.isfinite(seconds) and seconds >= 0):  # (also "+-5", "--5", "nan", "inf")
            return CommandError(
                line, f"bad command {line!r}: seek S (from the start), +S (on) or -S (back), S >= 0 seconds"
            )
        return Seek(-seconds if sign == "-" else seconds, bool(sign))
    if verb == "speed" and len(args) == 1:
        nums = _numbers(line, args)
        if isinstance(nums, CommandError):
            return nums
        if not 0 < nums[0] <= MAX_SPEED:
            return CommandError(line, f"bad command {line!r}: speed X, 0 < X <= {MAX_SPEED:g} (times real time)")
        return Speed(nums[0])
    return CommandError(line, f"unknown command {line!r}: {USAGE}")


def _kind_and_label(words: list[str]) -> tuple[str | None, str]:
    """A known kind first (case-insensitive) is the kind; the rest is the label."""
    if words and words[0].lower() in MARK_KINDS:
        return words[0].lower(), " ".join(words[1:])
    return None, " ".join(words)


def _checked(line: str, cmd: MarkAt | MarkHere | MarkEdit) -> MarkAt | MarkHere | MarkEdit | CommandError:
    """Refuse a label or kind the wire would not carry, rather than cut it."""
    label = cmd.label or ""
    if len(label) > MAX_LABEL:
        return CommandError(line, f"mark refused: the label is {len(label)} characters, more than {MAX_LABEL}")
    kind = cmd.kind or ""
    if len(kind) > MAX_KIND:
        return CommandError(line, f"mark refused: the kind is {len(kind)} characters, more than {MAX_KIND}")
    return cmd


def _mark_verb(line: str, sub: str, words: list[str]) -> Command | CommandError:
    if sub == "here":
        kind, label = _kind_and_label(words)
        return _checked(line, MarkHere(kind or DEFAULT_KIND, label))
    if sub == "edit" and len(words) >= 2:
        kind, label = _kind_and_label(words[1:])
        return _checked(line, MarkEdit(words[0], kind, label or None))
    if sub == "rm" and len(words) == 1:
        return MarkRemove(words[0])
    return CommandError(line, f"bad command {line!r}: {MARK_USAGE}")


DOSE_USAGE = "dose [X1 Y1 X2 Y2] [target MJ_CM2] | dose save DIR [X1 Y1 X2 Y2] [target MJ_CM2]"


def _dose(line: str, args: list[str]) -> Dose | DoseSave | CommandError:
    path = None
    if args and args[0].lower() == "save":
        if len(args) < 2:
            return CommandError(line, f"bad command {line!r}: {DOSE_USAGE}")
        path, args = args[1], args[2:]
    target = None
    if len(args) >= 2 and args[-2].lower() == "target":
        value = _numbers(line, args[-1:])
        if isinstance(value, CommandError):
            return value
        if value[0] <= 0:
            return CommandError(line, f"bad command {line!r}: the target dose must be above 0 mJ/cm²")
        target, args = value[0], args[:-2]
    if len(args) not in (0, 4):
        return CommandError(line, f"bad command {line!r}: {DOSE_USAGE}")
    box = None
    if args:
        nums = _numbers(line, args)
        if isinstance(nums, CommandError):
            return nums
        if nums[0] == nums[2] or nums[1] == nums[3]:
            return CommandError(line, f"bad command {line!r}: the rectangle's corners must differ in x and in y")
        box = (nums[0], nums[1], nums[2], nums[3])
    return Dose(box, target) if path is None else DoseSave(path, box, target)


ACK_USAGE = "ack [ROBOT] [KIND|all], KIND one of " + ", ".join(k.value for k in KINDS)


def _ack(line: str, words: list[str]) -> AckAlarm | CommandError:
    every, kind = False, None
    if words and words[-1].lower() == "all":
        every, words = True, words[:-1]
    elif words and (kind := parse_kind(words[-1])) is not None:
        words = words[:-1]
    if len(words) > 1:
        return CommandError(line, f"unknown alarm kind {words[-1]!r}: {ACK_USAGE}")
    robot = words[0] if words else None
    if robot is not None and not is_valid_id(robot):
        return CommandError(line, f"bad command {line!r}: {robot!r} is neither a robot id nor an alarm kind")
    return AckAlarm(robot, kind, every)


AREA_SHAPES = {"room": "room", "rect": "rect", "rectangle": "rect", "poly": "poly", "polygon": "poly"}


def _round(line: str, verb: str, args: list[str]) -> StartRound | CommandError:
    """``disinfect|sweep SHAPE NUMBERS [dose MJ_CM2] [with ROBOT,ROBOT]`` (options in any order)."""
    usage = f"bad command {line!r}: {ROUND_USAGE[verb]}"
    if not args or args[0].lower() not in AREA_SHAPES:
        return CommandError(line, usage)
    shape, words = AREA_SHAPES[args[0].lower()], args[1:]
    numbers: list[str] = []
    dose: float | None = None
    robots: list[str] = []
    i = 0
    while i < len(words):
        word = words[i].lower()
        if word == "dose" and verb == "sweep":
            return CommandError(line, f"bad command {line!r}: a sweep takes no dose ({ROUND_USAGE[verb]})")
        if word == "dose" and dose is None and i + 1 < len(words):
            try:
                dose = float(words[i + 1])
            except ValueError:
                dose = math.nan
            if not (math.isfinite(dose) and dose > 0):
                return CommandError(
                    line,
                    f"bad command {line!r}: the dose must be a finite number > 0 mJ/cm² (10 mJ/cm² = 100 J/m²),"
                    f" got {words[i + 1]!r}",
                )
            i += 2
        elif word == "with" and not robots:
            j = i + 1
            while j < len(words) and words[j].lower() != "dose":
                j += 1
            robots = [r for r in ",".join(words[i + 1 : j]).split(",") if r]
            if not robots:
                return CommandError(line, usage)
            i = j
        elif not robots and dose is None:  # the area's numbers come first
            numbers.append(words[i])
            i += 1
        else:
            return CommandError(line, usage)
    for robot in robots:
        if not is_valid_id(robot):
            return CommandError(line, f"bad command {line!r}: {robot!r} is not a robot id")
    if len(set(robots)) != len(robots):
        return CommandError(line, f"bad command {line!r}: a robot is named twice")
    if verb == "sweep" and len(robots) > 1:
        return CommandError(line, f"bad command {line!r}: a sweep is for one robot")
    want = {"room": "2", "rect": "4", "poly": f"6 to {2 * MAX_AREA_CORNERS} (3 to {MAX_AREA_CORNERS} corners)"}
    count = len(numbers)
    ok = count == 2 if shape == "room" else count == 4 if shape == "rect" else 6 <= count <= 2 * MAX_AREA_CORNERS
    if not ok or (shape == "poly" and count % 2):
        return CommandError(line, f"bad command {line!r}: {shape} takes {want[shape]} numbers: {ROUND_USAGE[verb]}")
    nums = _numbers(line, numbers)
    if isinstance(nums, CommandError):
        return nums
    area: AreaSpec
    if shape == "room":
        area = RoomArea(nums[0], nums[1])
    elif shape == "rect":
        area = RectArea(nums[0], nums[1], nums[2], nums[3])
    else:
        area = PolyArea(tuple(zip(nums[0::2], nums[1::2], strict=True)))
    return StartRound("uv" if verb == "disinfect" else "sweep", area, dose, tuple(robots))
