"""Control boards. ``serve`` runs a simulated board on TCP or a pty, for a real navigation board or an
agent to talk to; ``probe`` connects to a real or simulated board, prints what it says about
itself, and can drive its wheels for a few seconds before stopping them.

Examples:
  fleetlink board serve --port 7001
  fleetlink board serve --pty
  fleetlink board probe socket://127.0.0.1:7001
  fleetlink board probe /dev/ttyUSB0 --drive 0.1 --seconds 2
"""

from __future__ import annotations

import argparse
import math
import sys
import threading


def _byte(text: str) -> int:
    value = int(text, 0)
    if not 0 <= value <= 0xFF:
        raise argparse.ArgumentTypeError(f"{text} is not a byte")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="board_command", metavar="ACTION", required=True)

    serve = sub.add_parser(
        "serve",
        help="serve a simulated control board on TCP or a pty",
        description="Serve a simulated control board (Control Bus slave) until interrupted.",
    )
    where = serve.add_mutually_exclusive_group()
    where.add_argument("--port", type=int, default=7001, help="TCP port (default 7001; 0 picks a free one)")
    where.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal and print its path")
    serve.add_argument("--host", default="127.0.0.1", help="TCP address to listen on (default 127.0.0.1)")
    serve.add_argument("--watchdog", type=float, default=1.0, help="seconds without a request before the wheels stop")
    serve.add_argument("--ctrl-bus-cmd", type=_byte, default=0xF8, help="request TYPE byte (0xF8 SLAMTEC, 0xA8 thesis)")
    serve.add_argument(
        "--room", type=float, nargs=2, metavar=("W", "H"), default=(6.0, 4.0), help="walled room size in m"
    )
    serve.set_defaults(_run=run_serve)

    probe = sub.add_parser(
        "probe",
        help="handshake with a board, print identity, status and sensors, optionally drive",
        description="Handshake with a board, print what it reports, optionally drive the wheels then stop.",
    )
    probe.add_argument("url", help="/dev/ttyUSB0, a pty path, or socket://host:port")
    probe.add_argument("--drive", type=float, default=0.0, metavar="M_PER_S", help="forward speed to drive at")
    probe.add_argument("--turn", type=float, default=0.0, metavar="RAD_PER_S", help="turn rate to drive at")
    probe.add_argument("--seconds", type=float, default=2.0, help="how long to drive (default 2)")
    probe.add_argument("--ctrl-bus-cmd", type=_byte, default=0xF8, help="request TYPE byte (0xF8 SLAMTEC, 0xA8 thesis)")
    probe.add_argument("--timeout", type=float, default=0.2, help="per-request timeout in seconds")
    probe.set_defaults(_run=run_probe)


def run(args: argparse.Namespace) -> int:
    return int(args._run(args))


