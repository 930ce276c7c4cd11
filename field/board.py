"""The simulated control board: the slave side of the Control Bus, with the thesis' firmware behaviour.

Sans-I/O: ``receive(data, now)`` takes request bytes and returns reply bytes; ``step(now)``
advances the firmware (wheel PID, encoders, battery, payload, link watchdog) and the robot's
motion on a minimal floor. ``field.device_server.DeviceServer`` serves it on TCP and on a pty; the lockstep
field calls it in-process through the same bytes.
"""

from __future__ import annotations

import logging
import math
import random
from dataclasses import dataclass, field

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.frames import BOARD_BUFFER, Frame, FrameDecoder
from fleetlink.devices.ports import InProcessPort
from fleetlink.field.floor import Floor
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.clock import Clock

log = logging.getLogger(__name__)

__all__ = ["BoardConfig", "SimulatedBoard"]

# Bumper bitmap layout of this board (0 = triggered): bumpers from bit 0, cliff sensors after.
BUMPER_LEFT, BUMPER_RIGHT, CLIFF_LEFT, CLIFF_RIGHT = 0, 1, 2, 3
ALL_CLEAR = 0xFFFF_FFFF
_HOME_BUTTON = 0x02  # GET_BUTTONS bit 1
_FIRST_EXTENSION = p.CtrlBus.SET_UV_LAMP  # fleetlink's extension commands are 0xA0 and up


@dataclass(slots=True)
class BoardConfig:
    model: str = "FLK-UVC-01"  # 12 ASCII bytes at most on the wire
    firmware: int = 0x0102  # 1.2
    hardware: int = 0x0001
    serial: tuple[int, int, int] = (0x464C4B00, 0x00000001, 0x00000001)
    wheel_track: float = 0.22  # m (the sweeping-robot seed's default)
    radius: float = BODY_RADIUS_M  # round base (GET_BASE_CONF); the ultrasonic sits on its rim
    max_wheel_speed: float = 0.6  # m/s
    motor_tau: float = 0.08  # s, first-order motor lag under PID
    watchdog: float = 1.0  # s without a CTRL_BUS request before the wheels stop
    ultrasonic_range: tuple[float, float] = (0.25, 1.5)  # m (US-100 on the rescue robot)
    ultrasonic_cone: float = math.radians(40)
    cliff_offset: float = 0.14  # m ahead of the axle, left and right of centre
    battery_full_v: float = 16.8
    battery_empty_v: float = 12.0
    battery_capacity_ah: float = 2.6
    idle_current: float = 0.35  # A
    drive_current: float = 1.8  # A at full wheel speed
    charge_current: float = 1.5  # A
    tank_ml: float = 500.0
    atomiser_ml_per_s: tuple[float, float, float, float] = (0.0, 0.25, 0.5, 1.0)
    dock: tuple[float, float] | None = None  # x, y of a charging dock; on it when within 0.1 m
    wheel_scale: tuple[float, float] = (1.0, 1.0)  # true / nominal wheel radius, left and right
    gyro_bias: float = 0.0  # rad/s
    gyro_noise: float = 0.0  # rad/s, sd per control tick
    ultrasonic_noise: float = 0.005  # m, sd
    noise_seed: int = 0
    extensions: bool = True
    """Serve fleetlink's extension commands (0xA0-0xAB); False: a plain SLAMTEC-profile base,
    which answers each of them NOT_SUPPORTED."""


@dataclass(slots=True)
class WheelPid:
    """Incremental PID on wheel speed, as in the thesis' firmware: u += kp*(e-e1) + ki*e + kd*(e-2e1+e2)."""

    kp: float = 0.6
    ki: float = 0.35
    kd: float = 0.05
    u: float = 0.0  # duty, -1..1
    e1: float = 0.0
    e2: float = 0.0

    def update(self, error: float) -> float:
        self.u += self.kp * (error - self.e1) + self.ki * error + self.kd * (error - 2 * self.e1 + self.e2)
        self.u = max(-1.0, min(1.0, self.u))
        self.e2, self.e1 = self.e1, error
        return self.u

    def reset(self) -> None:
        self.u = self.e1 = self.e2 = 0.0


