"""Scenario files: which plan, which robots where, how noisy, which seed, how long, and what happens.

A scenario is TOML (docs/field-scenarios.md), declared here as dataclasses and read by the one
configuration mechanism (``shared/config.py``): ``load_scenario`` validates it and reports problems
with the file, the dotted key and the reason; nothing is half-loaded.

Events are a small family of frozen dataclasses told apart by ``kind``: world events the field
applies itself (doors, obstacles, board link cuts, wheel slip, the home button) and operator
commands (teleop bursts, goals, instant actions, marks) and network link cuts that a run hands to
its operator side (``field/events.py``).
"""

from __future__ import annotations

import math
import typing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import numpy as np
import numpy.typing as npt

from fleetlink.shared.config import ConfigError, Invalid, Setting, parse, read_toml
from fleetlink.shared.messages import MAX_MARK_LABEL, ActionType

__all__ = [
    "COMMAND_KINDS",
    "DRIVES",
    "EVENT_KINDS",
    "TELEOP_PERIOD_S",
    "ActionOrder",
    "AgentRestart",
    "Casualty",
    "DoorClose",
    "DoorOpen",
    "Event",
    "GoalOrder",
    "LidarSettings",
    "LinkCut",
    "LinkState",
    "MarkPlaced",
    "Noise",
    "Obstacle",
    "PressHome",
    "RobotSpec",
    "Scenario",
    "ScenarioError",
    "TeleopBurst",
    "WheelSlip",
    "load_scenario",
    "parse_scenario",
    "site_geometry",
]

SCENARIOS_DIR = Path(__file__).resolve().parent / "scenarios"

Drive = Literal["wander", "script", "idle", "agent"]
DRIVES: tuple[str, ...] = typing.get_args(Drive)
"""wander | script | idle: stand-in drivers; agent: a real agent drives the robot (lockstep runs)."""

TELEOP_PERIOD_S = 0.25
"""A teleop burst is one Teleop message every this many seconds for its duration."""


class ScenarioError(ConfigError):
    """A scenario file that cannot be used, with the place and the reason."""


def _sd(doc: str) -> Setting:
    return Setting(lo=0.0, doc=doc)


@dataclass(frozen=True, slots=True)
class Noise:
    wheel_scale_sd: Annotated[float, _sd("sd of each wheel's true/nominal radius ratio, drawn once per robot")] = 0.01
    gyro_bias_sd: Annotated[float, _sd("rad/s, drawn once per robot")] = 0.002
    gyro_noise_sd: Annotated[float, _sd("rad/s per control tick")] = 0.005
    ultrasonic_sd: Annotated[float, _sd("m")] = 0.005
    lidar_range_sd: Annotated[float, _sd("m")] = 0.01
    lidar_dropout: Annotated[
        float, Setting(lo=0.0, hi=1.0, what="a probability (0-1)", doc="probability a lidar sample returns nothing")
    ] = 0.01
    uwb_range_sd: Annotated[float, _sd("m (for the positioning system)")] = 0.10

    @classmethod
    def none(cls) -> Noise:
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class LidarSettings:
    enabled: bool = True
    rate_hz: Annotated[float, Setting(lo=1.0, hi=20.0, doc="revolutions per second")] = 10.0
    samples_per_second: Annotated[float, Setting(lo=100.0, hi=32000.0, doc="measurements a second")] = 8000.0
    """Measurements a second (the RPLIDAR A1's 8000); a turn has ``samples_per_second / rate_hz``."""
    motor: Annotated[
        Literal["auto", "running", "stopped"],
        Setting(doc="the simulated RPLIDAR's motor at start: auto = running when served over TCP or a pty (no DTR)"),
    ] = "auto"
    """The simulated A1's motor when it starts (``field.rplidar.motor_at_start``): ``auto`` runs it
    when the unit is served over TCP or a pty, where no DTR line reaches it (SLAMTEC's SDK starts an
    A1's motor only by DTR), and leaves it to the master's DTR in process; ``running`` / ``stopped``
    force it. SET_MOTOR_PWM 0 stops it and a PWM above 0 starts it either way."""


