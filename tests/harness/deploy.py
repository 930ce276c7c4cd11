"""The deploy/ configurations, run for real: a Mosquitto broker on deploy/mosquitto*.conf, a Zenoh
router on deploy/zenohd.json5, a throwaway site CA. Only ports and file paths are rewritten.

The broker, the rewriting, the CA and the password file are ``fleetlink.site``'s (the simulated
field runs a secured site with the same code); this module only names the broker the tests use.
"""

from __future__ import annotations

from pathlib import Path

from fleetlink.site.brokers import DEPLOY, BrokerSecurity, MosquittoBroker
from fleetlink.site.security import SiteCA, make_site_ca, mosquitto_passwd, zenoh_router_config

__all__ = ["DEPLOY", "DeployBroker", "SiteCA", "make_site_ca", "mosquitto_passwd", "zenoh_router_config"]


class DeployBroker(MosquittoBroker):
    """A broker running the deploy/ config ``conf`` with only its ports and paths rewritten."""

    def __init__(
        self,
        workdir: Path,
        conf: str,
        *,
        passwd: Path,
        acl: Path = DEPLOY / "mosquitto.acl",
        ca: SiteCA | None = None,
    ) -> None:
        super().__init__(workdir, security=BrokerSecurity(passwd=passwd, acl=acl, ca=ca, template=conf))
