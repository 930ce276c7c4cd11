"""Zenoh routers in processes of their own, and a mesh of two on loopback.

No ``zenohd`` binary comes with the eclipse-zenoh wheel (nor from Debian's archive), so a router
here is a Python session opened in ``mode: "router"`` by the one factory
(``fleetlink.links.zenoh.peer_config``: explicit endpoints, no scouting, the wire's message limit),
or on a zenohd-style configuration file (``--config deploy/zenohd.json5``: zenoh reads the same
JSON5). Routers linked by a ``connect`` endpoint route between their clients: robots on router A,
consoles on router B, every sample and liveliness token crossing the link between them
(docs/operations.md, "Two routers").

    python -m fleetlink.site.mesh --listen tcp/127.0.0.1:7447
    python -m fleetlink.site.mesh --listen tcp/127.0.0.1:7448 --connect tcp/127.0.0.1:7447

``ZenohRouter(listen, connect)``: one such process (``start``/``stop``, ``pid`` for its CPU);
``RouterMesh()``: two on free loopback ports, B connected to A (tests, bench/scale.py --light).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Self

from fleetlink.site.brokers import SiteError, free_port

__all__ = ["RouterMesh", "ZenohRouter", "main"]

READY = "ready"
START_TIMEOUT_S = 20.0


class ZenohRouter:
    """A Zenoh router in a child process: listens on ``listen``, links to the routers in ``connect``."""

    def __init__(
        self, listen: str, connect: Sequence[str] = (), *, config: Path | None = None, wrap: Sequence[str] = ()
    ) -> None:
        """``wrap``: what the router's command runs under (``ip netns exec NS``: a router inside a
        network namespace, tests/harness/lossy.py)."""
        self.listen = listen
        self.connect = tuple(connect)
        self.config = config
        self.wrap = tuple(wrap)
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def pid(self) -> int:
        if self._proc is None:
            raise RuntimeError("the router is not running")
        return self._proc.pid

    def start(self) -> Self:
        if self._proc is not None:
            return self
        argv = [*self.wrap, sys.executable, "-m", "fleetlink.site.mesh", "--listen", self.listen]
        for ep in self.connect:
            argv += ["--connect", ep]
        if self.config is not None:
            argv += ["--config", str(self.config)]
        proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self._proc = proc
        assert proc.stdout is not None
        line = _readline(proc.stdout, START_TIMEOUT_S)
        if line.strip() != READY:
            self.stop()
            raise SiteError(f"the zenoh router on {self.listen} did not start (said {line.strip()!r})")
        return self

    def stop(self) -> None:
        """End the router (idempotent): its stdin closes, it closes its session and exits."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.stdin is not None:
            proc.stdin.close()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class RouterMesh:
    """Two routers on free loopback ports, B linked to A: ``a.listen`` for robots, ``b.listen`` for consoles."""

    def __init__(self, host: str = "127.0.0.1") -> None:
        ep_a = f"tcp/{host}:{free_port(host)}"
        self.a = ZenohRouter(ep_a)
        self.b = ZenohRouter(f"tcp/{host}:{free_port(host)}", [ep_a])

    def start(self) -> Self:
        self.a.start()
        try:
            self.b.start()
        except BaseException:
            self.a.stop()
            raise
        return self

    def stop(self) -> None:
        self.b.stop()
        self.a.stop()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _readline(stream: IO[bytes], timeout: float) -> str:
    """One line from a child's stdout, or "" if none comes within ``timeout`` seconds."""
    import selectors

    with selectors.DefaultSelector() as sel:
        sel.register(stream, selectors.EVENT_READ)
        if not sel.select(timeout):
            return ""
    return stream.readline().decode(errors="replace")


def main(argv: list[str] | None = None) -> int:
    """The router process: open, say ``ready``, route until stdin closes (or Ctrl-C)."""
    import json

    import zenoh

    from fleetlink.links.zenoh import peer_config

    ap = argparse.ArgumentParser(prog="python -m fleetlink.site.mesh", description=__doc__.split("\n")[0])
    ap.add_argument("--listen", action="append", default=[], help="endpoint to listen on (repeat)")
    ap.add_argument("--connect", action="append", default=[], help="another router to link to (repeat)")
    ap.add_argument(
        "--config", type=Path, help="a zenohd JSON5 file (deploy/zenohd.json5); --listen/--connect override"
    )
    args = ap.parse_args(argv)
    if args.config is not None:
        conf = zenoh.Config.from_file(str(args.config))
        if args.listen:
            conf.insert_json5("listen/endpoints", json.dumps(args.listen))
        if args.connect:
            conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    else:
        conf = peer_config(args.listen, args.connect, mode="router")
    session = zenoh.open(conf)
    try:
        print(READY, flush=True)
        sys.stdin.read()  # until the parent closes our stdin (or goes away)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