def _pose_from_degrees(p: tuple[float, float, float]) -> tuple[float, float, float]:
    return (p[0], p[1], math.radians(p[2]))


Name = Annotated[str, Setting(min_len=1)]
ScriptRow = Annotated[tuple[float, float, float], Setting(what="[t_s, v_m_per_s, omega_rad_per_s]")]
Point = Annotated[tuple[float, float], Setting(what="[x, y]")]


@dataclass(frozen=True, slots=True)
class RobotSpec:
    name: Name
    pose: Annotated[
        tuple[float, float, float] | None,
        Setting(what="[x_m, y_m, theta_deg]", convert=_pose_from_degrees, doc="x m, y m, heading in degrees"),
    ] = None  # x, y, theta (rad); None: use ``start``
    start: Annotated[str | None, Setting(min_len=1, doc="a named start pose of the plan")] = None
    drive: Annotated[Drive, Setting(doc="wander | script | idle (stand-ins) | agent (a real agent)")] = "wander"
    script: tuple[ScriptRow, ...] = ()  # (t_s, v m/s, omega rad/s), held until the next
    speed: Annotated[float, Setting(lo=0.0, hi=1.0, doc="cruise speed for wander, m/s")] = 0.25
    wheel_track: Annotated[float, Setting(lo=0.05, hi=1.0, doc="m")] = 0.22
    lidar: bool = True

    def validate(self) -> None:
        if (self.pose is None) == (self.start is None):
            raise Invalid("", "give exactly one of start (a named start of the plan) or pose")
        for j in range(1, len(self.script)):
            if self.script[j][0] < self.script[j - 1][0]:
                raise Invalid(f"script[{j}]", "times must not go backwards")
        if self.drive == "script" and not self.script:
            raise Invalid("script", 'drive = "script" needs a script')


@dataclass(frozen=True, slots=True)
class AnchorSpec:
    id: Name
    x: float
    y: float
    z: Annotated[float, Setting(doc="m above the floor")] = 2.4


def _anchor_rows(anchors: tuple[AnchorSpec, ...]) -> tuple[tuple[str, float, float, float], ...]:
    return tuple((a.id, a.x, a.y, a.z) for a in anchors)


# -- events ----------------------------------------------------------------------------------------

At = Annotated[float, Setting(key="at_s", lo=0.0, doc="s from the start")]
Seconds = Annotated[float, Setting(key="duration_s", lo=0.0, doc="s")]


@dataclass(frozen=True, slots=True)
class DoorClose:
    kind: ClassVar[str] = "door_close"
    at: At
    door: Name

    def describe(self) -> str:
        return f"t={self.at:g} s: door {self.door} closes"


@dataclass(frozen=True, slots=True)
class DoorOpen:
    kind: ClassVar[str] = "door_open"
    at: At
    door: Name

    def describe(self) -> str:
        return f"t={self.at:g} s: door {self.door} opens"


@dataclass(frozen=True, slots=True)
class Obstacle:
    kind: ClassVar[str] = "obstacle"
    at: At
    polygon: Annotated[tuple[Point, ...], Setting(min_len=3, what="at least 3 [x, y] points")]

    def describe(self) -> str:
        return f"t={self.at:g} s: an obstacle appears ({len(self.polygon)} corners)"


@dataclass(frozen=True, slots=True)
class LinkCut:
    """The robot's board link is cut, and restored ``duration`` later."""

    kind: ClassVar[str] = "link_cut"
    at: At
    robot: Name
    duration: Seconds = 3.0

    def describe(self) -> str:
        return f"t={self.at:g} s: board link of {self.robot} cut for {self.duration:g} s"


