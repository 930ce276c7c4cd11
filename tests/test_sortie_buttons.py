"""The robot's own buttons, end to end in lockstep (issue 15): the whole agent hears them through
Control Bus bytes from the simulated board. The home button brings a robot that was driven away
back to where it first localised; the e-stop button latches the e-stop (MANUAL) with every
payload off, an operator cannot release it while the button is pressed, and can once it is not."""

from __future__ import annotations

import math

from fleetlink.devices.controlbus import protocol as p
from fleetlink.field.scenario import LidarSettings, Noise, RobotSpec, Scenario
from fleetlink.shared.messages import Ack, AckResult, ActionType, EStop, HomeSource
from fleetlink.site.lockstep import MissionRun

START = (9.0, 5.0, 0.0)  # office room-1, facing east (the fused heading starts east too)


def test_the_home_button_and_the_estop_button_through_the_board() -> None:
    scenario = Scenario(
        name="buttons",
        plan="office",
        seed=5,
        duration=70.0,
        robots=(RobotSpec("r1", pose=START, drive="idle", lidar=False),),
        noise=Noise(wheel_scale_sd=0.0, gyro_bias_sd=0.0),
        lidar=LidarSettings(enabled=False),
    )
    with MissionRun(scenario, mapping=False, record=False) as run:
        board = run.field.rigs[0].robot.board
        core = run.robots[0].node.core
        op = run.operator
        seen: dict[str, object] = {}
        next_teleop = [3.0]

        def script(t: float) -> None:
            if 3.0 <= t < 6.0 and t >= next_teleop[0]:  # an operator drives it 0.9 m east
                op.teleop("r1", 0.3, 0.0)
                next_teleop[0] = t + 0.25
            if t >= 9.0 and "home" not in seen:
                seen["away"] = (board.state.x, board.state.y)
                seen["home"] = core.home.home
                board.press_home()
            if t >= 40.0 and "lamp" not in seen:
                seen["lamp"] = True
                board.state.uv_lamp = True  # the lamp is on when the button goes down
            if t >= 41.0 and "pressed" not in seen:
                seen["pressed"] = t
                board.press(p.Button.ESTOP)
            if t >= 44.0 and "refused" not in seen:
                seen["refused"] = t
                op.action("r1", ActionType.ESTOP_RELEASE, "release-1")
            if t >= 46.0 and "up" not in seen:
                seen["up"] = t
                board.release(p.Button.ESTOP)
            if t >= 48.0 and "released" not in seen:
                seen["released"] = (core.pilot.estop, core.estop_source)
                op.action("r1", ActionType.ESTOP_RELEASE, "release-2")

        run.field.controllers.append(script)
        result = run.run()
        home = seen["home"]
        assert home is not None and home.source is HomeSource.LOCALISED  # type: ignore[attr-defined]
        away = seen["away"]
        assert math.dist(away, START[:2]) > 0.6  # type: ignore[arg-type]
        kinds = [e.kind for e in result.events]
        assert "home_button" in kinds and "goal_reached" in kinds, kinds
        # Back where it first localised, and where it started (truth), before the e-stop.
        at = next(row for row in result.field.truth["r1"] if row[0] >= 40.0)
        assert math.dist((at[1], at[2]), (home.x, home.y)) < 0.2  # type: ignore[attr-defined]
        assert math.dist((at[1], at[2]), START[:2]) < 0.2
        # The e-stop button: latched as MANUAL, every payload off, release refused while pressed.
        assert seen["released"] == (True, EStop.MANUAL)
        assert not board.state.uv_lamp
        acks = {a.commandHeaderId: a for a in result.acks if isinstance(a, Ack) and a.commandTopic == "actions"}
        first, second = sorted(acks.values(), key=lambda a: a.commandHeaderId)[-2:]
        assert first.result is AckResult.REJECTED and "button" in first.reason
        assert second.result is AckResult.ACCEPTED
        assert not core.pilot.estop
        assert "estop_latched" in kinds and "estop_released" in kinds
