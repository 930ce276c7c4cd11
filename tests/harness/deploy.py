"""The deploy/ configurations, run for real: a Mosquitto broker on deploy/mosquitto*.conf, a Zenoh
router on deploy/zenohd.json5, a throwaway site CA. Only ports and file paths are rewritten.

The rewriting, the CA and the password file are ``fleetlink.field.secure``'s (the simulated field
runs a secured site with the same functions); this module adds the broker the tests control.
"""

from __future__ import annotations

from pathlib import Path

from fleetlink.field.secure import DEPLOY, SiteCA, make_site_ca, mosquitto_conf, mosquitto_passwd, zenoh_router_config
from tests.harness.mosquitto import MosquittoBroker, free_port

__all__ = ["DEPLOY", "DeployBroker", "SiteCA", "make_site_ca", "mosquitto_passwd", "zenoh_router_config"]


class DeployBroker(MosquittoBroker):
    """A broker running a deploy/ config with only its ports and paths rewritten."""

    def __init__(
        self,
        workdir: Path,
        conf: str,
        *,
        passwd: Path,
        acl: Path = DEPLOY / "mosquitto.acl",
        ca: SiteCA | None = None,
    ) -> None:
        self.deploy_text = (DEPLOY / conf).read_text()
        self.passwd, self.acl, self.ca = passwd, acl, ca
        self.tls_port = free_port()
        super().__init__(workdir)

    def _write_conf(self) -> None:
        text = mosquitto_conf(
            self.deploy_text,
            host=self.host,
            port=self.port,
            tls_port=self.tls_port,
            passwd=self.passwd,
            acl=self.acl,
            workdir=self.workdir,
            log_path=self.log_path,
            ca=self.ca,
        )
        self.conf_path.write_text(text)
