"""A stalled link must not delay the other link's copy (issue 18), and teleops count in link health.

The stall is real: a Zenoh peer that stops reading (a frozen process, SIGSTOP) while the console's
session keeps its TCP connection to it. Once the socket and zenoh's transmit queue towards it are
full, a put with congestion control BLOCK (every command, links/zenoh.py) waits for room up to
zenoh's ``wait_before_close`` (5 s). The robot is the real agent on a simulated board
(tests/test_agent_links.py ``make_rig``), reached by the console on both links.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from fleetlink.links.base import LinkStats
from fleetlink.links.mqtt import MqttEndpoint
from fleetlink.links.sender import LinkSender, needs_sender
from fleetlink.links.zenoh import ZenohEndpoint, open_session
from fleetlink.operator.linkmanager import FALLBACK, PRIMARY, LinkManager, LinkPolicy
from fleetlink.operator.links import OperatorLink, mqtt_settings_for
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, Action, ActionType, InstantActions, LinkName, Teleop
from tests.harness import wait_until
from tests.harness.zenoh_peers import loopback_endpoint
from tests.test_agent_links import make_rig

# -- the sender alone ------------------------------------------------------------------------------


class StuckLink:
    """A link whose publish waits until ``release`` is set (an injected stall)."""

    name = LinkName.ZENOH

    def __init__(self) -> None:
        self.stats = LinkStats()
        self.release = threading.Event()
        self.sent: list[str] = []

    def publish(self, key: str, payload: bytes) -> bool:
        self.release.wait(5.0)
        self.sent.append(key)
        return True


def test_a_stuck_link_never_holds_the_caller_and_a_full_queue_drops_the_oldest() -> None:
    link = StuckLink()
    sender = LinkSender(link, capacity=3).start()  # type: ignore[arg-type]
    try:
        t0 = time.monotonic()
        for i in range(6):  # the first is taken (and stuck in publish); 3 wait; 2 push older ones out
            sender.submit(f"k{i}", b"x")
            if i == 0:
                wait_until(lambda: sender.waiting == 0, message="the first taken by the send thread")
        assert time.monotonic() - t0 < 0.5  # generous: submit only queues
        assert sender.dropped == 2 and link.stats.dropped == 2
        assert sender.waiting == 3
        assert not sender.flush(0.05)  # stuck
        link.release.set()
        assert sender.flush(2.0)
        assert link.sent == ["k0", "k3", "k4", "k5"]  # in order, the newest kept
    finally:
        link.release.set()
        sender.stop()


def test_stop_hands_on_what_was_queued() -> None:
    link = StuckLink()
    link.release.set()
    sender = LinkSender(link)  # type: ignore[arg-type]
    for i in range(5):
        sender.submit(f"k{i}", b"x")  # before start: held
    sender.start()
    sender.stop()
    assert link.sent == [f"k{i}" for i in range(5)]


def test_which_links_get_a_send_thread() -> None:
    assert needs_sender(ZenohEndpoint(listen=()))  # a put may wait (congestion control BLOCK)
    assert not needs_sender(MqttEndpoint(mqtt_settings_for("mqtt://127.0.0.1:1")))  # paho's loop writes
    assert needs_sender(StuckLink())  # a link that says nothing is assumed to wait


# -- teleops in link health ------------------------------------------------------------------------


@pytest.mark.parametrize("redundant", [True, False])
def test_teleop_copies_feed_rtt_loss_and_first_delivered(redundant: bool) -> None:
    lm = LinkManager(LinkPolicy(redundant=redundant))
    t = 0.0
    for link in (PRIMARY, FALLBACK):
        lm.heard("r1", link, t)
    for i in range(10):  # a held key: acked by the agent on each link it came by, never re-sent
        t += 0.1
        sends, _ = lm.command("r1", "teleop", i, b"drive", t, expect_ack=False)
        assert not any(s.resend for s in sends)
        lm.acked("r1", PRIMARY, "teleop", i, t + 0.002)
        if redundant:
            lm.acked("r1", FALLBACK, "teleop", i, t + 0.004)
    lm.command("r1", "teleop", 10, b"drive", t + 0.1, expect_ack=False)  # never acked
    for k in range(1, 5):
        lm.heard("r1", PRIMARY, t + 0.1 * k)
        out = lm.poll(t + 0.1 * k)
        assert not [o for o in out if getattr(o, "topic", "") == "teleop"]  # no re-send, no failure
    h = {x.link: x for x in lm.health("r1", t + 0.4)}
    assert h[PRIMARY].rtt_s == pytest.approx(0.002)
    assert h[PRIMARY].loss_pct == pytest.approx(100 / 11)
    assert lm.pending("r1") == 0
    if redundant:
        assert h[FALLBACK].rtt_s == pytest.approx(0.004)
        assert h[PRIMARY].first_pct == 100.0 and h[PRIMARY].lead_s == pytest.approx(0.002)
    else:
        assert h[FALLBACK].rtt_s is None and h[PRIMARY].first_pct is None


# -- a real stall ----------------------------------------------------------------------------------

FROZEN_PEER = """
import sys, threading, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", '["%s"]' % sys.argv[1])
conf.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(conf)
sub = s.declare_subscriber("**", lambda sample: None)
print("ready", flush=True)
threading.Event().wait()  # until the test kills it (SIGSTOP first)
"""


@pytest.fixture
def frozen_peer() -> Iterator[Any]:
    """A Zenoh client of the console that subscribes to everything, then stops reading (SIGSTOP)."""
    endpoint = loopback_endpoint()
    procs: list[subprocess.Popen[bytes]] = []

    def start() -> subprocess.Popen[bytes]:
        proc = subprocess.Popen([sys.executable, "-c", FROZEN_PEER, endpoint], stdout=subprocess.PIPE)
        procs.append(proc)
        assert proc.stdout is not None and proc.stdout.readline().strip() == b"ready"
        return proc

    try:
        yield endpoint, start
    finally:
        for proc in procs:
            proc.kill()
            proc.wait(5)


def test_a_stalled_zenoh_does_not_delay_the_mqtt_copy_to_a_real_agent(mosquitto: Any, frozen_peer: Any) -> None:
    listen, start_peer = frozen_peer
    clock = SystemClock()
    with make_rig(mosquitto) as rig:
        zenoh_at = rig.agent.config.zenoh.listen[0]
        session = open_session(listen=[listen], connect=[zenoh_at])
        op = OperatorLink(
            clock,
            "operator-2",
            ZenohEndpoint(session=session),
            MqttEndpoint(mqtt_settings_for(f"mqtt://127.0.0.1:{mosquitto.port}"), client_id="operator-2"),
            policy=LinkPolicy(redundant=True),
        )
        acks: list[tuple[str, Ack]] = []
        op.add_sink(lambda m, link, _now: acks.append((link, m)) if isinstance(m, Ack) else None)
        op.start()
        try:
            wait_until(lambda: all(h.age_s is not None for h in op.health("r1")), message="r1 on both links")
            peer = start_peer()
            wait_until(lambda: len(list(session.info.peers_zid())) >= 1, message="console peers")
            time.sleep(0.3)  # the frozen peer's subscription reaches the console
            os.kill(peer.pid, signal.SIGSTOP)
            # Fill the socket and zenoh's queue towards the frozen peer (telemetry-sized DROP puts on
            # a key only it hears): from here a BLOCK put waits for room.
            import zenoh

            big = b"\0" * 60_000
            t_fill = time.monotonic()
            while time.monotonic() - t_fill < 1.0:
                session.put("stall/fill", big, congestion_control=zenoh.CongestionControl.DROP)

            sent: list[int] = []
            t0 = time.monotonic()
            for i in range(8):
                action = Action(actionId=f"stop-{i}", actionType=ActionType.STOP, actionParameters=())
                sent.append(op.send(InstantActions, "r1", actions=(action,)).header.headerId)
            assert time.monotonic() - t0 < 0.5, "the caller waited for the stalled link"

            def answered() -> set[int]:
                return {a.commandHeaderId for _, a in list(acks) if a.commandTopic == "actions"}

            wait_until(lambda: set(sent) <= answered(), timeout=1.5, message="every command answered over MQTT")
            zenoh_sender = op.senders[LinkName.ZENOH]
            assert zenoh_sender.waiting > 0, "Zenoh was not stalled: the test proves nothing"
            assert time.monotonic() - t0 < 2.0  # well inside zenoh's 5 s wait
            assert LinkName.MQTT not in op.senders  # paho only queues: the MQTT copy is sent inline
            ran = [(link, a.commandHeaderId) for link, a in list(acks) if a.result is AckResult.ACCEPTED]
            # (a copy or two may have gone over Zenoh before its queue filled; the rest ran from MQTT)
            assert sum(1 for link, h in ran if link == "mqtt" and h in sent) >= len(sent) - 2

            os.kill(peer.pid, signal.SIGKILL)  # the stall ends: the queued Zenoh copies go out
            wait_until(lambda: op.flush(0.1), timeout=10.0, message="the Zenoh copies handed on")
            # Nothing lost is the point here, not how soon: a CI run with the other worker on a
            # 150 s e2e test once took longer than 5 s for the last of these answers.
            wait_until(
                lambda: set(sent) <= {a.commandHeaderId for lk, a in list(acks) if lk == "zenoh"},
                timeout=15.0,
                message="every Zenoh copy answered",
            )
            results: dict[int, list[AckResult]] = {h: [] for h in sent}
            for _link, a in list(acks):
                if a.commandTopic == "actions" and a.commandHeaderId in results:
                    results[a.commandHeaderId].append(a.result)
            # Run once each (accepted on one link), every other copy a duplicate; nothing lost. A
            # loaded host can hold an MQTT ack past ack_timeout_s, and the retry then sends another
            # copy on both links: more duplicates, never a second run.
            for r in results.values():
                assert r.count(AckResult.ACCEPTED) == 1, results
                assert set(r) == {AckResult.ACCEPTED, AckResult.DUPLICATE}, results
            assert op.pending("r1") == 0
        finally:
            op.close()


def test_teleops_from_the_console_show_in_link_health(mosquitto: Any) -> None:
    with make_rig(mosquitto) as rig:
        zenoh_at = rig.agent.config.zenoh.listen[0]
        op = OperatorLink(
            SystemClock(),
            "operator-2",
            ZenohEndpoint(connect=[zenoh_at]),
            MqttEndpoint(mqtt_settings_for(f"mqtt://127.0.0.1:{mosquitto.port}"), client_id="operator-2"),
            # An ack later than the timeout counts its copy lost: 0.25 s by default, which a CI host
            # busy with another worker once missed on one teleop of ten. What is checked here is
            # that acked teleops count as delivered, not how fast the host is.
            policy=LinkPolicy(redundant=True, ack_timeout_s=1.5),  # inside track_s (2 s)
        ).start()
        try:
            wait_until(lambda: all(h.age_s is not None for h in op.health("r1")), message="r1 on both links")
            for _ in range(10):  # a zero twist: needs no lease; acked on each link
                op.send(Teleop, "r1", expect_ack=False, v=0.0, omega=0.0, ttl_s=0.5)
                time.sleep(0.02)
            wait_until(
                lambda: sum(h.first_pct or 0.0 for h in op.health("r1")) == pytest.approx(100.0),
                message="first-delivered from teleop acks",
            )
            h = {x.link: x for x in op.health("r1")}
            assert h[PRIMARY].rtt_s is not None and h[FALLBACK].rtt_s is not None
            assert h[PRIMARY].loss_pct == 0.0 and h[FALLBACK].loss_pct == 0.0
            assert op.pending("r1") == 0
        finally:
            op.close()
