"""A private Mosquitto broker per test: ``fleetlink.site.brokers.MosquittoBroker`` as fixtures.

Every broker gets its own config, log and port (127.0.0.1, found by binding port 0), so tests never
talk to the system broker on 1883 and never see each other's traffic. The broker is a real
``mosquitto`` process: if the binary is missing the fixtures FAIL (run ``.ci/install-mosquitto``);
they never skip and never fall back to the embedded amqtt broker (that fallback is the demo
field's alone: ``fleetlink.site.brokers.start_demo_broker``, which the harness does not use).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from fleetlink.site.brokers import (
    INSTALL_HINT,
    MosquittoBroker,
    MosquittoNotFound,
    MosquittoStartError,
    find_mosquitto,
    free_port,
)

__all__ = [
    "INSTALL_HINT",
    "MosquittoBroker",
    "MosquittoNotFound",
    "MosquittoStartError",
    "find_mosquitto",
    "free_port",
    "mosquitto",
    "mosquitto_factory",
]

VERBOSE_LOG = ("all",)  # every packet in the broker log: what a failing test's diagnostics show


@pytest.fixture
def mosquitto_factory(tmp_path: Path) -> Iterator[Callable[..., MosquittoBroker]]:
    """``mosquitto_factory(extra_conf="") -> MosquittoBroker`` (started); all stopped at teardown."""
    brokers: list[MosquittoBroker] = []

    def make(extra_conf: str = "") -> MosquittoBroker:
        workdir = tmp_path / f"mosquitto-{len(brokers)}"
        try:
            broker = MosquittoBroker(workdir, extra_conf, log_types=VERBOSE_LOG)
        except MosquittoNotFound as exc:
            pytest.fail(str(exc), pytrace=False)
        brokers.append(broker)
        try:
            broker.start()
        except MosquittoStartError as exc:
            pytest.fail(str(exc), pytrace=False)
        return broker

    try:
        yield make
    finally:
        for broker in brokers:
            broker.stop()


@pytest.fixture
def mosquitto(mosquitto_factory: Callable[..., MosquittoBroker]) -> MosquittoBroker:
    """A started private broker with the default config (anonymous, loopback, no persistence)."""
    return mosquitto_factory()