@dataclass(slots=True)
class BoardState:
    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0
    v_left: float = 0.0  # actual wheel speeds, m/s
    v_right: float = 0.0
    set_left: float = 0.0  # set-points, m/s
    set_right: float = 0.0
    dist_left: float = 0.0  # cumulative, m
    dist_right: float = 0.0
    # dead reckoning accumulated since the last SET_V_AND_GET_DEADRECKON, in that call's frame
    dr_x: float = 0.0
    dr_y: float = 0.0
    dr_theta: float = 0.0
    voltage: float = 16.8
    charging: bool = False
    external_power: bool = False
    bumped_left: bool = False
    bumped_right: bool = False
    stalled: bool = False
    uv_lamp: bool = False
    atomiser: int = 0
    fan: int = 0  # level 0 (off) - 3
    tank_ml: float = 500.0
    leds: tuple[int, int, int, int] = (1, 0, 64, 0)
    buttons: int = 0
    pending_base_command: int | None = None
    watchdog_tripped: bool = False
    last_ctrl_bus: float | None = None
    connected: bool = False  # a CONNECT_BASE has succeeded
    errors: list[tuple[int, str]] = field(default_factory=list)
    temperature_c: float = 22.0
    humidity: float = 45.0
    pm2_5: float = 12.0
    tvoc_ppb: int = 120
    requests: int = 0
    error_replies: int = 0
    watchdog_trips: int = 0
    true_v: float = 0.0  # ground truth body velocity, m/s and rad/s
    true_w: float = 0.0
    gyro_rate: float = 0.0  # rad/s as the gyro reports it
    gyro_yaw: float = 0.0  # integrated gyro heading, rad
    gyro_samples: int = 0


