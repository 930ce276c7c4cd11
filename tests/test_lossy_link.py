"""A lossy link made for real (tests/harness/lossy.py): the kernel drops packets, TCP recovers them,
light robots behind it are still seen and still driven, and a held key through a lossy primary
keeps driving on redundant sending. Behaviour only; the figures at each loss rate are
bench/scale.py --light --lossy's and bench/failover.py --mode lossy's (docs/operations.md, "A lossy
link").
"""

from __future__ import annotations

import contextlib
import itertools
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetlink.field.light import light_names
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.operator.links import OperatorLink
from fleetlink.shared import wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, LinkName, Pose, State, Teleop
from fleetlink.site.brokers import free_port
from fleetlink.site.mesh import ZenohRouter
from tests.harness import StallWatch, end_child, wait_until
from tests.harness.lossy import LossyLink
from tests.test_light_fleet import NoLink

_WHY = LossyLink.unavailable()
# ./dev test installs nftables (.ci/install-tool), so under CI these tests must run: there a machine
# that cannot make the link fails them.
pytestmark = pytest.mark.skipif(_WHY is not None and not os.environ.get("CI"), reason=f"no lossy link here: {_WHY}")


@pytest.fixture
def link() -> Iterator[LossyLink]:
    if _WHY is not None:  # under CI only (elsewhere the module skips): say why, make nothing
        pytest.fail(f"no lossy link here: {_WHY}")
    with LossyLink() as made:
        yield made


def test_the_kernel_drops_packets_and_tcp_still_delivers_every_byte(link: LossyLink) -> None:
    link.set_loss(10.0)
    with socket.socket() as server:
        server.bind((link.host_ip, 0))
        server.listen()
        server.settimeout(30.0)
        port = server.getsockname()[1]
        code = (
            "import socket, time\n"
            f"s = socket.create_connection(({link.host_ip!r}, {port}))\n"
            "for _ in range(400):\n"
            "    s.sendall(bytes(100)); time.sleep(0.001)\n"
            "s.close()\n"
        )
        sender = subprocess.Popen(link.argv([sys.executable, "-c", code]))
        conn, _ = server.accept()
        got = 0
        with conn:
            conn.settimeout(30.0)
            while chunk := conn.recv(65536):
                got += len(chunk)
        assert sender.wait(30) == 0
    assert got == 40_000
    assert link.dropped() > 0  # ~10 % of ~800 packets each way
    link.set_loss(0.0)  # no rule left: nothing is dropped, nothing counted
    assert link.dropped() == 0 and link.loss == 0.0
    with pytest.raises(ValueError):
        link.set_loss(120.0)
    assert link.loss == 0.0


def test_light_robots_behind_a_lossy_link_are_seen_and_driven(link: LossyLink) -> None:
    """`fleetlink field --light 5` in the namespace at 5 % loss each way; the console on the router."""
    with contextlib.ExitStack() as stack:
        router = ZenohRouter(f"tcp/{link.host_ip}:{free_port(link.host_ip)}").start()
        stack.callback(router.stop)
        _drive_light_robots(link, router, stack)