@dataclass(frozen=True, slots=True)
class WheelSlip:
    kind: ClassVar[str] = "wheel_slip"
    at: At
    robot: Name
    duration: Seconds = 3.0
    wheel: Literal["left", "right"] = "left"
    fraction: Annotated[float, Setting(lo=0.0, hi=1.0, doc="share of the wheel's turn lost")] = 0.5

    def describe(self) -> str:
        return f"t={self.at:g} s: {self.wheel} wheel of {self.robot} slips {self.fraction:.0%} for {self.duration:g} s"


@dataclass(frozen=True, slots=True)
class PressHome:
    kind: ClassVar[str] = "press_home"
    at: At
    robot: Name

    def describe(self) -> str:
        return f"t={self.at:g} s: someone presses the home button on {self.robot}"


@dataclass(frozen=True, slots=True)
class TeleopBurst:
    """An operator drives ``robot`` at (v, omega): one Teleop every ``TELEOP_PERIOD_S`` for ``duration``."""

    kind: ClassVar[str] = "teleop"
    at: At
    robot: Name
    duration: Annotated[float, Setting(key="duration_s", lo=0.0, required=True, doc="s")]
    v: Annotated[float, Setting(lo=-5.0, hi=5.0, doc="m/s, forward")] = 0.0
    omega: Annotated[float, Setting(lo=-20.0, hi=20.0, doc="rad/s, counter-clockwise")] = 0.0

    def describe(self) -> str:
        return f"t={self.at:g} s: operator drives {self.robot} at {self.v:g} m/s, {self.omega:g} rad/s for {self.duration:g} s"


def _radians(deg: float) -> float:
    return math.radians(deg)


@dataclass(frozen=True, slots=True)
class GoalOrder:
    """An operator sends ``robot`` to (x, y), facing ``theta`` (radians; None: any heading)."""

    kind: ClassVar[str] = "goal"
    at: At
    robot: Name
    x: Annotated[float, Setting(doc="m, map frame")]
    y: Annotated[float, Setting(doc="m, map frame")]
    theta: Annotated[float | None, Setting(key="theta_deg", convert=_radians, doc="final heading, degrees")] = None

    def describe(self) -> str:
        facing = "" if self.theta is None else f" facing {math.degrees(self.theta):g} deg"
        return f"t={self.at:g} s: operator sends {self.robot} to ({self.x:g}, {self.y:g}){facing}"


Action = Literal["stop", "pause", "resume", "cancel", "estop", "estop_release", "return_home"]
_ACTION_TYPES = {
    "stop": ActionType.STOP,
    "pause": ActionType.PAUSE,
    "resume": ActionType.RESUME,
    "cancel": ActionType.CANCEL,
    "estop": ActionType.ESTOP,
    "estop_release": ActionType.ESTOP_RELEASE,
    "return_home": ActionType.RETURN_HOME,
}


@dataclass(frozen=True, slots=True)
class ActionOrder:
    """An operator's instant action to ``robot``."""

    kind: ClassVar[str] = "action"
    at: At
    robot: Name
    action: Action

    @property
    def action_type(self) -> ActionType:
        """The wire contract's name for it (``estop_release`` is ``estopRelease``)."""
        return _ACTION_TYPES[self.action]

    def describe(self) -> str:
        return f"t={self.at:g} s: operator sends {self.action} to {self.robot}"


@dataclass(frozen=True, slots=True)
class MarkPlaced:
    """An operator marks a point of interest (``mark_kind``: casualty, hazard, note, ...)."""

    kind: ClassVar[str] = "mark"
    at: At
    x: Annotated[float, Setting(doc="m, map frame")]
    y: Annotated[float, Setting(doc="m, map frame")]
    mark_kind: Annotated[str, Setting(min_len=1, max_len=32, doc="casualty, hazard, note, ...")] = "casualty"
    label: Annotated[str, Setting(max_len=MAX_MARK_LABEL)] = ""
    robot: Annotated[str | None, Setting(min_len=1, doc="the robot the operator works with")] = None

    def describe(self) -> str:
        label = f" {self.label!r}" if self.label else ""
        return f"t={self.at:g} s: operator marks a {self.mark_kind}{label} at ({self.x:g}, {self.y:g})"


