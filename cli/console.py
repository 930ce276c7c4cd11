"""The operator console: join an existing fleet over Zenoh (primary) and MQTT (fallback).

    fleetlink console --zenoh-connect tcp/10.0.0.5:7447 --mqtt mqtt://10.0.0.5:1883
    fleetlink console --config console.toml
    fleetlink console --read-only ...
    fleetlink console --user op-alice --password-file op-alice.password --ca-file ca.crt \
        --zenoh-connect tls/router.site-a.example:7447 --mqtt mqtts://broker.site-a.example:8883

On a secured site (docs/operations.md) the console logs in to the router and the broker as
``--user`` (``op-<name>``) with the password in ``--password-file``; ``--ca-file`` is the site CA
for tls/ and mqtts:// endpoints. The login is the console's sender id: the broker and the router
let it publish commands only under that name (docs/operations.md, "Identity").

Keys: u i o / j k l / m , . (teleop_twist_keyboard), arrows and w a s d drive the selected robot;
space or k stops it; Esc stops every robot; q/z, W/x, e/c change speeds; t takes the control
lease; h returns home; p toggles the payload; P pauses or resumes a round; M (shift-m) marks a
casualty, hazard or note at the selected robot's pose; ':' types a goal, a mark or a round
(':disinfect room X Y'); '/' filters; a click on the map sends a
goal (after confirmation) or places a mark; ctrl+q quits (and stops every robot).
See docs/console.md.

Config file (TOML), every key optional; command-line options win:

    operator = "operator-1"
    read_only = false
    marks_file = "marks.json"
    audit_log = "alarms.jsonl"            # the alarm audit log (default: next to the marks file)
    user = "op-alice"                    # a secured site: the login on both links (or --user)
    password_file = "op-alice.password"
    ca_file = "ca.crt"                   # the site CA, for tls/ and mqtts://
    [zenoh]
    connect = ["tls/router.site-a.example:7447"]
    listen = []
    [mqtt]
    url = "mqtts://broker.site-a.example:8883"
    [uv]                                 # the lamp UV rounds are planned for (the agent's [uv] keys)
    uvc_power_w = 10.0
    height_m = 0.6
    target_dose_mj_cm2 = 10.0            # :disinfect's default (dose MJ_CM2 overrides it)
    [links]                              # docs/console.md "Links"
    redundant = true                     # every command on both links at once; false: failover only (metered link)
    degraded_rtt_s = 0.1                 # a link is degraded (alarm) over this RTT p95,
    degraded_loss_pct = 5.0              # ... this share of copies unacked,
    degraded_silence_s = 1.0             # ... or this long silent
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import socket
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from fleetlink.cli.main import on_sigterm
from fleetlink.shared.config import Setting

log = logging.getLogger(__name__)


@dataclass
class ConsoleSettings:
    operator: str = "operator-1"
    zenoh_connect: tuple[str, ...] = ()
    zenoh_listen: tuple[str, ...] = ()
    mqtt_url: str = "mqtt://127.0.0.1:1883"
    read_only: bool = False
    marks_file: Path | None = field(default_factory=lambda: Path("marks.json"))
    audit_log: Path | None = None
    """The alarm audit log (JSON lines, appended); None: ``alarms.jsonl`` next to the marks file."""
    user: str | None = None
    password: str | None = field(default=None, repr=False)
    ca_file: str | None = None
    uv: ConsoleUvTable | None = None
    """The lamp and target dose rounds are planned for (``[uv]``); None: the agent's defaults."""
    links: ConsoleLinksTable = field(default_factory=lambda: ConsoleLinksTable())
    """Redundant sending and the link health thresholds (``[links]``)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, help="a console TOML file (see above)")
    parser.add_argument("--operator", help="this console's sender id (default operator-1)")
    parser.add_argument("--zenoh-connect", action="append", default=None, help="Zenoh endpoint to connect to (repeat)")
    parser.add_argument("--zenoh-listen", action="append", default=None, help="Zenoh endpoint to listen on (repeat)")
    parser.add_argument("--mqtt", dest="mqtt_url", help="MQTT broker url (default mqtt://127.0.0.1:1883)")
    parser.add_argument("--read-only", action="store_true", default=None, help="watch only: send no command")
    parser.add_argument("--marks", type=Path, dest="marks_file", help="where marks are saved (default marks.json)")
    parser.add_argument(
        "--audit-log", type=Path, help="the alarm audit log, JSON lines (default alarms.jsonl next to the marks file)"
    )
    parser.add_argument("--user", help="log in to the router and the broker as this user (op-<name>)")
    parser.add_argument("--password-file", type=Path, help="the --user's password (one line)")
    parser.add_argument("--ca-file", help="the site CA for tls/ Zenoh endpoints and mqtts:// urls")


@dataclass(frozen=True, slots=True)
class ConsoleZenohTable:
    connect: tuple[Annotated[str, Setting(min_len=1)], ...] = ()
    listen: tuple[Annotated[str, Setting(min_len=1)], ...] = ()


@dataclass(frozen=True, slots=True)
class ConsoleMqttTable:
    url: Annotated[str, Setting(min_len=1, doc="mqtt://host[:1883] or mqtts://host[:8883]")]


NonEmpty = Annotated[str | None, Setting(min_len=1)]


@dataclass(frozen=True, slots=True)
class ConsoleUvTable:
    """``[uv]``: the lamp a UV round (``:disinfect``) is planned for and its default target dose;
    the same keys and defaults as the agent's ``[uv]`` (agent/config.py, deploy/robot.example.toml)."""

    uvc_power_w: Annotated[float, Setting(lo=1e-3, hi=10_000.0, doc="UV-C optical output, W (not electrical W)")] = 10.0
    height_m: Annotated[float, Setting(lo=0.01, hi=10.0, doc="lamp centre above the floor, m")] = 0.6
    tube_length_m: Annotated[float, Setting(lo=0.0, hi=5.0, doc="0: point source; else a vertical tube, m")] = 0.0
    min_distance_m: Annotated[float, Setting(lo=0.01, hi=5.0, doc="the model holds beyond this distance, m")] = 0.3
    target_dose_mj_cm2: Annotated[
        float, Setting(lo=1e-4, hi=100_000.0, doc="the dose every cell should get, mJ/cm² (10 = 100 J/m²)")
    ] = 10.0

    def validate(self) -> None:
        self.lamp()  # the lamp model's own checks (the floor beyond min_distance_m)

    def lamp(self) -> Any:
        """The ``shared.dose.Lamp``."""
        from fleetlink.shared.dose import Lamp

        return Lamp(self.uvc_power_w, self.height_m, self.tube_length_m, self.min_distance_m)


