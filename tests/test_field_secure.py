"""`fleetlink field --secure`, headless: the field as one site (``fleetlink.site.field.FieldSite``)
with ``security``: a secured site (deploy/'s Mosquitto with a generated
password file and ACL, a Zenoh router on deploy/zenohd.json5 with usrpwd and default-deny access
control, TLS from a throwaway CA when openssl is there), the field's agents logged in as their
robot ids, the UWB gateway as uwb-gateway, ground truth as sim, the console's link as the operator.

Absence is shown with sentinels: after the forbidden messages, something the same path may carry
arrives; anything sent before it would have too.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import paho.mqtt.client as mqtt
import pytest
import zenoh

from fleetlink.field.realtime import RealtimeField
from fleetlink.links.mqtt import connect_client
from fleetlink.links.zenoh import peer_config
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, FixStatus, Teleop, UwbFix
from fleetlink.shared.mqtt import MqttSettings
from fleetlink.site.field import FieldSite, Security
from fleetlink.site.security import SiteSecurity
from tests.harness import wait_until
from tests.test_field_realtime import quiet_scenario

# One worker runs this module under pytest-xdist, so its module-scoped set-up runs once.
pytestmark = pytest.mark.xdist_group("field_secure")

OPERATOR = "op-operator-1"
SECOND_OPERATOR = "op-operator-2"  # more people: their own logins and sender ids
THIRD_OPERATOR = "op-operator-3"
FORGED = 42.0  # a fix no gateway would report here


@dataclass
class Secured:
    site: SiteSecurity
    field: RealtimeField
    fs: FieldSite
    link: Any
    acks: list[Ack]
    uwb_in: list[tuple[str, str, bytes]]  # (link, key, payload) of every uwb message reaching uvc-1's agent
    lock: threading.Lock

    def moved(self, robot: str, start: tuple[float, float, float]) -> float:
        pose = next(r.pose for r in self.field.world.robots if r.name == robot)
        return math.hypot(pose[0] - start[0], pose[1] - start[1])

    def pose(self, robot: str) -> tuple[float, float, float]:
        return next(r.pose for r in self.field.world.robots if r.name == robot)


@pytest.fixture(scope="module")
def secured() -> Iterator[Secured]:
    clock = SystemClock()
    scenario = quiet_scenario(
        robots=[
            {"name": "uvc-1", "start": "living", "drive": "idle"},
            {"name": "uvc-2", "start": "bedroom", "drive": "idle"},
        ],
        lidar={"enabled": False},
    )
    fs = FieldSite(scenario, clock=clock, security=Security((OPERATOR, SECOND_OPERATOR, THIRD_OPERATOR))).start()
    link = None
    try:
        assert fs.security is not None and fs.agents is not None and fs.gateway is not None and fs.truth is not None
        assert fs.link is None and fs.boards is None  # no operator asked for: no console link; agents drive
        lock = threading.Lock()
        uwb_in: list[tuple[str, str, bytes]] = []
        agents = fs.agents
        agent = agents.agents["uvc-1"]
        for lk in agent.links:  # tap what reaches the agent from each link: a second receiver on its endpoint

            def tap(key: str, payload: bytes, name: Any = lk.name) -> None:
                with lock:
                    uwb_in.append((name.value, key, payload))

            lk.subscribe(keys.key("uvc-1", "uwb"), tap)
        acks: list[Ack] = []
        link = fs.operator_link(OPERATOR)
        link.add_sink(lambda m, _l, _t: acks.append(m) if isinstance(m, Ack) else None)
        link.start()
        wait_until(
            lambda: all(
                a.zenoh is not None and a.zenoh.up and a.mqtt is not None and a.mqtt.up for a in agents.agents.values()
            ),
            timeout=15,
            message="every agent logged in on both links",
        )
        yield Secured(fs.security, fs.field, fs, link, acks, uwb_in, lock)
    finally:
        if link is not None:
            link.close()
        fs.stop()


def test_the_operators_console_link_drives_a_robot(secured: Secured) -> None:
    s = secured
    assert s.site.tls == (s.site.ca is not None)
    start, other = s.pose("uvc-1"), s.pose("uvc-2")
    sent: list[int] = []

    def drive() -> bool:
        sent.append(s.link.send(Teleop, "uvc-1", v=0.2, omega=0.0, ttl_s=0.5).header.headerId)
        return s.moved("uvc-1", start) > 0.05

    wait_until(drive, interval=0.1, timeout=15, message="uvc-1 moving under the console's teleop")
    wait_until(lambda: any(a.commandHeaderId in sent and a.result is AckResult.ACCEPTED for a in list(s.acks)))
    assert s.moved("uvc-2", other) < 0.01


def test_no_credentials_no_connection_on_either_link(secured: Secured) -> None:
    site = secured.site
    for user, password in ((None, None), (OPERATOR, "wrong"), ("intruder", "x")):
        auth = site.zenoh_auth(OPERATOR)
        auth.update(username=user, password=password)
        with pytest.raises(zenoh.ZError):
            zenoh.open(peer_config(**auth))
    for user, password in ((None, None), (OPERATOR, "wrong")):
        refused: list[str] = []
        done = threading.Event()
        base = site.mqtt_settings()
        c = connect_client(
            MqttSettings(
                host=base.host, port=base.port, tls=base.tls, ca_file=base.ca_file, username=user, password=password
            ),
            client_id=f"intruder-{user}",
            start=False,
        )

        def on_connect(
            client: mqtt.Client,
            _u: object,
            _f: object,
            reason: Any,
            _p: object,
            refused: list[str] = refused,
            done: threading.Event = done,
        ) -> None:
            refused.append(str(reason))
            client.disconnect()
            done.set()

        c.on_connect = on_connect
        c.connect_async(base.host, base.port, keepalive=5)
        c.loop_start()
        try:
            wait_until(done.is_set, message="a CONNACK")
        finally:
            c.loop_stop()
        assert refused[0] in ("Not authorized", "Bad user name or password"), refused


def test_another_robot_cannot_drive_a_robot(secured: Secured) -> None:
    s = secured
    wait_until(lambda: s.fs.agents.agents["uvc-1"].board.snapshot.connected)

    def at_rest() -> bool:  # the module's robots are shared: an earlier test's drive may still run out
        before = s.pose("uvc-1")
        time.sleep(0.3)
        return s.moved("uvc-1", before) < 0.005

    wait_until(at_rest, timeout=10, message="uvc-1 at rest")
    start = s.pose("uvc-1")
    clock = SystemClock()
    forger = wire.HeaderCounter(clock, robot="uvc-1", sender=OPERATOR)  # even claiming the operator's id
    z = zenoh.open(peer_config(**s.site.zenoh_auth("uvc-2")))
    m = connect_client(s.site.mqtt_settings("uvc-2"), client_id="forger-uvc-2")
    try:
        wait_until(m.is_connected, message="uvc-2's MQTT login")
        for _ in range(10):
            msg = forger.make(Teleop, v=0.3, omega=0.0, ttl_s=1.0)
            z.put(wire.key_of(msg), wire.encode(msg))  # under the operator's name
            # QoS 1: acknowledged by the broker once handled (dropped, by the ACL).
            m.publish(wire.key_of(msg), wire.encode(msg), qos=1).wait_for_publish(5)
        # Sentinel: the operator's own command after the forgeries reaches the agent and is acked.
        sentinel = s.link.send(Teleop, "uvc-1", v=0.0, omega=0.0, ttl_s=0.2).header.headerId
        wait_until(lambda: any(a.commandHeaderId == sentinel for a in list(s.acks)), message="the sentinel's ack")
        assert s.moved("uvc-1", start) < 0.02  # 10 teleops at 0.3 m/s would have moved it
    finally:
        m.disconnect()
        m.loop_stop()
        z.close()


def test_forged_uwb_fixes_never_reach_the_agent(secured: Secured) -> None:
    s = secured
    clock = SystemClock()
    wait_until(lambda: len(s.uwb_in) >= 3, timeout=15, message="the gateway's fixes reaching uvc-1")
    counter = wire.HeaderCounter(clock, robot="uvc-1", sender="field-uwb")  # claiming the gateway's id
    fix = counter.make(
        UwbFix, tag="uvc-1", x=FORGED, y=FORGED, z=0.3, sd_x=0.01, sd_y=0.01, quality=100, status=FixStatus.OK,
        anchors=("A1", "A2", "A3"), residual_rms_m=0.0, measured_at=clock.wall(),
    )  # fmt: skip
    data = wire.encode(fix)
    for user in ("uvc-2", "uvc-1", OPERATOR, "sim"):
        z = zenoh.open(peer_config(**s.site.zenoh_auth(user)))
        try:
            for _ in range(5):
                z.put(keys.key("uvc-1", "uwb"), data)
        finally:
            z.close()
        c = connect_client(s.site.mqtt_settings(user), client_id=f"forger-{user}")
        try:
            wait_until(c.is_connected, message=f"{user}'s MQTT login")
            for _ in range(5):
                c.publish(keys.key("uvc-1", "uwb"), data, qos=1).wait_for_publish(5)
        finally:
            c.disconnect()
            c.loop_stop()
    # Sentinels: the gateway's fixes after every forgery was handled (MQTT), and a fix from the
    # gateway's own Zenoh login (the router, ingress from a user allowed to write fixes).
    gw = zenoh.open(peer_config(**s.site.zenoh_auth("uwb-gateway")))
    try:
        good = wire.encode(counter.make(
            UwbFix, tag="uvc-1", x=1.0, y=1.0, z=0.3, sd_x=0.05, sd_y=0.05, quality=90, status=FixStatus.OK,
            anchors=("A1", "A2", "A3"), residual_rms_m=0.0, measured_at=clock.wall(),
        ))  # fmt: skip

        def zenoh_sentinel() -> bool:
            gw.put(keys.key("uvc-1", "uwb"), good)
            with s.lock:
                return any(lk == "zenoh" and p == good for lk, _, p in s.uwb_in)

        wait_until(zenoh_sentinel, interval=0.1, message="a gateway fix over the router")
    finally:
        gw.close()
    with s.lock:
        n = sum(1 for lk, _, _ in s.uwb_in if lk == "mqtt")
    wait_until(lambda: sum(1 for lk, _, _ in list(s.uwb_in) if lk == "mqtt") >= n + 3, message="gateway fixes after")
    with s.lock:
        got = list(s.uwb_in)
    assert all(p != data for _, _, p in got), "a forged fix reached the agent"


def test_a_second_console_joins_with_the_printed_credentials(secured: Secured) -> None:
    import argparse

    from fleetlink.cli.console import add_arguments, load_settings, open_link

    site = secured.site
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    argv = [
        "--user", OPERATOR, "--password-file", str(site.password_file(OPERATOR)),
        "--zenoh-connect", site.zenoh_endpoint, "--mqtt", site.mqtt_url,
    ] + (["--ca-file", site.ca_file] if site.ca_file else [])  # fmt: skip
    command = next(line for line in site.describe() if "fleetlink console" in line)
    assert " ".join(argv) in command
    settings = load_settings(parser.parse_args(argv))
    assert settings.operator == OPERATOR and settings.user == OPERATOR
    link = open_link(settings, SystemClock())
    try:
        wait_until(lambda: link.delivered["zenoh"] > 0 and link.delivered["mqtt"] > 0, message="robots heard on both")
    finally:
        link.close()


def test_a_late_console_gets_the_marks_another_console_holds(secured: Secured) -> None:
    """The generated ACL lets operators answer marks queries, so a console that joins late catches up."""
    from fleetlink.shared.messages import Mark

    s = secured
    holder = s.fs.operator_link(SECOND_OPERATOR)
    late = s.fs.operator_link(THIRD_OPERATOR)
    try:
        holder.start()
        mark = Mark(
            header=holder.counter.header(Mark.TOPIC, robot="uvc-1"),
            markId="casualty-1",
            x=1.5,
            y=2.5,
            label="under the stairs",
            kind="casualty",
            sd_m=0.0,
            removed=False,
        )
        holder.serve_marks(lambda: [mark])
        got: list[Mark] = []
        late.add_sink(lambda m, _l, _t: got.append(m) if isinstance(m, Mark) else None)
        late.start()
        # The queryable's declaration takes a moment to reach the router: ask until it answers.
        wait_until(lambda: late.fetch_marks(0.5) > 0 and bool(got), timeout=15, message="a marks reply")
        assert got[0].markId == "casualty-1" and (got[0].x, got[0].y) == (1.5, 2.5)
    finally:
        late.close()
        holder.close()


def test_a_consoles_fleet_map_and_frames_reach_another_console(secured: Secured) -> None:
    """The generated ACL lets a console share the fleet map it builds (served under the id ``fleet``,
    as a robot serves its map) and say where the robots without UWB lie on it (``FleetFrames``)."""
    import numpy as np

    from fleetlink.agent.mapping.keeper import MapPublication
    from fleetlink.agent.mapping.share import fetch_map
    from fleetlink.cli.console import fleet_map_service
    from fleetlink.shared.messages import FleetFrames, RobotFrame

    s = secured
    holder = s.fs.operator_link(SECOND_OPERATOR)
    late = s.fs.operator_link(THIRD_OPERATOR)
    service = None
    try:
        holder.start()
        late.start()
        service = fleet_map_service(holder, None, threading.Lock(), SystemClock(), SECOND_OPERATOR)
        assert service.share is not None
        cells = np.zeros((20, 30), dtype=np.int8)
        cells[0, :] = 100
        service.share.publish(MapPublication(3, cells, 0.05, (-1.0, -0.5), None, site_frame=True))
        frames: list[FleetFrames] = []
        late.add_sink(lambda m, _l, _t: frames.append(m) if isinstance(m, FleetFrames) else None)
        msg = service.share.counter.make(
            FleetFrames,
            reference="",
            frames=(RobotFrame(robot="uvc-2", x=1.0, y=2.0, theta=0.5, began=0.0),),
            unframed=(),
        )
        query = late.query_link()
        wait_until(
            lambda: (snap := fetch_map(query, keys.FLEET_MAP, timeout=0.5)) is not None and snap.version == 3,
            timeout=15,
            message="the fleet map fetched by another console",
        )

        def heard() -> bool:
            service.share.link.publish(wire.key_of(msg), wire.encode(msg))  # type: ignore[union-attr]
            return bool(frames)

        wait_until(heard, timeout=15, message="FleetFrames heard by another console")
        assert frames[0].frames[0].robot == "uvc-2"
    finally:
        if service is not None and service.share is not None:
            service.share.stop()
        late.close()
        holder.close()
