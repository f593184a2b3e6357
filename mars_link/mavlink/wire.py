"""MAVLink encoding of the world/unit/coordinator messages (the boundary of every SITL link).

| message | MAVLink | link |
|---|---|---|
| SensorPacket.imu | HIL_SENSOR (world -> unit), HIGHRES_IMU (unit -> coordinator) | accel, gyro float32, time_usec |
| SensorPacket.position | ODOMETRY, estimator_type MOCAP, frames LOCAL_NED (q unused) | mocap-grade position and velocity of the unit centre, NED |
| SensorPacket.truth | ODOMETRY, estimator_type NAIVE, frames LOCAL_NED (velocity in NED) | ground truth, only with sensor noise off |
| RotorCommand | SET_ACTUATOR_CONTROL_TARGET, group 0, controls[0..3] | thrust as a fraction of `full_scale_thrust_n` |
| RotorCommand.latch_setpoint | same message, controls[4] | the latches to OPEN, as a bit mask 0..15 (0: all engaged) |
| ActuatorOutput | HIL_ACTUATOR_CONTROLS, controls[0..3], flags = LOCKSTEP | same scale; controls[4]: latches open, as above |
| SensorPacket.latches | NAMED_VALUE_INT "LATCH" (world -> unit -> coordinator) | the latched sides, bit mask 0..15 |
| SensorPacket.battery | BATTERY_STATUS (world -> unit -> coordinator), before the packet's frames | pack mV in voltages[0], cA, remaining % (the unit's) |
| SensorPacket.gps | HIL_GPS (world -> unit, forwarded as is to the coordinator) | fix 3D, lat/lon degE7 and alt mm AMSL around the home, vn/ve/vd cm/s, vel, cog, eph/epv (cm, as PX4 reads them), satellites |
| SensorPacket.baro, .mag | HIL_SENSOR / HIGHRES_IMU abs_pressure (hPa), pressure_alt (m), xmag..zmag (gauss), their fields_updated bits | the gps profile's barometer and magnetometer |

The latch sensor is sent when it changes (and with a unit's first packet), in the same datagram and
before the packet's IMU frame; receivers hold the last value (`LatchSensor`). The latch setpoint rides
every rotor command as the mask of latches to open, so an all-zero control (any stock sender) keeps
them engaged.

A sensor packet travels as its optional position, truth and GNSS frames first and the IMU frame last; the
IMU frame's `fields_updated` carries two mars-link flags (bits 14, 15; unused by both messages) saying which of the optional
frames belong to it, so a receiver knows when a packet is complete (a HIL_GPS frame of the same time and
sender is attached when there is one: no bit is left in HIGHRES_IMU's 16), and a third (bit 13, also unused) saying
that the truth's body touches the ground (`RigidBodyState.on_ground`, which ODOMETRY has no field for).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.geo import WIRE_ORIGIN
from mars_link.core.gnss import course_cdeg, ground_speed_cmps
from mars_link.core.messages import LATCH_ALL, ActuatorOutput, BatterySample, RotorCommand, SensorPacket, f32
from mars_link.core.state import BaroSample, GpsSample, ImuSample, MagSample, PositionSample, RigidBodyState

FLAG_HAS_POSITION = 1 << 14
FLAG_HAS_TRUTH = 1 << 15
FLAG_ON_GROUND = 1 << 13
IMU_FIELDS = 0x3F  # xacc..zgyro updated
MAG_FIELDS = 0x1C0  # xmag..zmag updated
BARO_FIELDS = 0x200 | 0x800  # abs_pressure and pressure_alt updated
GPS_FIX_3D = 3
ACCEL_FIELDS, GYRO_FIELDS = 0x07, 0x38  # a failed accelerometer or gyro leaves its bits clear (sensor_failures)
HIL_ACTUATOR_CONTROLS_FLAGS_LOCKSTEP = 1
ARMED_CUSTOM_MODE = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


def usec(t_s: float) -> int:
    return int(round(t_s * 1e6))


def new_mav(system_id: int, component_id: int = 1) -> mavlink.MAVLink:
    """A pymavlink encoder/decoder with no file behind it (we do the I/O)."""
    mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    mav.robust_parsing = True
    return mav


# ----------------------------------------------------------------------------- sensor packets
def sensor_packet_messages(packet: SensorPacket, upstream: bool = False) -> list[mavlink.MAVLink_message]:
    """Messages for one packet; `upstream` = unit -> coordinator (HIGHRES_IMU instead of HIL_SENSOR)."""
    t = usec(packet.t_s)
    msgs: list[mavlink.MAVLink_message] = []
    flags = (ACCEL_FIELDS if packet.imu.accel_ok else 0) | (GYRO_FIELDS if packet.imu.gyro_ok else 0)
    if packet.position is not None:
        p = packet.position
        vel = [math.nan] * 3 if p.velocity_ned_mps is None else p.velocity_ned_mps
        msgs.append(_odometry(t, p.position_ned_m, (1.0, 0.0, 0.0, 0.0), vel, (math.nan,) * 3,
                              mavlink.MAV_ESTIMATOR_TYPE_MOCAP))
        flags |= FLAG_HAS_POSITION
    if packet.truth is not None:
        s = packet.truth
        msgs.append(_odometry(t, s.position_ned_m, s.quaternion_wxyz, s.velocity_ned_mps,
                              s.angular_velocity_frd_radps, mavlink.MAV_ESTIMATOR_TYPE_NAIVE))
        flags |= FLAG_HAS_TRUTH | (FLAG_ON_GROUND if s.on_ground else 0)
    if packet.gps is not None:
        msgs.append(gps_message(t, packet.gps))
    mag: tuple[float, ...] = (0.0, 0.0, 0.0)
    pressure, pressure_alt = 0.0, 0.0
    if packet.mag is not None:
        mag = tuple(map(float, packet.mag.field_frd_gauss))
        flags |= MAG_FIELDS
    if packet.baro is not None:
        pressure, pressure_alt = packet.baro.pressure_hpa, packet.baro.altitude_amsl_m
        flags |= BARO_FIELDS
    a, g = packet.imu.accel_frd_mps2, packet.imu.gyro_frd_radps
    cls = mavlink.MAVLink_highres_imu_message if upstream else mavlink.MAVLink_hil_sensor_message
    msgs.append(cls(t, *map(float, a), *map(float, g), *mag, pressure, 0.0, pressure_alt, 0.0, flags, 0))
    return msgs


def gps_message(t_usec: int, g: GpsSample) -> mavlink.MAVLink_message:
    """HIL_GPS as PX4's simulator sends it (3D fix; yaw 0: no dual-antenna heading)."""
    return mavlink.MAVLink_hil_gps_message(
        t_usec, GPS_FIX_3D, g.lat_e7, g.lon_e7, g.alt_mm, g.eph_cm, g.epv_cm, ground_speed_cmps(g.vel_ned_cmps),
        *g.vel_ned_cmps, course_cdeg(g.vel_ned_cmps), g.satellites, 0, 0)