def run_serve(args: argparse.Namespace) -> int:
    from fleetlink.devices.controlbus.protocol import Profile
    from fleetlink.field.board import BoardConfig, SimulatedBoard
    from fleetlink.field.device_server import DeviceServer
    from fleetlink.field.floor import Floor
    from fleetlink.shared.clock import SystemClock

    w, h = args.room
    board = SimulatedBoard(
        BoardConfig(watchdog=args.watchdog),
        Floor.box(w, h),
        Profile(ctrl_bus_cmd=args.ctrl_bus_cmd),
        pose=(w / 2, h / 2, 0.0),
    )
    server = DeviceServer(board, SystemClock(), name="board")
    if args.pty:
        where = server.serve_pty()
        print(f"simulated board on {where}  (connect with: fleetlink board probe {where})", flush=True)
    else:
        port = server.serve_tcp(args.host, args.port)
        print(f"simulated board on socket://{args.host}:{port}", flush=True)
    done = threading.Event()
    try:
        while not done.wait(1.0):
            with server.lock:
                events, board.events[:] = list(board.events), []
            for e in events:
                print(f"board: {e}", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0


def run_probe(args: argparse.Namespace) -> int:
    from fleetlink.devices.controlbus import protocol as p
    from fleetlink.devices.controlbus.client import BoardClient, BoardError, BoardRefused
    from fleetlink.devices.ports import PortClosed, SerialPort
    from fleetlink.shared.clock import SystemClock

    clock = SystemClock()
    try:
        port = SerialPort(args.url)
    except PortClosed as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    client = BoardClient(port, clock, p.Profile(ctrl_bus_cmd=args.ctrl_bus_cmd), timeout=args.timeout)
    try:
        info = client.connect()
        print(f"model     {info.model}")
        print(f"firmware  {info.firmware_text}   hardware {info.hardware}   serial {info.serial_text}")
        for label, req in (
            ("conf", p.GetBaseConf()),
            ("status", p.GetBaseStatus()),
            ("motors", p.GetMotorData()),
            ("sensors", p.GetSensorData()),
            ("bumpers", p.GetBumperData()),
            ("health", p.GetHealth()),
            ("power", p.GetPowerData()),
            ("payload", p.GetPayloadStatus()),
            ("env", p.GetEnvData()),
            ("buttons", p.GetButtons()),
        ):
            try:
                print(f"{label:<9} {_describe(client.request(req))}")
            except BoardRefused as exc:
                print(f"{label:<9} (not supported: {p.ErrorCode.describe(exc.code)})")
        health = client.request(p.GetHealth())
        assert isinstance(health, p.Health)
        for i in range(health.error_count):
            err = client.request(p.GetHealthError(i))
            assert isinstance(err, p.HealthError)
            print(f"error     0x{err.code:04X} {err.message}")
        if args.drive or args.turn:
            if not (math.isfinite(args.drive) and math.isfinite(args.turn)):
                print("error: --drive and --turn must be finite numbers", file=sys.stderr)
                return 2
            _drive(client, clock, args.drive, args.turn, args.seconds)
    except BoardError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        client.close()
    return 0


def _drive(client: object, clock: object, vx: float, omega: float, seconds: float) -> None:
    from fleetlink.devices.controlbus import protocol as p
    from fleetlink.devices.controlbus.client import BoardClient
    from fleetlink.shared.clock import SystemClock

    assert isinstance(client, BoardClient) and isinstance(clock, SystemClock)
    x = y = th = 0.0
    start = clock.now()
    nxt = start
    print(f"driving at {vx:.2f} m/s, {omega:.2f} rad/s for {seconds:.1f} s")
    try:
        while clock.now() - start < seconds:
            dr = client.request(p.SetVelocity(vx, 0.0, omega))
            assert isinstance(dr, p.DeadReckon)
            c, s = math.cos(th), math.sin(th)
            x, y, th = x + c * dr.dx - s * dr.dy, y + s * dr.dx + c * dr.dy, th + dr.dtheta
            nxt += 0.02
            clock.sleep_until(nxt)
    finally:
        client.request(p.SetVelocity(0.0, 0.0, 0.0))
        print("stopped")
    motor = client.request(p.GetMotorData())
    print(f"dead reckoning: x={x:+.3f} m y={y:+.3f} m theta={math.degrees(th):+.1f} deg")
    print(f"wheel odometer: {_describe(motor)}")


def _describe(reply: object) -> str:
    from fleetlink.devices.controlbus import protocol as p

    if isinstance(reply, p.BaseConf):
        return f"{'round' if reply.base_type == 0 else 'square'} base r={reply.radius:.3f} m, {len(reply.sensors)} range sensors, {len(reply.bumpers)} bumpers"
    if isinstance(reply, p.BaseStatus):
        flags = [
            n
            for n, on in (
                ("charging", reply.charging),
                ("external power", reply.external_power),
                ("on dock", reply.on_dock),
            )
            if on
        ]
        return f"battery {reply.battery_percent} %" + (f" ({', '.join(flags)})" if flags else "")
    if isinstance(reply, p.MotorData):
        return f"left {reply.left:.3f} m, right {reply.right:.3f} m, status 0x{reply.status:02X}"
    if isinstance(reply, p.SensorData):
        used = [f"{d:.2f}" for d in reply.distances if d > 0]
        return "ranges (m): " + (" ".join(used) if used else "no echo")
    if isinstance(reply, p.BumperData):
        hit = [i for i in range(8 * reply.width) if reply.triggered(i)]
        return f"bitmap 0x{reply.bitmap:0{2 * reply.width}X}" + (
            f", triggered bits {hit}" if hit else ", nothing triggered"
        )
    if isinstance(reply, p.Health):
        names = [n for n, b in (("warning", 1), ("error", 2), ("fatal", 4)) if reply.flags & b]
        return f"{', '.join(names) or 'ok'}; {reply.error_count} error(s)"
    if isinstance(reply, p.PowerData):
        return f"{reply.voltage:.2f} V, {reply.current:+.2f} A, {reply.battery_percent} %"
    if isinstance(reply, p.PayloadStatus):
        return f"UV-C {'on' if reply.uv_lamp else 'off'}, atomiser {reply.atomiser_level}, fan {reply.fan_level}, tank {reply.tank_percent} %"
    if isinstance(reply, p.EnvData):
        return f"{reply.temperature_c:.1f} °C, {reply.humidity_percent:.0f} % RH, PM2.5 {reply.pm2_5:.1f} µg/m³, TVOC {reply.tvoc_ppb} ppb"
    if isinstance(reply, p.Buttons):
        return f"buttons 0x{reply.bitmap:02X}"
    return repr(reply)