def _drive_light_robots(link: LossyLink, router: ZenohRouter, stack: contextlib.ExitStack) -> None:
    link.set_loss(5.0)
    fleet = subprocess.Popen(
        link.argv([sys.executable, "-m", "fleetlink.cli.main", "field", "--light", "5", "--zenoh-connect",
                   router.listen, "--zenoh-listen", "none", "--duration", "60"]),
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    console = ZenohEndpoint(connect=[router.listen], mode="client", label="zenoh-console")
    operator = OperatorLink(SystemClock(), "op-a", console, NoLink())  # type: ignore[arg-type]
    heard: list[wire.Message] = []
    lock = threading.Lock()

    def sink(msg: wire.Message, _link: str, _now: float) -> None:
        with lock:
            heard.append(msg)

    stack.callback(end_child, fleet)
    operator.add_sink(sink)
    operator.start()
    stack.callback(operator.close)
    names = set(light_names(5))

    def robots(cls: type[wire.Message]) -> set[str]:
        with lock:
            return {m.header.robot for m in heard if isinstance(m, cls)}

    wait_until(lambda: robots(Pose) == names and robots(State) == names, 30.0, message="every robot heard")
    with lock:
        x0 = max(m.x for m in heard if isinstance(m, Pose) and m.header.robot == "L0002")
    sent = operator.send(Teleop, "L0002", v=0.5, omega=0.0, ttl_s=1.0)

    def acks() -> list[Ack]:
        with lock:
            return [m for m in heard if isinstance(m, Ack) and m.commandHeaderId == sent.header.headerId]

    wait_until(lambda: bool(acks()), 10.0, message="the teleop acked through the loss")
    first, *copies = [(a.result, a.link) for a in acks()]
    assert first == (AckResult.ACCEPTED, LinkName.ZENOH)
    # TCP recovers a lost segment in 0.2 s or more: an ack that late has the command sent again (the
    # link's 0.25 s ack timeout), and that copy is acked as a duplicate, never run twice.
    assert all(c == (AckResult.DUPLICATE, LinkName.ZENOH) for c in copies), copies

    def moved() -> bool:
        with lock:
            return any(isinstance(m, Pose) and m.header.robot == "L0002" and m.x > x0 + 0.1 for m in heard)

    wait_until(moved, 10.0, message="the robot moving")
    wait_until(lambda: link.dropped() > 0, 10.0, message="packets dropped on the way")


def test_a_held_key_through_a_lossy_primary_keeps_driving_with_redundant_sending(link: LossyLink) -> None:
    """Zenoh through a router in the namespace at 20 % loss each way, MQTT clean: every drive of a
    held key and every goal arrives on both links and runs once, and no gap between drives reaches
    their time-to-live (bench/failover.py --mode lossy has the delays: failover alone stalls the
    drives for TCP's timeouts, up to ~0.36 s here)."""
    from fleetlink.operator.commander import TELEOP_TTL_S
    from fleetlink.operator.linkmanager import LinkPolicy
    from fleetlink.shared.messages import Order
    from fleetlink.site.brokers import MosquittoBroker
    from tests.harness.link_robot import LinkRobot, goal, open_operator

    clock = SystemClock()
    watch = StallWatch()
    policy = LinkPolicy(state_window_s=0.35, ack_timeout_s=0.25, holdoff_s=0.3, redundant=True)
    with tempfile.TemporaryDirectory() as tmp, MosquittoBroker(Path(tmp)) as broker:
        op, endpoint = open_operator(
            broker.port, policy, sender="op-lossy", listen=f"tcp/{link.host_ip}:{free_port(link.host_ip)}"
        )
        try:
            with link.router(endpoint) as via:
                robot = LinkRobot("r1", via, broker.port, clock, zenoh_mode="client")
                try:
                    wait_until(lambda: all(h.age_s is not None for h in op.health("r1")), message="both links")
                    probes: list[str] = []

                    def acked_on_both() -> bool:  # the robot's Zenoh subscriptions are in place
                        if all(h.rtt_s is not None for h in op.health("r1")):
                            return True
                        fields = goal(1000 + len(probes))
                        probes.append(fields["orderId"])
                        op.send(Order, "r1", **fields)
                        return False

                    wait_until(acked_on_both, timeout=10, interval=0.2, message="a goal acked on both links")
                    wait_until(lambda: op.pending("r1") == 0, timeout=10, message="the probes acked")
                    dup0 = robot.gate.stats.duplicates
                    link.set_loss(20.0)
                    sent = []
                    drive_sent: dict[int, float] = {}  # headerId -> when the drive was sent
                    with watch:
                        for i in range(120):  # 6 s: a drive every 50 ms, a goal every 200 ms
                            at = time.monotonic()  # the harness robot's clock (SystemClock.now)
                            msg = op.send(Teleop, "r1", expect_ack=False, v=0.2, omega=0.0, ttl_s=TELEOP_TTL_S)
                            drive_sent[msg.header.headerId] = at
                            if i % 4 == 0:
                                fields = goal(i)
                                sent.append(fields["orderId"])
                                op.send(Order, "r1", **fields)
                            time.sleep(0.05)
                        wait_until(lambda: op.pending("r1") == 0, timeout=10, message="every goal acked")
                    # Every command came on both links (TCP resends what the primary lost): the
                    # first copy ran, the second was the gate's duplicate.
                    wait_until(
                        lambda: robot.gate.stats.duplicates - dup0 >= 120 + len(sent), timeout=10, message="every copy"
                    )
                    assert link.dropped() > 0
                finally:
                    robot.close()
        finally:
            op.close()
    runs = [e.order[0] for e in robot.executed if e.order is not None]
    assert sorted(runs) == sorted(sent + probes)  # each goal once: none lost, none twice
    drives = [(e.at, drive_sent[e.header_id]) for e in robot.executed if e.topic == "teleop"]
    assert len(drives) == 120
    # No deadman stop the links made: between two drives run, the time the links added to the time
    # between their sends stays under the time-to-live less the key's repeat period. (The gap as run
    # alone also counts this process's own stalls, up to 0.73 s on a loaded CI host with the sender
    # asleep as long; and a stall of the receiving threads, 0.60 s once in CI, shows in the watch.)
    added = [
        (b_at - a_at) - (b_sent - a_sent) - watch.stalled(a_at, b_at)
        for (a_at, a_sent), (b_at, b_sent) in itertools.pairwise(drives)
    ]
    assert max(added) < TELEOP_TTL_S - 0.05