def gps_from_message(m, t_s: float) -> GpsSample:
    return GpsSample(t_s, m.get_srcSystem(), m.lat, m.lon, m.alt, (m.vn, m.ve, m.vd), m.eph, m.epv,
                     m.satellites_visible)


def _odometry(t_usec: int, pos, q, vel, rates, estimator_type: int) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_odometry_message(
        t_usec, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_NED,
        *map(float, pos), [float(x) for x in q], *map(float, vel), *map(float, rates),
        [math.nan] + [0.0] * 20, [math.nan] + [0.0] * 20, 0, estimator_type, 100,
    )


@dataclass
class SensorFrames:
    """One sensor packet as received: its IMU frame (HIL_SENSOR or HIGHRES_IMU) and the optional
    position (ODOMETRY, MOCAP) and truth (ODOMETRY, NAIVE) frames of the same time and sender."""

    imu: mavlink.MAVLink_message
    position: mavlink.MAVLink_message | None = None
    truth: mavlink.MAVLink_message | None = None
    gps: mavlink.MAVLink_message | None = None  # HIL_GPS

    def packet(self) -> SensorPacket:
        m, unit = self.imu, self.imu.get_srcSystem()
        t_s = m.time_usec / 1e6
        pos = None
        if (p := self.position) is not None:
            vel = np.array([p.vx, p.vy, p.vz])
            pos = PositionSample(t_s, unit, np.array([p.x, p.y, p.z]), None if np.isnan(vel).any() else vel)
        truth = None
        if (s := self.truth) is not None:
            truth = RigidBodyState(t_s, np.array([s.x, s.y, s.z]), np.array([s.vx, s.vy, s.vz]),
                                   np.array(s.q, dtype=float), np.array([s.rollspeed, s.pitchspeed, s.yawspeed]),
                                   on_ground=bool(m.fields_updated & FLAG_ON_GROUND))
        flags = m.fields_updated
        imu = ImuSample(t_s, unit, np.array([m.xgyro, m.ygyro, m.zgyro]), np.array([m.xacc, m.yacc, m.zacc]),
                        flags & ACCEL_FIELDS == ACCEL_FIELDS, flags & GYRO_FIELDS == GYRO_FIELDS)
        gps = None if self.gps is None else gps_from_message(self.gps, t_s)
        baro = BaroSample(t_s, unit, m.abs_pressure, m.pressure_alt) if flags & BARO_FIELDS == BARO_FIELDS else None
        mag = MagSample(t_s, unit, np.array([m.xmag, m.ymag, m.zmag])) if flags & MAG_FIELDS == MAG_FIELDS else None
        return SensorPacket(t_s, unit, imu, pos, truth, 0, gps, baro, mag)

    def upstream_messages(self) -> list[mavlink.MAVLink_message]:
        """What `sensor_packet_messages(self.packet(), upstream=True)` gives, built from the received
        fields directly (a unit forwards every sensor packet to the coordinator on the real-time
        path; no arrays in between)."""
        m, t = self.imu, self.imu.time_usec
        msgs = []
        flags = IMU_FIELDS
        if (p := self.position) is not None:
            vel = (p.vx, p.vy, p.vz)
            if not all(v == v for v in vel):  # any NaN: no velocity
                vel = (math.nan,) * 3
            msgs.append(_odometry(t, (p.x, p.y, p.z), (1.0, 0.0, 0.0, 0.0), vel, (math.nan,) * 3,
                                  mavlink.MAV_ESTIMATOR_TYPE_MOCAP))
            flags |= FLAG_HAS_POSITION
        if (s := self.truth) is not None:
            msgs.append(_odometry(t, (s.x, s.y, s.z), s.q, (s.vx, s.vy, s.vz), (s.rollspeed, s.pitchspeed, s.yawspeed),
                                  mavlink.MAV_ESTIMATOR_TYPE_NAIVE))
            flags |= FLAG_HAS_TRUTH | (m.fields_updated & FLAG_ON_GROUND)
        if (g := self.gps) is not None:
            msgs.append(mavlink.MAVLink_hil_gps_message(t, g.fix_type, g.lat, g.lon, g.alt, g.eph, g.epv, g.vel, g.vn,
                                                        g.ve, g.vd, g.cog, g.satellites_visible, g.id, g.yaw))
        flags |= m.fields_updated & (MAG_FIELDS | BARO_FIELDS)
        msgs.append(mavlink.MAVLink_highres_imu_message(t, m.xacc, m.yacc, m.zacc, m.xgyro, m.ygyro, m.zgyro,
                                                        m.xmag, m.ymag, m.zmag, m.abs_pressure, m.diff_pressure,
                                                        m.pressure_alt, m.temperature, flags, 0))
        return msgs