@dataclass(frozen=True, slots=True)
class ConsoleLinksTable:
    """``[links]``: how commands go out and when a link counts as degraded (docs/console.md "Links")."""

    redundant: Annotated[
        bool, Setting(doc="every command on both links at once; false (a metered link): the active link, failover")
    ] = True
    degraded_rtt_s: Annotated[float, Setting(lo=1e-3, hi=60.0, doc="RTT p95 over this: degraded, s")] = 0.1
    degraded_loss_pct: Annotated[float, Setting(lo=0.0, hi=100.0, doc="copies unacked over this: degraded, %")] = 5.0
    degraded_silence_s: Annotated[
        float, Setting(lo=0.1, hi=600.0, doc="heard before, silent this long: degraded, s")
    ] = 1.0

    def policy(self) -> Any:
        """The ``operator.linkmanager.LinkPolicy``."""
        from fleetlink.operator.linkmanager import LinkPolicy

        return LinkPolicy(
            redundant=self.redundant,
            degraded_rtt_s=self.degraded_rtt_s,
            degraded_loss_pct=self.degraded_loss_pct,
            degraded_silence_s=self.degraded_silence_s,
        )


@dataclass(frozen=True, slots=True)
class ConsoleFile:
    """console.toml (see the module docstring); every key optional, command-line options win."""

    operator: Annotated[str | None, Setting(min_len=1, doc="this console's sender id")] = None
    read_only: Annotated[bool | None, Setting(doc="watch only: send no command")] = None
    marks_file: Annotated[str | None, Setting(min_len=1, doc="where marks are saved")] = None
    audit_log: Annotated[str | None, Setting(min_len=1, doc="the alarm audit log (JSON lines)")] = None
    user: Annotated[str | None, Setting(min_len=1, doc="a secured site: the login on both links")] = None
    password_file: NonEmpty = None
    ca_file: Annotated[str | None, Setting(min_len=1, doc="the site CA, for tls/ and mqtts://")] = None
    zenoh: ConsoleZenohTable | None = None
    mqtt: ConsoleMqttTable | None = None
    uv: ConsoleUvTable | None = None
    links: ConsoleLinksTable | None = None