@dataclass(frozen=True, slots=True)
class LinkState:
    """One of ``robot``'s links goes down (``cut``) or comes back (``restore``).

    ``board`` is the robot's control-board link (as ``link_cut``, without the automatic restore);
    ``zenoh``, ``mqtt`` and ``lidar`` are for the run's link layer to cut.
    """

    kind: ClassVar[str] = "link"
    at: At
    robot: Name
    link: Literal["zenoh", "mqtt", "board", "lidar"]
    state: Literal["cut", "restore"]

    def describe(self) -> str:
        return f"t={self.at:g} s: {self.link} link of {self.robot} {'cut' if self.state == 'cut' else 'restored'}"


@dataclass(frozen=True, slots=True)
class AgentRestart:
    """``robot``'s agent process stops and starts again, as systemd restarts one that crashed: what it
    held in memory is lost, and its map begins again where the robot stands (without UWB, in a new
    frame). A lockstep run carries it out (``MissionRun.restart_agent``)."""

    kind: ClassVar[str] = "agent_restart"
    at: At
    robot: Name

    def describe(self) -> str:
        return f"t={self.at:g} s: {self.robot}'s agent restarts"


Event = (
    DoorClose
    | DoorOpen
    | Obstacle
    | LinkCut
    | WheelSlip
    | PressHome
    | TeleopBurst
    | GoalOrder
    | ActionOrder
    | MarkPlaced
    | LinkState
    | AgentRestart
)
EVENT_KINDS: tuple[str, ...] = tuple(c.kind for c in typing.get_args(Event))
COMMAND_KINDS = ("teleop", "goal", "action", "mark")
"""Operator commands: a run hands them to its operator side (``EventRunner(on_command=...)``)."""


# -- the file --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Casualty:
    """Someone lying in the building (``[[casualties]]``): ground truth that a run's operator looks
    for and that its marks are scored against (site/sortie.py). Not a body in the world: the robots'
    sensors do not see it, only the operator's camera does."""

    name: Name
    x: Annotated[float, Setting(doc="m, plan frame")]
    y: Annotated[float, Setting(doc="m, plan frame")]
    label: Annotated[str, Setting(max_len=MAX_MARK_LABEL, doc="what the operator writes on the mark")] = ""


@dataclass(frozen=True, slots=True)
class Scenario:
    name: str
    plan: Annotated[str, Setting(min_len=1, required=True, doc="a built-in plan name, or a path")]
    seed: Annotated[int, Setting(lo=0, hi=2**63 - 1, doc="every random draw derives from it")] = 0
    duration: Annotated[float, Setting(key="duration_s", lo=0.0, doc="s")] = 60.0
    robots: Annotated[tuple[RobotSpec, ...], Setting(min_len=1, required=True)] = ()
    anchors: Annotated[
        tuple[tuple[str, float, float, float], ...],
        Setting(read_as=tuple[AnchorSpec, ...], convert=_anchor_rows, doc="replaces the plan's UWB anchors"),
    ] = ()  # (id, x, y, z); overrides the plan's when given
    uwb: Annotated[
        bool,
        Setting(
            doc="false: the site's UWB system is off (no fixes): robots map and localise in their own maps' frames"
        ),
    ] = True
    noise: Noise = field(default_factory=Noise)
    lidar: LidarSettings = field(default_factory=LidarSettings)
    events: tuple[Event, ...] = ()
    casualties: tuple[Casualty, ...] = ()
    truth_rate_hz: Annotated[float, Setting(lo=0.1, hi=1000.0, doc="ground-truth samples a second")] = 20.0
    control_period: Annotated[float, Setting(key="control_period_s", lo=0.001, hi=0.05, doc="physics sub-step, s")] = (
        0.01
    )
    description: str = ""
    source: Annotated[str, Setting(read=False)] = "<memory>"

    def uwb_anchors(
        self, plan_anchors: typing.Iterable[tuple[str, float, float, float]]
    ) -> tuple[tuple[str, float, float, float], ...]:
        """The anchors the field's UWB system ranges from: the scenario's, else its plan's (``plan_anchors``);
        none when ``uwb`` is off. The field runs no UWB with fewer than three."""
        if not self.uwb:
            return ()
        return self.anchors or tuple((a[0], float(a[1]), float(a[2]), float(a[3])) for a in plan_anchors)

    def validate(self) -> None:
        names: set[str] = set()
        for i, rb in enumerate(self.robots):
            if rb.name in names:
                raise Invalid(f"robots[{i}].name", f"robot {rb.name!r} appears twice")
            names.add(rb.name)
        for i, a in enumerate(self.anchors):
            if any(b[0] == a[0] for b in self.anchors[:i]):
                raise Invalid(f"anchors[{i}].id", f"anchor {a[0]!r} appears twice")
        for i, c in enumerate(self.casualties):
            if any(b.name == c.name for b in self.casualties[:i]):
                raise Invalid(f"casualties[{i}].name", f"casualty {c.name!r} appears twice")
        for i, ev in enumerate(self.events):
            robot = getattr(ev, "robot", None)
            if robot is not None and robot not in names:
                raise Invalid(f"events[{i}].robot", f"no robot named {robot!r} in this scenario")


