"""The in-process Port: one pair for every simulated device (the board answers, the lidar streams too)."""

from __future__ import annotations

import numpy as np
import pytest

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.client import BoardClient, BoardTimeout
from fleetlink.devices.ports import InProcessPort, PortClosed
from fleetlink.devices.rplidar import protocol as lp
from fleetlink.field.board import SimulatedBoard
from fleetlink.field.lidar import LidarConfig
from fleetlink.field.rplidar import FixedScan, SimulatedRplidar
from fleetlink.shared.clock import SimClock


def test_a_reply_comes_back_at_once_without_moving_time() -> None:
    clock = SimClock(start=5.0)
    port = SimulatedBoard(now=5.0).in_process_port(clock)
    port.write(p.encode_sync(b"abcd"))
    assert port.read_some(clock, 6.0) == p.encode_sync(b"abcd")
    assert clock.now() == 5.0


def test_waiting_for_a_reply_that_never_comes_advances_the_sim_clock_to_the_deadline() -> None:
    clock = SimClock(start=5.0)
    port = SimulatedBoard(now=5.0).in_process_port(clock)
    port.cut = True
    port.write(p.encode_request(p.GetBaseStatus()))  # vanishes
    assert port.read_some(clock, 5.25) == b""
    assert clock.now() == 5.25
    # The lockstep field's port returns at once and leaves time to its owner.
    still = SimulatedBoard(now=5.25).in_process_port(clock, advance_clock=False)
    assert still.read_some(clock, 9.0) == b""
    assert clock.now() == 5.25


def test_a_board_client_times_out_in_simulated_time_on_a_cut_cable() -> None:
    clock = SimClock(start=0.0)
    port = SimulatedBoard(now=0.0).in_process_port(clock)
    client = BoardClient(port, clock, timeout=0.1, retries=2)
    assert isinstance(client.request(p.GetBaseStatus()), p.BaseStatus)
    assert clock.now() == 0.0  # answered in the same instant
    port.cut = True
    with pytest.raises(BoardTimeout):
        client.request(p.GetBaseStatus())
    # The request's 0.1 s, then two retries whose SYNCs each wait 0.1 s: exactly 0.3 s passed.
    assert clock.now() == pytest.approx(0.3)
    assert client.stats.timeouts == 3 and client.stats.retries == 2
    port.cut = False
    assert isinstance(client.request(p.GetBaseStatus()), p.BaseStatus)


def test_a_streaming_device_is_stepped_while_the_reader_waits() -> None:
    clock = SimClock(start=0.0)
    angles = np.linspace(0.0, 2 * np.pi, 360, endpoint=False)
    lidar = SimulatedRplidar(LidarConfig(), FixedScan(angles, np.full(360, 2.0)), now=0.0)
    port = lidar.in_process_port(clock, tick=0.001)
    port.set_dtr(False)  # DTR low: the A1's motor runs
    assert lidar.motor_on
    port.write(lp.encode_request(lp.Command.SCAN))
    assert port.read_some(clock, 1.0) == lp.SCAN_DESCRIPTOR.encode()
    # The first nodes are due a few ms later: the read advances the clock in ticks until they are.
    nodes = port.read_some(clock, 1.0)
    assert nodes and len(nodes) % lp.NODE_LEN == 0
    assert 0.0 < clock.now() <= 0.01
    # Cut: the stream goes nowhere and DTR is not forwarded; closed: the port fails.
    port.cut = True
    assert port.read_some(clock, clock.now() + 0.05) == b""
    port.set_dtr(True)
    assert lidar.motor_on
    port.close()
    with pytest.raises(PortClosed):
        port.read_some(clock, clock.now() + 1.0)
    with pytest.raises(PortClosed):
        port.write(b"\xa5\x25")


def test_injected_bytes_arrive_with_the_next_read() -> None:
    clock = SimClock(start=0.0)
    port = InProcessPort(lambda data: b"")
    port.inject(b"noise")
    assert port.read_some(clock, 1.0) == b"noise"
    assert clock.now() == 0.0