class SimulatedBoard:
    """One board. Not thread-safe: the server serialises ``receive`` and ``step`` with a lock."""

    def __init__(
        self,
        config: BoardConfig | None = None,
        floor: Floor | None = None,
        profile: p.Profile = p.DEFAULT_PROFILE,
        pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
        now: float = 0.0,
    ) -> None:
        self.config = config or BoardConfig()
        self.floor = floor or Floor()
        self.profile = profile
        self.state = BoardState(x=pose[0], y=pose[1], theta=pose[2], tank_ml=self.config.tank_ml)
        self.state.voltage = self.config.battery_full_v
        self._pid = (WheelPid(), WheelPid())
        self._rng = random.Random(self.config.noise_seed)
        # No code filter: an unknown CMD must be answered with 0x8000, not silently skipped.
        self._decoder = FrameDecoder(valid_codes=None, max_frame=BOARD_BUFFER, report_drops=True)
        self._now = now
        self._slow_dt = 0.0
        self.slip = [0.0, 0.0]  # fraction of each wheel's motion lost to slip (scripted events set it)
        self.events: list[str] = []  # human-readable firmware events, drained by the owner

    # ---------------------------------------------------------------------------------------
    # Bytes in, bytes out
    # ---------------------------------------------------------------------------------------

    def in_process_port(self, clock: Clock, *, advance_clock: bool = True) -> InProcessPort:
        """A master's port onto this board in the same process: each request answered at once at
        ``clock``'s time. The board's firmware is stepped by its owner, not by the port."""
        return InProcessPort(lambda data: self.receive(data, clock.now()), advance_clock=advance_clock)

    def receive(self, data: bytes, now: float) -> bytes:
        """Handle request bytes (any split); return the reply bytes to send back."""
        self.step(now)
        out = bytearray()
        error_pending = False  # at most one error reply per burst of bad bytes
        for item in self._decoder.feed(data):
            if isinstance(item, Frame):
                out += self._handle_frame(item)
                error_pending = False
                continue
            if error_pending:
                continue
            reason = item.reason
            code = {
                "garbage": p.ErrorCode.NOT_SYNCHRONISED,
                "too_long": p.ErrorCode.REQUEST_TOO_LONG,
                "zero_length": p.ErrorCode.NOT_SYNCHRONISED,
                "checksum": p.ErrorCode.CHECKSUM_MISMATCH,
            }.get(reason)
            if code is not None:
                out += self._error(code)
                error_pending = True
        return bytes(out)

    def _handle_frame(self, frame: Frame) -> bytes:
        st = self.state
        st.requests += 1
        if frame.code == p.CMD_SYNC or frame.code == p.CMD_ECHO:
            # "the board sends the whole request frame back unchanged"
            return frame.encode()
        req = p.decode_request(frame, self.profile)
        if isinstance(req, p.Rejected):
            log.debug("board refused request: %s", req.reason)
            return self._error(req.error)
        if isinstance(req, (p.Sync, p.Echo)):
            return frame.encode()
        if isinstance(req, p.BaseCommand):
            # DFU/reboot: acknowledged; a reboot forgets the connection.
            if req.command == 2:
                st.connected = False
            return p.encode_ok(p.Empty())
        # A CTRL_BUS request: feeds the link watchdog.
        st.last_ctrl_bus = self._now
        if st.watchdog_tripped:
            # Driving resumes on this request; the "core disconnected" error stays in the
            # health list until the master has read and cleared it.
            st.watchdog_tripped = False
            self.events.append("link restored: driving allowed again")
        try:
            reply = self._serve(req)
        except _Refusal as exc:
            return self._error(exc.code)
        return p.encode_ok(reply)

    def _error(self, code: int) -> bytes:
        self.state.error_replies += 1
        return p.encode_error(code)

    # ---------------------------------------------------------------------------------------
    # Commands
    # ---------------------------------------------------------------------------------------

    def _serve(self, req: p.Request) -> p.Reply:
        st, cfg = self.state, self.config
        if req.CODE >= _FIRST_EXTENSION and not cfg.extensions:
            raise _Refusal(p.ErrorCode.NOT_SUPPORTED)
        if isinstance(req, p.GetTelemetry):  # first: the master's most frequent request
            return p.Telemetry(
                p.MotorData(st.dist_left, st.dist_right, p.MotorStatus.STALL if st.stalled else 0),
                p.ImuData(st.gyro_rate, st.gyro_yaw, st.gyro_samples),
                p.SensorData((self.ultrasonic(),)),
                p.BumperData(self.bumper_bitmap(), 4),
            )
        if isinstance(req, p.ConnectBase):
            if req.protocol_version != 1:
                raise _Refusal(p.ErrorCode.NOT_SUPPORTED)
            st.connected = True
            return p.BaseInfo(cfg.model, cfg.firmware, cfg.hardware, cfg.serial)
        if isinstance(req, p.GetBaseConf):
            us = p.MountPose(cfg.radius, 0.0, 0.05, 0.0)
            bl = p.MountPose(cfg.radius * math.cos(0.6), cfg.radius * math.sin(0.6), 0.03, 0.6)
            br = p.MountPose(cfg.radius * math.cos(-0.6), cfg.radius * math.sin(-0.6), 0.03, 2 * math.pi - 0.6)
            return p.BaseConf(0, cfg.radius, 0, (us,), (bl, br))
        if isinstance(req, p.GetBinaryConf):
            return p.BinaryConf(f"track={cfg.wheel_track};radius={cfg.radius};vmax={cfg.max_wheel_speed}".encode())
        if isinstance(req, p.GetBaseStatus):
            return p.BaseStatus(self.battery_percent, self._power_flags())
        if isinstance(req, p.GetMotorData):
            status = p.MotorStatus.STALL if st.stalled else 0
            return p.MotorData(st.dist_left, st.dist_right, status)
        if isinstance(req, p.GetSensorData):
            return p.SensorData((self.ultrasonic(),))
        if isinstance(req, p.GetBumperData):
            return p.BumperData(self.bumper_bitmap(), 4)
        if isinstance(req, p.GetAutoHomeData):
            if req.data_type != 0:
                raise _Refusal(p.ErrorCode.BAD_ARGUMENTS)
            return p.AutoHomeData(0, b"")
        if isinstance(req, p.SetBaseMotor):
            left, right = req.speeds[0], req.speeds[1]
            self._set_wheels(left, right)
            return p.Empty()
        if isinstance(req, p.SetVelocity):
            if req.vy != 0.0:
                # A differential base cannot move sideways.
                raise _Refusal(p.ErrorCode.BAD_ARGUMENTS)
            half = cfg.wheel_track / 2
            self._set_wheels(req.vx - req.omega * half, req.vx + req.omega * half)
            reply = p.DeadReckon(st.dr_x, st.dr_y, st.dr_theta, 0x02 if st.stalled else 0)
            st.dr_x = st.dr_y = st.dr_theta = 0.0
            return reply
        if isinstance(req, p.PollBaseCommand):
            return p.PendingBaseCommand(st.pending_base_command)
        if isinstance(req, p.AnswerBaseCommand):
            st.pending_base_command = None
            return p.Empty()
        if isinstance(req, p.SendEvent):
            self.events.append(f"event 0x{req.event:02X} from the navigation side")
            return p.Empty()
        if isinstance(req, p.GetHealth):
            return p.Health(self.health_flags(), len(st.errors))
        if isinstance(req, p.GetHealthError):
            if req.index >= len(st.errors):
                raise _Refusal(p.ErrorCode.BAD_ARGUMENTS)
            code, msg = st.errors[req.index]
            return p.HealthError(code, msg)
        if isinstance(req, p.ClearHealthError):
            if not any(c == req.code for c, _ in st.errors):
                raise _Refusal(p.ErrorCode.BAD_ARGUMENTS)
            self._clear_error(req.code)
            return p.Empty()
        if isinstance(req, p.SetUvLamp):
            st.uv_lamp = req.on
            return p.Empty()
        if isinstance(req, p.SetAtomiser):
            if req.level > 0 and st.tank_ml <= 0.0:
                self._raise_error(p.HealthErrorCode.TANK_EMPTY, "disinfectant tank empty")
                raise _Refusal(p.ErrorCode.OPERATION_FAILED)
            st.atomiser = req.level
            return p.Empty()
        if isinstance(req, p.SetFan):
            st.fan = req.level
            return p.Empty()
        if isinstance(req, p.GetPayloadStatus):
            return p.PayloadStatus(st.uv_lamp, st.atomiser, st.fan, self.tank_percent)
        if isinstance(req, p.GetEnvData):
            return p.EnvData(self.tank_percent, st.temperature_c, st.humidity, st.pm2_5, st.tvoc_ppb)
        if isinstance(req, p.GetPowerData):
            return p.PowerData(st.voltage, self._current(), self.battery_percent, self._power_flags())
        if isinstance(req, p.GetImuData):
            return p.ImuData(st.gyro_rate, st.gyro_yaw, st.gyro_samples)
        if isinstance(req, p.GetButtons):
            return p.Buttons(st.buttons)
        if isinstance(req, p.SetLeds):
            st.leds = (req.mode, req.red, req.green, req.blue)
            return p.Empty()
        if isinstance(req, p.Beep):
            self.events.append(f"beep {req.frequency_hz} Hz for {req.duration_s:.2f} s")
            return p.Empty()
        raise _Refusal(p.ErrorCode.NOT_SUPPORTED)

    def _set_wheels(self, left: float, right: float) -> None:
        vmax = self.config.max_wheel_speed
        self.state.set_left = max(-vmax, min(vmax, left))
        self.state.set_right = max(-vmax, min(vmax, right))

    # ---------------------------------------------------------------------------------------
    # Firmware and physics
    # ---------------------------------------------------------------------------------------

    def step(self, now: float, max_dt: float = 0.005) -> None:
        """Advance to ``now`` in sub-steps of at most ``max_dt`` (the PID's period)."""
        if now - self._now > 5.0:
            # The owner was away (a paused process): do not replay minutes of physics in a burst.
            log.warning("board clock jumped %.1f s; skipping ahead", now - self._now)
            self._now = now - 5.0
        while self._now < now:
            dt = min(max_dt, now - self._now)
            self._tick(dt)
            self._now += dt
        self._flush_housekeeping()

    def _tick(self, dt: float) -> None:
        st, cfg = self.state, self.config
        # Link watchdog: only CTRL_BUS requests count (SYNC and ECHO do not).
        if (
            not st.watchdog_tripped
            and st.last_ctrl_bus is not None
            and self._now + dt - st.last_ctrl_bus > cfg.watchdog
        ):
            st.watchdog_tripped = True
            st.watchdog_trips += 1
            st.set_left = st.set_right = 0.0
            self._raise_error(p.HealthErrorCode.CORE_DISCONNECTED, "core disconnected")
            self.events.append(f"link watchdog: no request for {cfg.watchdog:.1f} s, wheels stopped")
        if st.watchdog_tripped:
            st.set_left = st.set_right = 0.0
        if st.buttons & p.Button.ESTOP:  # the button cuts the motors and the payload in hardware
            st.set_left = st.set_right = 0.0
            st.uv_lamp, st.atomiser, st.fan = False, 0, 0

        if st.v_left == 0.0 and st.v_right == 0.0 and st.set_left == 0.0 and st.set_right == 0.0:
            # Standing still with nothing to do: only the slow housekeeping runs (and the gyro,
            # which at rest reads its bias).
            st.true_v = st.true_w = 0.0
            st.gyro_rate = cfg.gyro_bias
            if cfg.gyro_bias:
                st.gyro_yaw = (st.gyro_yaw + cfg.gyro_bias * dt + math.pi) % (2 * math.pi) - math.pi
            st.gyro_samples += 1
            self._housekeeping(dt)
            return

        # Per-wheel speed loop with stop-before-reverse; a zero set-point is a stop.
        speeds = []
        for i, (v, target) in enumerate(((st.v_left, st.set_left), (st.v_right, st.set_right))):
            pid = self._pid[i]
            goal = 0.0 if target == 0.0 or (v * target < 0 and abs(v) > 0.001) else target
            if goal == 0.0 and abs(v) < 1e-3:
                pid.reset()
                speeds.append(0.0)
                continue
            duty = pid.update((goal - v) / cfg.max_wheel_speed)
            # Motor: first-order response of speed to duty.
            v_next = v + (duty * cfg.max_wheel_speed - v) * min(1.0, dt / cfg.motor_tau)
            if goal == 0.0 and v_next * v <= 0.0:
                # Braking ends at standstill: a stop never turns the wheel the other way.
                pid.reset()
                v_next = 0.0
            speeds.append(v_next)
        vl, vr = speeds

        # Encoders count wheel rotation at the nominal radius; the floor sees the true radius
        # (wheel-scale error) and loses whatever slips.
        enc_l, enc_r = vl * dt, vr * dt
        true_l = enc_l * cfg.wheel_scale[0] * (1.0 - self.slip[0])
        true_r = enc_r * cfg.wheel_scale[1] * (1.0 - self.slip[1])
        th = st.theta
        dx_w, dy_w, dth = _arc(th, (true_l + true_r) / 2, (true_r - true_l) / cfg.wheel_track)
        nx, ny = st.x + dx_w, st.y + dy_w
        there = self.floor.clearance(nx, ny) if (dx_w or dy_w) else math.inf
        if there < cfg.radius and there < self.floor.clearance(st.x, st.y):
            # The body hit something: it stops, the bumper on that side fires, the wheels stall.
            side = self._contact_side(nx, ny)
            st.bumped_left = side <= 0
            st.bumped_right = side >= 0
            st.stalled = True
            st.v_left = st.v_right = 0.0
            st.set_left = st.set_right = 0.0
            st.true_v = st.true_w = 0.0
            for pid in self._pid:
                pid.reset()
            self._housekeeping(dt)
            return
        if (st.bumped_left or st.bumped_right) and there > self.floor.clearance(st.x, st.y):
            # A bump switch stays pressed while the body rests against the wall; moving away releases it.
            st.bumped_left = st.bumped_right = False
        st.stalled = False
        st.v_left, st.v_right = vl, vr
        st.dist_left += enc_l
        st.dist_right += enc_r
        st.x, st.y = nx, ny
        st.theta = (th + dth + math.pi) % (2 * math.pi) - math.pi
        st.true_v = (true_l + true_r) / (2 * dt)
        st.true_w = dth / dt
        # The gyro sees the true turn rate, plus its bias and noise.
        noise = self._rng.gauss(0.0, cfg.gyro_noise) if cfg.gyro_noise else 0.0
        st.gyro_rate = st.true_w + cfg.gyro_bias + noise
        st.gyro_yaw = (st.gyro_yaw + st.gyro_rate * dt + math.pi) % (2 * math.pi) - math.pi
        st.gyro_samples += 1
        # Dead reckoning from the encoders, in the frame of the last SET_V_AND_GET_DEADRECKON call.
        lx, ly, lth = _arc(st.dr_theta, (enc_l + enc_r) / 2, (enc_r - enc_l) / cfg.wheel_track)
        st.dr_x += lx
        st.dr_y += ly
        st.dr_theta += lth
        self._housekeeping(dt)

    def _housekeeping(self, dt: float) -> None:
        """Battery and payload change slowly: update them once per ``step`` call, not every tick."""
        self._slow_dt += dt

    def _flush_housekeeping(self) -> None:
        if self._slow_dt > 0.0:
            self._battery(self._slow_dt, 0.0)
            self._payload(self._slow_dt)
            self._slow_dt = 0.0

    def _contact_side(self, x: float, y: float) -> int:
        """-1 if the nearest wall is to the robot's left, +1 to its right, 0 ahead."""
        st = self.state
        ahead_left = self.floor.ray(x, y, st.theta + 0.6, self.config.radius * 1.5)
        ahead_right = self.floor.ray(x, y, st.theta - 0.6, self.config.radius * 1.5)
        if math.isinf(ahead_left) and math.isinf(ahead_right):
            return 0
        if abs(ahead_left - ahead_right) < 0.02:
            return 0
        return -1 if ahead_left < ahead_right else 1

    def _current(self) -> float:
        st, cfg = self.state, self.config
        if st.charging:
            return cfg.charge_current
        load = (abs(st.v_left) + abs(st.v_right)) / (2 * cfg.max_wheel_speed)
        payload = 0.8 * st.uv_lamp + 0.3 * st.atomiser + 0.15 * st.fan
        return -(cfg.idle_current + cfg.drive_current * load + payload)

    def _battery(self, dt: float, load: float) -> None:
        st, cfg = self.state, self.config
        st.external_power = cfg.dock is not None and math.hypot(st.x - cfg.dock[0], st.y - cfg.dock[1]) < 0.1
        st.charging = st.external_power and st.voltage < cfg.battery_full_v
        span = cfg.battery_full_v - cfg.battery_empty_v
        # Linear charge model: full span over the capacity in amp-seconds.
        dv = self._current() * dt / (cfg.battery_capacity_ah * 3600) * span
        st.voltage = max(cfg.battery_empty_v - 0.5, min(cfg.battery_full_v, st.voltage + dv))
        if self.battery_percent < 10:
            self._raise_error(p.HealthErrorCode.BATTERY_LOW, "battery below 10 %")

    def _payload(self, dt: float) -> None:
        st, cfg = self.state, self.config
        if st.atomiser:
            st.tank_ml = max(0.0, st.tank_ml - cfg.atomiser_ml_per_s[st.atomiser] * dt)
            st.humidity = min(95.0, st.humidity + 0.02 * st.atomiser * dt)
            if st.tank_ml <= 0.0:
                st.atomiser = 0
                self._raise_error(p.HealthErrorCode.TANK_EMPTY, "disinfectant tank empty")
                self.events.append("tank empty: atomiser switched off")
        else:
            st.humidity = max(35.0, st.humidity - 0.005 * dt)
        if st.fan:  # the HEPA filter clears the air faster at a higher level
            st.pm2_5 = max(2.0, st.pm2_5 - 0.025 * st.fan * dt)

    # ---------------------------------------------------------------------------------------
    # Readings
    # ---------------------------------------------------------------------------------------

    @property
    def now(self) -> float:
        return self._now

    def start_clock(self, now: float) -> None:
        """Set the firmware's time base (before serving), without simulating the time before it."""
        self._now = now

    @property
    def battery_percent(self) -> int:
        cfg = self.config
        frac = (self.state.voltage - cfg.battery_empty_v) / (cfg.battery_full_v - cfg.battery_empty_v)
        return max(0, min(100, round(100 * frac)))

    @property
    def tank_percent(self) -> int:
        return max(0, min(100, round(100 * self.state.tank_ml / self.config.tank_ml)))

    def _power_flags(self) -> int:
        st = self.state
        flags = 0
        if st.charging:
            flags |= p.PowerFlag.CHARGING
        if st.external_power:
            flags |= p.PowerFlag.EXTERNAL_POWER | p.PowerFlag.ON_DOCK
        return flags

    def ultrasonic(self) -> float:
        """Front ultrasonic in metres; 0 when no echo inside its range."""
        st, cfg = self.state, self.config
        lo, hi = cfg.ultrasonic_range
        sx = st.x + cfg.radius * math.cos(st.theta)
        sy = st.y + cfg.radius * math.sin(st.theta)
        # The nearest reflector inside the cone (9 rays), walls and other robots alike.
        half = cfg.ultrasonic_cone / 2
        d = min(self.floor.rays(sx, sy, [st.theta - half + i * half / 4 for i in range(9)], hi))
        if math.isinf(d):
            return 0.0
        return max(lo, d + self._rng.gauss(0.0, cfg.ultrasonic_noise))

    def cliff_sensors(self) -> tuple[bool, bool]:
        st, cfg = self.state, self.config
        out = []
        for side in (1, -1):
            a = st.theta + side * 0.5
            out.append(
                self.floor.over_cliff(st.x + cfg.cliff_offset * math.cos(a), st.y + cfg.cliff_offset * math.sin(a))
            )
        return out[0], out[1]

    def bumper_bitmap(self) -> int:
        st = self.state
        bits = ALL_CLEAR
        cliff_l, cliff_r = self.cliff_sensors()
        for bit, hit in (
            (BUMPER_LEFT, st.bumped_left),
            (BUMPER_RIGHT, st.bumped_right),
            (CLIFF_LEFT, cliff_l),
            (CLIFF_RIGHT, cliff_r),
        ):
            if hit:
                bits &= ~(1 << bit)
        return bits & 0xFFFF_FFFF

    def health_flags(self) -> int:
        flags = 0
        for code, _ in self.state.errors:
            flags |= p.HealthFlag.ERROR if code in (p.HealthErrorCode.MOTOR_STALL,) else p.HealthFlag.WARNING
        return flags

    def _raise_error(self, code: int, message: str) -> None:
        if not any(c == code for c, _ in self.state.errors):
            self.state.errors.append((code, message))

    def _clear_error(self, code: int) -> None:
        self.state.errors = [(c, m) for c, m in self.state.errors if c != code]

    # ---------------------------------------------------------------------------------------
    # Things a person does to the robot
    # ---------------------------------------------------------------------------------------

    def press(self, buttons: int) -> None:
        """Press buttons (Buttons bits); HOME also queues a go-home base command."""
        self.state.buttons |= buttons
        if buttons & p.Button.HOME:
            self.state.pending_base_command = p.PendingCommandCode.GO_HOME

    def drive(self, vx: float, omega: float, now: float) -> None:
        """Set the body velocity directly, as a CTRL_BUS velocity request would (feeds the watchdog).

        For lockstep runs whose stand-in drivers need no byte link; agents always go through bytes.
        """
        self.step(now)
        st = self.state
        st.last_ctrl_bus = now
        st.watchdog_tripped = False
        half = self.config.wheel_track / 2
        self._set_wheels(vx - omega * half, vx + omega * half)

    def press_home(self) -> None:
        """Someone presses the home button: the base then asks the master to go home."""
        self.press(_HOME_BUTTON)

    def release(self, buttons: int) -> None:
        self.state.buttons &= ~buttons

    def refill_tank(self) -> None:
        self.state.tank_ml = self.config.tank_ml
        self._clear_error(p.HealthErrorCode.TANK_EMPTY)

    def drain_tank(self) -> None:
        self.state.tank_ml = 0.0


def _arc(theta: float, ds: float, dth: float) -> tuple[float, float, float]:
    """Displacement (dx, dy, dtheta) of a differential drive moving ds along an arc turning dth,
    starting at heading theta (exact, not Euler)."""
    if abs(dth) < 1e-9:
        return ds * math.cos(theta), ds * math.sin(theta), dth
    r = ds / dth
    return r * (math.sin(theta + dth) - math.sin(theta)), -r * (math.cos(theta + dth) - math.cos(theta)), dth


class _Refusal(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(p.ErrorCode.describe(code))
        self.code = code
