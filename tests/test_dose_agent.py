"""A real agent's dose layer over real Zenoh on loopback: the field's disinfection robot (its board and
lidar served on TCP like hardware, its agent as ``fleetlink field`` runs it) is placed by UWB fixes,
drives half a metre (the fusion finds its heading, the map restarts in the site frame), then stands
with the lamp on; the layer fetched from ``fleetlink/v1/uvc-1/dose`` has the lamp's dose where the
robot stands, as the board reported the lamp on, and stops growing when the lamp goes off."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import zenoh

from fleetlink.agent.dose_share import fetch_dose
from fleetlink.field.realtime import RealtimeField
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.dose_codec import SharedDose
from fleetlink.shared.messages import (
    Action,
    ActionType,
    DoseSnapshot,
    FixStatus,
    InstantActions,
    KeyValue,
    LeaseRequest,
    Teleop,
    UwbFix,
)
from fleetlink.site.agents import FIELD_LAMP, FieldAgents
from tests.harness import wait_until
from tests.harness.mosquitto import free_port
from tests.harness.zenoh_peers import zenoh_config
from tests.test_field_realtime import quiet_scenario

OP = "op-test"


@pytest.mark.slow
def test_a_field_agent_serves_its_dose_layer_over_zenoh() -> None:
    clock = SystemClock()
    field = RealtimeField(quiet_scenario(), clock=clock)  # uvc-1 in the apartment, its lidar at 10 Hz
    listen = f"tcp/127.0.0.1:{free_port()}"
    session: zenoh.Session | None = None
    asker: ZenohEndpoint | None = None
    agents: FieldAgents | None = None
    stop = threading.Event()
    fixer: threading.Thread | None = None
    try:
        endpoints = field.start()
        session = zenoh.open(zenoh_config(listen=[listen]))
        agents = FieldAgents(endpoints, clock=clock, zenoh_connect=[listen], operators=(OP,))
        agent = agents.start()["uvc-1"]
        assert agent.config.uv == FIELD_LAMP and agent.node.dose is not None
        robot = next(r for r in field.world.robots if r.name == "uvc-1")
        gw = wire.HeaderCounter(clock, robot="uvc-1", sender="uwb-gateway")
        op = wire.HeaderCounter(clock, robot="uvc-1", sender=OP)

        def put(topic: str, msg: wire.Message) -> None:
            assert session is not None
            key = keys.sender_key("uvc-1", topic, OP) if topic in keys.SENDER_TOPICS else keys.key("uvc-1", topic)
            session.put(key, wire.encode(msg))

        def fixes() -> None:  # the UWB gateway's part: the true position, 10 Hz, over Zenoh
            while not stop.wait(0.1):
                x, y, _ = robot.pose
                put("uwb", gw.make(
                    UwbFix, tag="uvc-1", x=x, y=y, z=0.3, sd_x=0.03, sd_y=0.03, quality=90, status=FixStatus.OK,
                    anchors=("a1", "a2", "a3"), residual_rms_m=0.02, measured_at=clock.wall(),
                ))  # fmt: skip

        fixer = threading.Thread(target=fixes, daemon=True)
        fixer.start()
        wait_until(lambda: agent.core.fusion.position_initialized, timeout=15, message="placed by the fixes")

        def lease() -> None:
            put(LeaseRequest.TOPIC, op.make(LeaseRequest, duration_s=30.0, release=False))

        def drive() -> bool:  # half a metre with fixes: the fusion finds the heading
            put("teleop", op.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5))
            return agent.core.fusion.heading_initialized

        lease()
        wait_until(drive, timeout=20, interval=0.1, message="the heading from driving with fixes")
        dose = agent.node.dose

        def floor_here() -> bool:
            """The map in the site frame, sure enough of the floor around the robot (cells seen free by
            three turns: map_saver's 25 %) for the dose to land there; turning in place maps turns."""
            put("teleop", op.make(Teleop, v=0.0, omega=0.8, ttl_s=0.5))
            floor = dose.floor
            if floor is None:
                return False
            x, y, _ = robot.pose
            ring = floor.sample(np.array([x - 0.3, x, x + 0.3]), np.array([y - 0.3, y, y + 0.3]))
            return bool(ring.all())

        wait_until(floor_here, timeout=20, interval=0.1, message="the floor around the robot in the site-frame map")
        assert dose.grid.lamp_seconds == 0.0 and fetch_dose_now(session) is None  # no lamp yet: no layer

        def lamp(on: bool) -> None:
            lease()
            action = Action(
                actionId=f"lamp-{time.monotonic():.3f}",
                actionType=ActionType.PAYLOAD,
                actionParameters=(KeyValue(key="device", value="uv"), KeyValue(key="on", value=str(on).lower())),
            )
            put("actions", op.make(InstantActions, actions=(action,)))

        wait_until(lambda: agent.core.velocity == (0.0, 0.0), timeout=5, message="the robot standing")
        lamp(True)
        wait_until(lambda: agent.core.board.payload_on, timeout=5, message="the board reporting the lamp on")
        on_at = time.monotonic()
        asker = ZenohEndpoint(session=session)
        asker.start()
        layers: list[SharedDose] = []

        def layer_with(seconds: float) -> bool:
            lease()  # the operator stays in contact
            snap = fetch_dose(asker, "uvc-1", timeout=1.0)
            if snap is None or snap.lamp_on_s < seconds:
                return False
            layers.append(SharedDose.from_snapshot(snap))
            return True

        wait_until(lambda: layer_with(3.0), timeout=20, interval=0.3, message="3 s of lamp in the shared layer")
        lamp(False)
        wait_until(lambda: not agent.core.board.payload_on, timeout=5, message="the lamp off")
        lit_s = time.monotonic() - on_at
        layer = layers[-1]
        assert layer.target_j_m2 == 100.0 and layer.resolution == FIELD_LAMP.dose_resolution_m
        # Where the robot stands (site frame, as the fixes say), the point source's dose: E(0) = P / (4 pi h²).
        x, y, _ = robot.pose
        grid = layer.grid()
        peak = FIELD_LAMP.uvc_power_w / (4.0 * math.pi * FIELD_LAMP.height_m**2)
        here = grid.dose_at(np.array([x]), np.array([y]))[0, 0]
        assert 0.8 * peak * layer.lamp_on_s <= here <= 1.0001 * peak * layer.lamp_on_s
        rows, cols = np.unravel_index(int(np.argmax(grid.dose)), grid.shape)
        ox, oy = grid.origin
        top = (ox + (cols + 0.5) * grid.resolution, oy + (rows + 0.5) * grid.resolution)
        assert math.hypot(top[0] - x, top[1] - y) < 0.3  # the layer is in the site frame, under the robot
        assert layer.unplaced_s < 0.5  # it was placed the whole time the lamp was on

        # Off: the layer's lamp time stops where the board said off.
        def settled() -> bool:
            snap = fetch_dose(asker, "uvc-1", timeout=1.0)
            return snap is not None and abs(snap.lamp_on_s - dose.grid.lamp_seconds) < 1e-9

        wait_until(settled, timeout=10, interval=0.3, message="the last of the layer shared")  # fmt: skip
        final = dose.grid.lamp_seconds
        assert 3.0 <= final <= lit_s + 0.5
        stop.set()
        mark = dose.sampled_until
        assert mark is not None

        def ticked_on() -> bool:  # a second and more of the keeper's ticks with the lamp off (the share period)
            seen = dose.sampled_until
            return seen is not None and seen >= mark + 1.2

        wait_until(ticked_on, timeout=10, interval=0.1, message="the dose keeper ticking on with the lamp off")
        assert dose.grid.lamp_seconds == final
    finally:
        stop.set()
        if fixer is not None:
            fixer.join(2)
        if agents is not None:
            agents.stop()
        if asker is not None:
            asker.close()
        if session is not None:
            session.close()
        field.stop()


def fetch_dose_now(session: zenoh.Session | None) -> DoseSnapshot | None:
    assert session is not None
    asker = ZenohEndpoint(session=session)
    asker.start()
    try:
        return fetch_dose(asker, "uvc-1", timeout=0.5)
    finally:
        asker.close()