class SensorFrameAssembler:
    """Collects ODOMETRY and HIL_SENSOR (or HIGHRES_IMU) frames into SensorFrames: a packet's optional
    frames come first, its IMU frame last and its `fields_updated` flags say which must be there."""

    def __init__(self) -> None:
        self._position: dict[tuple[int, int], mavlink.MAVLink_message] = {}
        self._truth: dict[tuple[int, int], mavlink.MAVLink_message] = {}
        self._gps: dict[tuple[int, int], mavlink.MAVLink_message] = {}
        self.dropped_incomplete = 0

    def feed_frames(self, msg: mavlink.MAVLink_message) -> SensorFrames | None:
        kind = msg.get_type()
        if kind == "ODOMETRY":
            store = self._position if msg.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_MOCAP else self._truth
            store[(msg.get_srcSystem(), msg.time_usec)] = msg
        elif kind == "HIL_GPS":
            self._gps[(msg.get_srcSystem(), msg.time_usec)] = msg
        elif kind in ("HIL_SENSOR", "HIGHRES_IMU"):
            t = msg.time_usec
            key = (msg.get_srcSystem(), t)
            pos = self._position.pop(key, None) if self._position else None
            truth = self._truth.pop(key, None) if self._truth else None
            if (msg.fields_updated & FLAG_HAS_POSITION and pos is None) or (
                msg.fields_updated & FLAG_HAS_TRUTH and truth is None
            ):
                self.dropped_incomplete += 1
                return None
            gps = self._gps.pop(key, None) if self._gps else None
            self._prune(t)
            return SensorFrames(msg, pos, truth, gps)
        return None

    def _prune(self, t_usec: int) -> None:
        for store in (self._position, self._truth, self._gps):
            if store:
                for key in [k for k in store if k[1] < t_usec]:
                    del store[key]


