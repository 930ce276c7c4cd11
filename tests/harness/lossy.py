"""A lossy link made for real: a network namespace behind a veth pair whose packets the kernel drops.

    with LossyLink() as link:            # needs root, ``ip`` and ``nft``; see ``LossyLink.unavailable``
        link.set_loss(5.0)               # percent of packets dropped, each way, chosen at random
        subprocess.Popen(link.argv(["fleetlink", "field", "--light", "50", "--zenoh-connect", f"tcp/{link.host_ip}:7447"]))

What runs inside (``link.argv``) reaches the host through the veth pair only: the host
end is ``host_ip``, the namespace's ``ns_ip``. Loss is nftables' ``numgen random`` on the namespace's
input and output hooks, so a connection from inside loses ``loss`` percent of its packets in each
direction and TCP recovers them as on a radio that drops frames (retransmission timeouts, 200 ms at
least). ``tc netem`` would add delay too, but this host's kernel has no ``sch_netem`` and no tc
actions (``gact``): nftables is what it has. Delay is not modelled.
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import os
import shutil
import subprocess
from collections.abc import Iterator, Sequence
from typing import Self

__all__ = ["LossyLink"]

_SUBNETS = itertools.count(0)


_LOCK = "/tmp/fleetlink-lossy.lock"
"""Held while a link picks its subnet and takes it (test workers make links side by side)."""


def _tool(name: str) -> str | None:
    """The tool's path: PATH, then the sbin folders a non-login root shell may lack."""
    return shutil.which(name) or shutil.which(name, path="/usr/sbin:/sbin:/usr/local/sbin")


def _sh(*argv: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    tool = _tool(argv[0]) or argv[0]
    return subprocess.run([tool, *argv[1:]], capture_output=True, text=True, check=check, timeout=10)


def _free_subnet(start: int) -> int:
    """A 10.231.k.0/24 no interface of the host uses yet."""
    used = _sh("ip", "-o", "-4", "addr", "show", check=False).stdout
    for i in range(250):
        k = (start + i) % 250
        if f"10.231.{k}." not in used:
            return k
    raise RuntimeError("no free 10.231.k.0/24 subnet for a lossy link")


class LossyLink:
    """One namespace, one veth pair, a loss rule. Closing removes them all (the namespace first)."""

    def __init__(self, name: str | None = None) -> None:
        n = next(_SUBNETS)
        self.name = name or f"fl-lossy-{os.getpid()}-{n}"
        self._host_if = f"flh{os.getpid() % 100000}x{n}"[:15]
        self._ns_if = f"fln{os.getpid() % 100000}x{n}"[:15]
        self._start = os.getpid() + n
        self.host_ip = ""
        self.ns_ip = ""
        """The veth's two ends (10.231.k.1 and .2), set by ``open``."""
        self.loss = 0.0
        self._up = False

    @staticmethod
    def unavailable() -> str | None:
        """Why no lossy link can be made here (None: it can)."""
        if os.name != "posix" or os.geteuid() != 0:
            return "making a network namespace needs root"
        for tool, package in (("ip", "iproute2"), ("nft", "nftables")):
            if _tool(tool) is None:
                return f"no `{tool}` on this machine (Debian: apt-get install {package})"
        probe = f"fl-probe-{os.getpid()}"
        made = _sh("ip", "netns", "add", probe, check=False)
        if made.returncode != 0:
            return f"cannot make a network namespace: {made.stderr.strip()}"
        try:
            ok = _sh("ip", "netns", "exec", probe, str(_tool("nft")), "add", "table", "inet", "probe", check=False)
            if ok.returncode != 0:
                return f"nftables does not work in a namespace here: {ok.stderr.strip()}"
        finally:
            _sh("ip", "netns", "del", probe, check=False)
        return None

    def open(self) -> Self:
        """Make the namespace, the pair and the (empty) loss rules; on any failure, undo what was made."""
        try:
            self._open()
        except BaseException:
            self.close()
            raise
        return self

    def _open(self) -> None:
        ns = self._ns()
        nft = str(_tool("nft"))
        _sh("ip", "netns", "add", self.name)
        self._up = True
        _sh("ip", "link", "add", self._host_if, "type", "veth", "peer", "name", self._ns_if)
        _sh("ip", "link", "set", self._ns_if, "netns", self.name)
        with open(_LOCK, "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # a free subnet, taken before another link looks
            k = _free_subnet(self._start)
            self.host_ip, self.ns_ip = f"10.231.{k}.1", f"10.231.{k}.2"
            _sh("ip", "addr", "add", f"{self.host_ip}/24", "dev", self._host_if)
        _sh("ip", "link", "set", self._host_if, "up")
        _sh(*ns, "ip", "addr", "add", f"{self.ns_ip}/24", "dev", self._ns_if)
        _sh(*ns, "ip", "link", "set", self._ns_if, "up")
        _sh(*ns, "ip", "link", "set", "lo", "up")
        _sh(*ns, nft, "add", "table", "inet", "lossy")
        for chain, hook in (("in", "input"), ("out", "output")):
            _sh(*ns, nft, "add", "chain", "inet", "lossy", chain, f"{{ type filter hook {hook} priority 0; }}")

    def set_loss(self, percent: float) -> None:
        """Drop ``percent`` of the packets crossing the veth, each way (0 to 100, to 0.1 %)."""
        if not 0.0 <= percent <= 100.0:
            raise ValueError(f"loss {percent} % is not within 0-100 %")
        per_mille = round(percent * 10)
        for chain in ("in", "out"):
            _sh(*self._ns(), str(_tool("nft")), "flush", "chain", "inet", "lossy", chain)
            if per_mille:
                rule = f"iifname {self._ns_if}" if chain == "in" else f"oifname {self._ns_if}"
                _sh(
                    *self._ns(),
                    str(_tool("nft")),
                    "add",
                    "rule",
                    "inet",
                    "lossy",
                    chain,
                    *rule.split(),
                    "numgen",
                    "random",
                    "mod",
                    "1000",
                    "<",
                    str(per_mille),
                    "counter",
                    "drop",
                )
        self.loss = per_mille / 10.0

    def dropped(self) -> int:
        """Packets dropped so far by the loss rules (both ways)."""
        out = _sh(*self._ns(), str(_tool("nft")), "list", "table", "inet", "lossy", check=False).stdout
        total = 0
        for word, nxt in itertools.pairwise(out.split()):
            if word == "packets":
                total += int(nxt)
        return total

    def argv(self, command: Sequence[str]) -> list[str]:
        """``command`` run inside the namespace."""
        return [*self._ns(), *command]

    @contextlib.contextmanager
    def router(self, connect: str, port: int = 7447) -> Iterator[str]:
        """A Zenoh router inside the namespace (``site.mesh.ZenohRouter``), linked to ``connect`` (an
        endpoint on the host end); yields its endpoint. A client session connecting to it has every
        packet to and from ``connect`` cross the lossy veth twice."""
        from fleetlink.site.mesh import ZenohRouter

        with ZenohRouter(f"tcp/{self.ns_ip}:{port}", [connect], wrap=self._ns()) as router:
            yield router.listen

    def close(self) -> None:
        if not self._up:
            return
        self._up = False
        _sh("ip", "netns", "del", self.name, check=False)  # takes its end of the veth, and so the pair
        _sh("ip", "link", "del", self._host_if, check=False)

    def _ns(self) -> tuple[str, ...]:
        return (str(_tool("ip") or "ip"), "netns", "exec", self.name)

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()
