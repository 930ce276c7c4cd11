"""The real-time field end to end: boards and lidars over TCP as hardware, ground truth over real Zenoh."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from fleetlink.agent.lidar.driver import LidarDriver
from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.client import BoardClient
from fleetlink.devices.ports import SerialPort
from fleetlink.field.realtime import RealtimeField
from fleetlink.field.scenario import parse_scenario
from fleetlink.field.truth import TruthPublisher
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Truth
from tests.harness import wait_until


def quiet_scenario(**extra: object):  # type: ignore[no-untyped-def]
    data: dict[str, object] = {
        "plan": "apartment",
        "seed": 2,
        "robots": [{"name": "uvc-1", "start": "living", "drive": "idle"}],
        "noise": {
            k: 0.0
            for k in (
                "wheel_scale_sd",
                "gyro_bias_sd",
                "gyro_noise_sd",
                "ultrasonic_sd",
                "lidar_range_sd",
                "lidar_dropout",
            )
        },
        "lidar": {"rate_hz": 10.0},
    }
    data.update(extra)
    return parse_scenario(data)


def test_board_and_lidar_are_served_like_hardware_and_truth_goes_out_on_zenoh(zenoh_peers) -> None:  # type: ignore[no-untyped-def]
    field_session, listener = zenoh_peers(2)
    clock = SystemClock()
    truths: list[Truth] = []
    lock = threading.Lock()

    def on_truth(sample) -> None:  # type: ignore[no-untyped-def]
        msg = wire.decode_key(str(sample.key_expr), sample.payload.to_bytes())
        with lock:
            truths.append(msg)  # type: ignore[arg-type]

    sub = listener.declare_subscriber(keys.ZENOH_ALL_TRUTH, on_truth)
    publisher = TruthPublisher(ZenohEndpoint(session=field_session), clock)
    field = RealtimeField(quiet_scenario(), clock=clock, truth_sink=publisher.publish)
    try:
        endpoints = field.start()
        ep = endpoints["uvc-1"]
        assert ep.board.startswith("socket://127.0.0.1:") and ep.lidar and ep.lidar.startswith("socket://")

        # The board: a real Control Bus handshake over TCP, then a drive command moves the body.
        board = BoardClient(SerialPort(ep.board), clock)
        try:
            assert board.connect().model == "FLK-UVC-01"
            start = field.world.robots[0].pose
            deadline = clock.now() + 1.0
            while clock.now() < deadline:
                board.request(p.SetVelocity(0.0, 0.0, 0.5))
                clock.sleep_until(clock.now() + 0.02)
            board.request(p.SetVelocity(0.0, 0.0, 0.0))
            turned = math.remainder(field.world.robots[0].pose[2] - start[2], 2 * math.pi)
            assert 0.25 < turned < 0.6
        finally:
            board.close()

        # The lidar: an RPLIDAR master gets revolutions that match the room as the world sees it.
        lidar = LidarDriver.open(ep.lidar, clock)
        try:
            assert lidar.get_health().status == 0
            lidar.start_scan()
            revs = lidar.read_revolutions(3, timeout=5.0)
            x, y, th = field.world.robots[0].pose
            rev = revs[-1]
            assert 700 <= len(rev) <= 900  # 8000 samples/s at 10 Hz
            expected = field.world.raycaster.cast(x, y, rev.angles_rad + th, 12.0)
            seen = rev.valid & np.isfinite(expected)
            assert seen.mean() > 0.9
            err = np.abs(rev.distances_m[seen] - expected[seen])
            assert np.median(err) < 0.01  # noise is off; quantisation is 1/4 mm, angle 1/64 degree
        finally:
            lidar.close()

        # Ground truth: wire-contract Truth messages under the simulation namespace.
        wait_until(lambda: len(truths) >= 5, timeout=5.0, message="truth samples on zenoh")
        with lock:
            last = truths[-1]
        assert last.header.robot == "uvc-1" and last.header.sender == "field"
        assert (last.x, last.y) == pytest.approx(field.world.robots[0].pose[:2], abs=0.05)
        assert last.sim_time_s > 0.5
    finally:
        field.stop()
        publisher.close()
        sub.undeclare()


def test_a_scripted_link_cut_stops_the_robot_in_real_time() -> None:
    clock = SystemClock()
    sc = quiet_scenario(events=[{"at_s": 0.3, "kind": "link_cut", "robot": "uvc-1", "duration_s": 1.5}])
    field = RealtimeField(sc, clock=clock)
    try:
        ep = field.start()["uvc-1"]
        board = BoardClient(SerialPort(ep.board), clock, timeout=0.05, retries=0)
        try:
            board.connect()
            cut_seen = False
            deadline = clock.now() + 1.3
            while clock.now() < deadline:
                try:
                    board.request(p.SetVelocity(0.2, 0.0, 0.0))
                except Exception:
                    cut_seen = True
                clock.sleep_until(clock.now() + 0.02)
            assert cut_seen
            state = field.world.robots[0].board.state
            wait_until(lambda: state.watchdog_tripped, timeout=2.0, message="the board's watchdog")
            wait_until(lambda: state.v_left == 0.0 and state.v_right == 0.0, timeout=1.0, message="wheels stopped")
            assert any("link of uvc-1 cut" in e for e in field.events.log)
        finally:
            board.close()
    finally:
        field.stop()