class SensorPacketAssembler(SensorFrameAssembler):
    """SensorFrameAssembler that returns SensorPackets."""

    def feed(self, msg: mavlink.MAVLink_message) -> SensorPacket | None:
        frames = self.feed_frames(msg)
        return None if frames is None else frames.packet()


# ----------------------------------------------------------------------------- latches
LATCH_NAME = b"LATCH"


def latch_message(t_s: float, mask: int) -> mavlink.MAVLink_message:
    """A unit's latch sensor (NAMED_VALUE_INT "LATCH"): bit k set when side k holds a docked neighbour."""
    return mavlink.MAVLink_named_value_int_message(int(usec(t_s) // 1000) & 0xFFFFFFFF, LATCH_NAME, int(mask))


def latch_from_message(msg) -> int | None:
    """The latch mask of a NAMED_VALUE_INT "LATCH" (None: another name, or a value out of 0..15)."""
    name = msg.name.rstrip("\x00") if isinstance(msg.name, str) else msg.name.rstrip(b"\x00").decode("ascii", "replace")
    if name != "LATCH" or not 0 <= msg.value <= LATCH_ALL:
        return None
    return int(msg.value)


def latches_open(setpoint: int) -> float:
    """controls[4] of a rotor command or actuator output: the latches to open (0: all engaged)."""
    return float(LATCH_ALL & ~setpoint)


def latch_setpoint_of(control: float) -> int | None:
    """The latch setpoint carried by controls[4] (None: not a whole mask 0..15)."""
    if not (math.isfinite(control) and 0.0 <= control <= LATCH_ALL and control == int(control)):
        return None
    return LATCH_ALL & ~int(control)


class LatchSensor:
    """The last latch mask heard from each sender (the sensor is sent when it changes)."""

    def __init__(self) -> None:
        self.mask: dict[int, int] = {}

    def feed(self, msg) -> bool:
        """True if `msg` was a valid latch report (now held for its sender)."""
        value = latch_from_message(msg)
        if value is None:
            return False
        self.mask[msg.get_srcSystem()] = value
        return True


# ----------------------------------------------------------------------------- rotor commands
def rotor_command_message(cmd: RotorCommand, full_scale_n: float) -> mavlink.MAVLink_message:
    controls = [float(x) / full_scale_n for x in cmd.thrusts_n] + [latches_open(cmd.latch_setpoint)] + [0.0] * 3
    return mavlink.MAVLink_set_actuator_control_target_message(usec(cmd.t_s), 0, cmd.unit_id, 1, controls)


def rotor_command_from_message(msg, full_scale_n: float) -> RotorCommand:
    thrusts = np.array(msg.controls[:4], dtype=np.float32).astype(np.float64) * full_scale_n
    latch = latch_setpoint_of(msg.controls[4])
    return RotorCommand(msg.time_usec / 1e6, msg.target_system, thrusts, LATCH_ALL if latch is None else latch)


def actuator_output_message(out: ActuatorOutput, full_scale_n: float) -> mavlink.MAVLink_message:
    controls = [float(x) / full_scale_n for x in out.thrusts_n] + [latches_open(out.latch_setpoint)] + [0.0] * 11
    return mavlink.MAVLink_hil_actuator_controls_message(
        usec(out.t_s), controls, ARMED_CUSTOM_MODE, HIL_ACTUATOR_CONTROLS_FLAGS_LOCKSTEP
    )


def actuator_output_from_message(msg, full_scale_n: float) -> ActuatorOutput:
    thrusts = np.array(msg.controls[:4], dtype=np.float32).astype(np.float64) * full_scale_n
    latch = latch_setpoint_of(msg.controls[4])
    return ActuatorOutput(msg.time_usec / 1e6, msg.get_srcSystem(), thrusts, LATCH_ALL if latch is None else latch)


# ----------------------------------------------------------------------------- battery
def battery_status(mv: int, ca: int, pct: int, used_mah: int = -1,
                   state: int = mavlink.MAV_BATTERY_CHARGE_STATE_UNDEFINED) -> mavlink.MAVLink_message:
    """BATTERY_STATUS of one pack measured as a whole: its voltage in voltages[0] (MAVLink's rule when cells
    are not measured one by one), the other cells UINT16_MAX."""
    return mavlink.MAVLink_battery_status_message(
        0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 32767, [mv] + [65535] * 9, ca,
        used_mah, -1, pct, 0, state, [0] * 4, 0, 0)


def battery_report_message(b: BatterySample) -> mavlink.MAVLink_message:
    """A pack's sample: world -> unit (what its power module measures; remaining -1) and unit ->
    coordinator (with the unit's remaining estimate); in the same datagram as, and before, the sensor
    packet it belongs to."""
    return battery_status(round(b.voltage_v * 1000), round(b.current_a * 100),
                          -1 if b.remaining < 0 else round(b.remaining * 100))


def battery_from_message(msg) -> BatterySample | None:
    """The sample of a BATTERY_STATUS (None: no voltage or no current in it)."""
    v, i = msg.voltages[0], msg.current_battery
    if v == 65535 or i < 0:
        return None
    return BatterySample(v / 1000.0, i / 100.0, -1.0 if msg.battery_remaining < 0 else msg.battery_remaining / 100.0)


# ----------------------------------------------------------------------------- HIL_STATE_QUATERNION
def _int16(x: float) -> int:
    return int(max(-32767, min(32767, round(x))))


def hil_state_fields(s: RigidBodyState) -> tuple:
    """A unit centre's truth as HIL_STATE_QUATERNION's fields carry it: (quaternion, body rates, lat degE7,
    lon degE7, alt mm, vx, vy, vz cm/s, speed cm/s). Position on the spherical Earth the firmware assumes
    (`WIRE_ORIGIN`): 1e-7 deg is about 1.1 cm."""
    lat, lon, alt_mm = WIRE_ORIGIN.to_global_int(s.position_ned_m)
    v = s.velocity_ned_mps
    speed_cms = min(65535, int(round(float(np.linalg.norm(v)) * 100)))
    return ([float(x) for x in s.quaternion_wxyz], [float(x) for x in s.angular_velocity_frd_radps], lat, lon, alt_mm,
            _int16(v[0] * 100), _int16(v[1] * 100), _int16(v[2] * 100), speed_cms)


def hil_state_from_fields(time_usec: int, q, rates, lat: int, lon: int, alt_mm: int, vx: int, vy: int,
                          vz: int) -> RigidBodyState:
    """The state a unit's firmware takes from HIL_STATE_QUATERNION's fields (q finite, of norm near 1)."""
    quat = np.array(q, dtype=float)
    return RigidBodyState(time_usec * 1e-6, WIRE_ORIGIN.to_ned(lat * 1e-7, lon * 1e-7, alt_mm * 1e-3),
                          np.array([vx, vy, vz]) * 0.01, quat / np.linalg.norm(quat), np.array(rates, dtype=float))


def hil_state_received(s: RigidBodyState, time_usec: int) -> RigidBodyState:
    """What a unit's firmware holds after the world sent it `s` in HIL_STATE_QUATERNION (its float fields
    float32 on the wire): an in-process unit is given this, the numbers a SITL unit flies its own fail-safe on."""
    q, rates, lat, lon, alt_mm, vx, vy, vz, _ = hil_state_fields(s)
    return hil_state_from_fields(time_usec, f32(q), f32(rates), lat, lon, alt_mm, vx, vy, vz)