def load_settings(args: argparse.Namespace) -> ConsoleSettings:
    """Defaults, then the config file, then command-line options. ConfigError/ValueError with reasons."""
    from fleetlink.operator.links import parse_mqtt_url
    from fleetlink.shared import keys
    from fleetlink.shared.config import load

    s = ConsoleSettings()
    operator_given = bool(args.operator)
    if args.config is not None:
        f = load(args.config, ConsoleFile)
        if f.user is not None:
            s.user = f.user
        if f.password_file is not None:
            s.password = _read_password(Path(f.password_file))
        if f.ca_file is not None:
            s.ca_file = f.ca_file
        if f.operator is not None:
            operator_given = True
            s.operator = f.operator
        if f.read_only is not None:
            s.read_only = f.read_only
        if f.marks_file is not None:
            s.marks_file = Path(f.marks_file)
        if f.audit_log is not None:
            s.audit_log = Path(f.audit_log)
        if f.zenoh is not None:
            s.zenoh_connect, s.zenoh_listen = f.zenoh.connect, f.zenoh.listen
        if f.mqtt is not None:
            s.mqtt_url = f.mqtt.url
        s.uv = f.uv
        if f.links is not None:
            s.links = f.links
    if getattr(args, "user", None):
        s.user = args.user
    if getattr(args, "password_file", None):
        s.password = _read_password(args.password_file)
    if getattr(args, "ca_file", None):
        s.ca_file = args.ca_file
    if args.operator:
        s.operator = args.operator
        operator_given = True
    if s.user is not None:
        if operator_given and s.operator != s.user:
            raise ValueError(
                f"operator {s.operator!r} differs from the login {s.user!r}: on a secured site the login is "
                "the sender id (the broker and the router accept commands only under it); drop --operator"
            )
        s.operator = s.user
    if args.zenoh_connect:
        s.zenoh_connect = tuple(args.zenoh_connect)
    if args.zenoh_listen:
        s.zenoh_listen = tuple(args.zenoh_listen)
    if args.mqtt_url:
        s.mqtt_url = args.mqtt_url
    if args.read_only:
        s.read_only = True
    if args.marks_file:
        s.marks_file = args.marks_file
    if getattr(args, "audit_log", None):
        s.audit_log = args.audit_log
    keys.check_id(s.operator, "operator id")
    if (s.user is None) != (s.password is None):
        raise ValueError("--user and --password-file go together (both or neither)")
    if s.user is not None or s.ca_file is not None or s.mqtt_url.startswith("mqtts://"):
        mqtt_client_settings(s)  # raises ConfigError on a bad url
    else:
        parse_mqtt_url(s.mqtt_url)
    return s


def _read_password(path: Path) -> str:
    try:
        password = path.read_text(encoding="utf-8").strip("\r\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot read the password file {str(path)!r}: {exc}") from exc
    if not password:
        raise ValueError(f"the password file {str(path)!r} is empty")
    return password


def mqtt_client_settings(s: ConsoleSettings) -> Any:
    """``shared.mqtt.MqttSettings`` for a console with credentials or TLS (None: a plain url will do)."""
    from fleetlink.shared.mqtt import MqttSettings

    if s.user is None and s.ca_file is None and not s.mqtt_url.startswith("mqtts://"):
        return None
    return MqttSettings.from_url(s.mqtt_url, username=s.user, password=s.password, ca_file=s.ca_file)


def open_link(settings: ConsoleSettings, clock: Any, client_id: str | None = None) -> Any:
    """The console's OperatorLink (Zenoh + MQTT) from its settings, started (fleetlink.site.operator).
    ``client_id``: the broker's client id (default ``<operator>-<host>``; unique on the broker)."""
    from fleetlink.site.operator import open_operator_link

    auth: dict[str, Any] = {}
    if settings.user is not None:
        auth = {"username": settings.user, "password": settings.password}
        if not settings.zenoh_listen:
            auth["mode"] = "client"  # a client of the site's router
    if settings.ca_file is not None:
        auth["root_ca"] = settings.ca_file
    return open_operator_link(
        clock,
        settings.operator,
        mqtt_url=settings.mqtt_url,
        mqtt=mqtt_client_settings(settings),
        zenoh_listen=settings.zenoh_listen,
        zenoh_connect=settings.zenoh_connect,
        zenoh_auth=auth,
        client_id=client_id or f"{settings.operator}-{socket.gethostname()}"[:64],
        policy=settings.links.policy(),
    ).start()