def load_scenario(path: str | Path) -> Scenario:
    p = Path(path)
    scenario = parse_scenario(read_toml(p, ScenarioError), source=str(p))
    plan = scenario.plan
    if ("/" in plan or plan.endswith((".toml", ".yaml", ".yml"))) and not Path(plan).is_absolute():
        plan = str((p.parent / plan).resolve())
    return replace(scenario, plan=plan)


def parse_scenario(data: typing.Mapping[str, typing.Any], source: str = "<memory>") -> Scenario:
    """A scenario from decoded TOML; ``ScenarioError`` naming ``source``, the key and the problem.

    ``name`` defaults to the file's stem; events come out sorted by time (stable).
    """
    sc = parse({"name": "", **data}, Scenario, source=source, error=ScenarioError)
    return replace(
        sc,
        name=sc.name or Path(source).stem,
        events=tuple(sorted(sc.events, key=lambda e: e.at)),
        source=source,
    )


def _resolve(name: str, base: Path | None, builtin_dir: Path | None = None) -> str | Path:
    """A built-in name stays a name (plans) or maps into ``builtin_dir``; a path is made absolute."""
    if builtin_dir is not None and "/" not in name and not name.endswith(".toml"):
        return builtin_dir / f"{name}.toml"
    if "/" in name or name.endswith((".toml", ".yaml", ".yml")):
        p = Path(name)
        return p if p.is_absolute() or base is None else (base / p).resolve()
    return name


AnchorRow = tuple[str, float, float, float]


def site_geometry(
    plan: str | None, scenario: str | None, base: Path | None = None
) -> tuple[tuple[AnchorRow, ...], npt.NDArray[np.float64] | None]:
    """Anchors and walls for a UWB gateway whose uwb.toml names a ``plan`` and/or a ``scenario``
    (built-in names or paths relative to ``base``): the scenario's anchors, else the plan's; the
    plan (``plan`` if given, else the scenario's) gives the walls. ValueError when either fails to load.

    It is ``positioning.config.SiteLoader``: positioning does not read field files itself.
    """
    from fleetlink.field.plans import load_plan

    anchors: tuple[AnchorRow, ...] = ()
    floor = None
    if scenario is not None:
        sc = load_scenario(_resolve(scenario, base, SCENARIOS_DIR))
        floor = load_plan(sc.plan)
        anchors = sc.anchors
    if plan is not None:
        floor = load_plan(_resolve(plan, base))
    if floor is None:
        return anchors, None
    if not anchors:
        anchors = tuple((a.id, a.x, a.y, a.z) for a in floor.anchors)
    return anchors, floor.segments()