def run_console(settings: ConsoleSettings, link: Any = None) -> int:
    """Open the links (unless given), run the app, stop every robot and close the links on the way out."""
    import threading

    from fleetlink.operator.console import ConsoleApp, attach
    from fleetlink.operator.dose import DoseFetcher, DoseFollower
    from fleetlink.operator.fleet import FleetModel
    from fleetlink.operator.maps import MapFetcher, MapFollower
    from fleetlink.shared.clock import SystemClock

    clock = SystemClock()
    if link is None:
        link = open_link(settings, clock)
    fleet = FleetModel(settings.operator)
    lock = threading.Lock()
    maps = MapFollower(fleet)
    doses = DoseFollower(fleet)
    attach(link, fleet, lock, maps, doses)
    app = ConsoleApp(
        link, fleet, clock, lock=lock, doses=doses, read_only=settings.read_only, marks_file=settings.marks_file,
        audit_log=audit_log_path(settings), **round_options(settings),
    )  # fmt: skip
    fleet_map = fleet_map_service(link, maps, lock, clock, settings.operator)
    fetcher = MapFetcher(maps, link.fetch_map, clock, lock, after_poll=fleet_map.step).start()
    dose_fetcher = DoseFetcher(doses, link.fetch_dose, clock, lock).start()  # merges the layers off the UI thread
    marks = share_marks(link, fleet, lock, clock=clock, publish=not settings.read_only)
    try:
        with _sigterm_ends(app):
            app.run()
    finally:
        app.send_stop_to_all()  # also after a crash or Ctrl-C: safety before features
        marks.stop()
        fetcher.stop()
        dose_fetcher.stop()
        if fleet_map.share is not None:
            fleet_map.share.stop()
        link.close()
    return 0


def fleet_map_service(link: Any, maps: Any, lock: Any, clock: Any, operator: str) -> Any:
    """The fleet map this console builds from the robots' maps (site/fleetmap.py), served on its
    primary link when that answers queries, so ``fleetlink map save --fleet`` can fetch it."""
    from fleetlink.agent.mapping.share import MapShare
    from fleetlink.shared import keys
    from fleetlink.site.fleetmap import FleetMapService

    share = None
    primary = link.query_link() if hasattr(link, "query_link") else None
    if primary is not None:
        share = MapShare(primary, keys.FLEET_MAP, clock, sender=operator)
        share.start()
    return FleetMapService(maps, lock, clock, share=share, query=primary)


def round_options(settings: ConsoleSettings) -> dict[str, Any]:
    """What the console plans rounds with: the planner (fleetlink.site.rounds, over the agent's
    coverage planner), the lamp and the default target dose (``[uv]``, else the agent's defaults)."""
    from fleetlink.shared.dose import j_m2
    from fleetlink.site.rounds import plan_round

    uv = settings.uv or ConsoleUvTable()
    return {"planner": plan_round, "lamp": uv.lamp(), "target_j_m2": j_m2(uv.target_dose_mj_cm2)}


def audit_log_path(settings: ConsoleSettings) -> Path:
    """Where the alarm audit log goes: as set, else ``alarms.jsonl`` next to the marks file."""
    if settings.audit_log is not None:
        return settings.audit_log
    return (settings.marks_file.parent if settings.marks_file is not None else Path(".")) / "alarms.jsonl"


def _sigterm_ends(app: Any) -> contextlib.AbstractContextManager[None]:
    """While the app runs, SIGTERM asks it to exit like ctrl+q: Textual then stops its terminal
    threads and restores the terminal. (The CLI's SIGTERM-as-Ctrl-C, raised inside Textual's
    event loop, skipped that: the console sent its stop but hung on exit, its threads alive.)"""

    def end(signum: int, frame: object) -> None:
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # not in the app's loop (starting or ending): Ctrl-C's way out
            raise KeyboardInterrupt(f"signal {signum}") from None
        loop.call_soon_threadsafe(app.exit)

    return on_sigterm(end)


def share_marks(link: Any, fleet: Any, lock: Any, **options: Any) -> Any:
    """Share marks with the other consoles (operator/marksync.py ``MarkSharing``, started): this
    console's retained sets on MQTT, answers to their Zenoh marks queries, and its own queries
    (``asks``: seconds after start), so a console that starts late or restarts gets every mark.
    ``stop()`` it on the way out."""
    from fleetlink.operator.marksync import MarkSharing

    return MarkSharing(link, fleet, lock, **options).start()


def run(args: argparse.Namespace) -> int:
    from fleetlink.shared.config import ConfigError

    try:
        settings = load_settings(args)
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    # Logs would scribble over the terminal UI: keep warnings, send them to a file next to the marks.
    logging.getLogger().handlers.clear()
    logging.basicConfig(
        filename="console.log", level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        return run_console(settings)
    except Exception as exc:  # zenoh raises its own ZError for bad endpoints
        print(f"error: cannot start the console: {exc}", file=sys.stderr)
        return 1
