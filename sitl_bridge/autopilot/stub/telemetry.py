"""What the stub tells the world over MAVLink: one function per message, PX4's field choices.

Each function takes the autopilot (and what else it needs) and returns the message's fields
as a dict; `MessagePacker` turns that into a MAVLink 2 frame. Times are simulated time
(`time_boot_ms` = the autopilot's clock, the HIL_SENSOR time_usec).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from sitl_bridge import mavlink

from .modes import MainMode
from .vec import quat_to_euler, quat_yaw

if TYPE_CHECKING:
    from .autopilot import StubAutopilot

d = mavlink.dialect

MAV_TYPE_QUADROTOR = 2
MAV_AUTOPILOT_PX4 = 12
# SYS_STATUS sensor bits MAVSDK reads for health (protocol sheet B5)
SENSORS_READY = (
    d.MAV_SYS_STATUS_SENSOR_3D_GYRO | d.MAV_SYS_STATUS_SENSOR_3D_ACCEL | d.MAV_SYS_STATUS_SENSOR_3D_MAG
    | d.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | d.MAV_SYS_STATUS_SENSOR_GPS
    | d.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | d.MAV_SYS_STATUS_AHRS | d.MAV_SYS_STATUS_PREARM_CHECK
)
# PX4 v1.16.0 release: major.minor.patch.type (255 = official)
PX4_FLIGHT_SW_VERSION = (1 << 24) | (16 << 16) | (0 << 8) | 255
CAPABILITIES = (
    d.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | d.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | d.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED | d.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | d.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
)
BATTERY_CELL_MV = 4050
_UINT16_MAX = 65535
_INT16_MAX = 32767


class MessagePacker:
    """Frames messages given as field dicts (arrays as sequences), for one sender."""

    def __init__(self, system_id: int, component_id: int) -> None:
        self.encoder = mavlink.FrameEncoder(system_id, component_id)
        # per class without arrays: (all fields zero, getter of the wire-order values);
        # None for a class with arrays, which takes the general path over its layout
        self._flat: dict[type, tuple[dict[str, Any], Callable[[dict[str, Any]], tuple]] | None] = {}
        self._layouts: dict[type, list[tuple[str, int]]] = {}

    def pack(self, cls: type, **fields: Any) -> bytes:
        """One MAVLink 2 frame of message class `cls`; missing fields are 0."""
        return self.pack_fields(cls, fields)

    def pack_fields(self, cls: type, fields: dict[str, Any]) -> bytes:
        """`pack` for a fields dict already built (the streams' builders return one)."""
        flat = self._flat.get(cls, ())
        if flat == ():
            flat = self._learn(cls)
        if flat is not None:   # no arrays: the common, fast case (the getter runs in C)
            zeros, getter = flat
            try:
                values = getter(fields)  # the streams' builders give every field
            except KeyError:
                values = getter({**zeros, **fields})  # missing fields are 0
            return self.encoder.pack(cls, *values)
        values: list[Any] = []
        for name, length in self._layouts[cls]:
            value = fields.get(name, 0)
            if length:
                items = list(value) if value != 0 else []
                items += [0] * (length - len(items))
                values.extend(items[:length])
            else:
                values.append(value)
        return self.encoder.pack(cls, *values)

    def _learn(self, cls: type) -> tuple[dict[str, Any], Callable[[dict[str, Any]], tuple]] | None:
        types = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
        # char arrays travel as one bytes value ("16s"), other arrays element by element
        layout = [(name, 0 if types[name] == "char" else length)
                  for name, length in zip(cls.ordered_fieldnames, cls.array_lengths, strict=True)]
        self._layouts[cls] = layout
        flat = None
        if not any(length for _, length in layout):
            names = [name for name, _ in layout]
            getter = operator.itemgetter(*names)
            # a one-field message's getter returns the value itself: always hand back a tuple
            flat = ({name: 0 for name in names}, getter if len(names) > 1 else lambda f: (getter(f),))
        self._flat[cls] = flat
        return flat


def time_boot_ms(ap: StubAutopilot) -> int:
    """The autopilot's clock in ms (uint32 wrap like PX4)."""
    return (ap.time_us // 1000) & 0xFFFFFFFF


def _base_mode(ap: StubAutopilot) -> int:
    mode = d.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if ap.armed:
        mode |= d.MAV_MODE_FLAG_SAFETY_ARMED
    if ap.commander.main_mode in (MainMode.AUTO, MainMode.OFFBOARD):
        mode |= d.MAV_MODE_FLAG_AUTO_ENABLED | d.MAV_MODE_FLAG_GUIDED_ENABLED | d.MAV_MODE_FLAG_STABILIZE_ENABLED
    if ap.params["SYS_HITL"]:
        mode |= d.MAV_MODE_FLAG_HIL_ENABLED
    return mode


def heartbeat(ap: StubAutopilot) -> dict[str, Any]:
    """HEARTBEAT: quadrotor, PX4, PX4 custom_mode, armed flag, standby/active/critical."""
    if ap.commander.failsafe_active and ap.armed:
        status = d.MAV_STATE_CRITICAL
    else:
        status = d.MAV_STATE_ACTIVE if ap.armed else d.MAV_STATE_STANDBY
    return dict(type=MAV_TYPE_QUADROTOR, autopilot=MAV_AUTOPILOT_PX4, base_mode=_base_mode(ap),
                custom_mode=ap.custom_mode, system_status=status, mavlink_version=3)


def sys_status(ap: StubAutopilot) -> dict[str, Any]:
    """SYS_STATUS: sensors present/enabled/healthy; GPS and prearm health follow the estimate."""
    est = ap.estimate
    health = SENSORS_READY
    if not (est.position_valid and est.gps_fix_type >= 3):
        health &= ~d.MAV_SYS_STATUS_SENSOR_GPS
    if not (est.position_valid and est.attitude_valid):
        health &= ~(d.MAV_SYS_STATUS_PREARM_CHECK | d.MAV_SYS_STATUS_AHRS)
    cells = int(ap.params["BAT1_N_CELLS"]) if "BAT1_N_CELLS" in ap.params else 4
    # Geofence "healthy" (not breached): the stub has no fence, so there is nothing to breach;
    # without the bit ground stations such as MAVProxy report a fence breach.
    health |= d.MAV_SYS_STATUS_GEOFENCE
    return dict(onboard_control_sensors_present=SENSORS_READY, onboard_control_sensors_enabled=SENSORS_READY,
                onboard_control_sensors_health=health, load=200, voltage_battery=cells * BATTERY_CELL_MV,
                current_battery=-1, battery_remaining=100)


def extended_sys_state(ap: StubAutopilot) -> dict[str, Any]:
    """EXTENDED_SYS_STATE: multicopter, MAV_LANDED_STATE."""
    return dict(vtol_state=d.MAV_VTOL_STATE_MC, landed_state=int(ap.landed_state))


# The 50 Hz builders below (attitude, attitude_quaternion, global_position_int) read the
# estimate once and the clock straight from the commander: they run several times per
# simulated second per link.

def attitude(ap: StubAutopilot) -> dict[str, Any]:
    """ATTITUDE: Euler angles and body rates of the estimate."""
    est = ap.estimator.estimate
    roll, pitch, yaw = quat_to_euler(est.quaternion_ned_frd)
    p, q, r = est.angular_velocity_frd_rad_s
    return dict(time_boot_ms=(ap.commander.time_us // 1000) & 0xFFFFFFFF, roll=roll, pitch=pitch, yaw=yaw,
                rollspeed=p, pitchspeed=q, yawspeed=r)


def attitude_quaternion(ap: StubAutopilot) -> dict[str, Any]:
    """ATTITUDE_QUATERNION (w, x, y, z) of the estimate."""
    est = ap.estimator.estimate
    qw, qx, qy, qz = est.quaternion_ned_frd
    p, q, r = est.angular_velocity_frd_rad_s
    return dict(time_boot_ms=(ap.commander.time_us // 1000) & 0xFFFFFFFF, q1=qw, q2=qx, q3=qy, q4=qz,
                rollspeed=p, pitchspeed=q, yawspeed=r)


def local_position_ned(ap: StubAutopilot) -> dict[str, Any]:
    """LOCAL_POSITION_NED relative to the estimator's origin."""
    est = ap.estimator.estimate
    x, y, z = est.position_ned_m
    vx, vy, vz = est.velocity_ned_m_s
    return dict(time_boot_ms=(ap.commander.time_us // 1000) & 0xFFFFFFFF, x=x, y=y, z=z, vx=vx, vy=vy, vz=vz)


def _clamp_int(value: float, low: int, high: int) -> int:
    if value != value:
        return 0
    v = round(value)
    return low if v < low else high if v > high else v


_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1


def global_position_int(ap: StubAutopilot) -> dict[str, Any]:
    """GLOBAL_POSITION_INT: lat/lon degE7, AMSL and relative altitude mm, velocity cm/s, heading."""
    est = ap.estimator.estimate
    home = ap.commander.home
    alt = est.alt_amsl_m
    home_alt = home.alt_amsl_m if home else alt
    vx, vy, vz = est.velocity_ned_m_s
    heading_cdeg = round(math.degrees(quat_yaw(est.quaternion_ned_frd)) * 100.0) % 36000
    return dict(time_boot_ms=(ap.commander.time_us // 1000) & 0xFFFFFFFF,
                lat=_clamp_int(est.lat_deg * 1e7, -900_000_000, 900_000_000),
                lon=_clamp_int(est.lon_deg * 1e7, -1_800_000_000, 1_800_000_000),
                alt=_clamp_int(alt * 1000.0, _INT32_MIN, _INT32_MAX),
                relative_alt=_clamp_int((alt - home_alt) * 1000.0, _INT32_MIN, _INT32_MAX),
                vx=_clamp_int(vx * 100, -_INT16_MAX, _INT16_MAX), vy=_clamp_int(vy * 100, -_INT16_MAX, _INT16_MAX),
                vz=_clamp_int(vz * 100, -_INT16_MAX, _INT16_MAX), hdg=heading_cdeg)


def gps_raw_int(ap: StubAutopilot) -> dict[str, Any]:
    """GPS_RAW_INT from the last GPS fix the autopilot received."""
    est = ap.estimate
    vx, vy, _ = est.velocity_ned_m_s
    speed = math.hypot(vx, vy)
    cog = int(round(math.degrees(math.atan2(vy, vx)) * 100.0)) % 36000 if speed > 0.1 else _UINT16_MAX
    return dict(time_usec=ap.time_us, fix_type=est.gps_fix_type,
                lat=_clamp_int(est.lat_deg * 1e7, -900_000_000, 900_000_000),
                lon=_clamp_int(est.lon_deg * 1e7, -1_800_000_000, 1_800_000_000),
                alt=_clamp_int(est.alt_amsl_m * 1000.0, -(2**31), 2**31 - 1),
                eph=_clamp_int(est.gps_eph_cm, 0, _UINT16_MAX), epv=_clamp_int(est.gps_epv_cm, 0, _UINT16_MAX),
                vel=_clamp_int(speed * 100.0, 0, _UINT16_MAX), cog=cog, satellites_visible=est.gps_satellites)


def home_position(ap: StubAutopilot) -> dict[str, Any] | None:
    """HOME_POSITION, or None before home is set."""
    home = ap.home
    if home is None:
        return None
    x, y, z = home.position_ned_m
    half = 0.5 * home.yaw_rad
    return dict(latitude=_clamp_int(home.lat_deg * 1e7, -900_000_000, 900_000_000),
                longitude=_clamp_int(home.lon_deg * 1e7, -1_800_000_000, 1_800_000_000),
                altitude=_clamp_int(home.alt_amsl_m * 1000.0, -(2**31), 2**31 - 1),
                x=x, y=y, z=z, q=(math.cos(half), 0.0, 0.0, math.sin(half)), time_usec=ap.time_us)


def battery_status(ap: StubAutopilot) -> dict[str, Any]:
    """BATTERY_STATUS: a full, steady pack (the sim does not model energy)."""
    cells = int(ap.params["BAT1_N_CELLS"]) if "BAT1_N_CELLS" in ap.params else 4
    voltages = [BATTERY_CELL_MV] * min(cells, 10) + [_UINT16_MAX] * (10 - min(cells, 10))
    return dict(id=0, battery_function=d.MAV_BATTERY_FUNCTION_ALL, type=d.MAV_BATTERY_TYPE_LIPO,
                temperature=_INT16_MAX, voltages=voltages, current_battery=-1, current_consumed=-1,
                energy_consumed=-1, battery_remaining=100, charge_state=d.MAV_BATTERY_CHARGE_STATE_OK)


def autopilot_version(ap: StubAutopilot) -> dict[str, Any]:
    """AUTOPILOT_VERSION: PX4 v1.16.0 capabilities relevant to MAVSDK."""
    return dict(capabilities=CAPABILITIES, flight_sw_version=PX4_FLIGHT_SW_VERSION,
                middleware_sw_version=PX4_FLIGHT_SW_VERSION, os_sw_version=0, board_version=0,
                vendor_id=0, product_id=0, uid=0x5354554200000000 + ap.instance)


# message id -> (message class, field builder): what SET_MESSAGE_INTERVAL / REQUEST_MESSAGE can serve
BUILDERS = {
    d.MAVLINK_MSG_ID_HEARTBEAT: (d.MAVLink_heartbeat_message, heartbeat),
    d.MAVLINK_MSG_ID_SYS_STATUS: (d.MAVLink_sys_status_message, sys_status),
    d.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: (d.MAVLink_extended_sys_state_message, extended_sys_state),
    d.MAVLINK_MSG_ID_ATTITUDE: (d.MAVLink_attitude_message, attitude),
    d.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: (d.MAVLink_attitude_quaternion_message, attitude_quaternion),
    d.MAVLINK_MSG_ID_LOCAL_POSITION_NED: (d.MAVLink_local_position_ned_message, local_position_ned),
    d.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: (d.MAVLink_global_position_int_message, global_position_int),
    d.MAVLINK_MSG_ID_GPS_RAW_INT: (d.MAVLink_gps_raw_int_message, gps_raw_int),
    d.MAVLINK_MSG_ID_HOME_POSITION: (d.MAVLink_home_position_message, home_position),
    d.MAVLINK_MSG_ID_BATTERY_STATUS: (d.MAVLink_battery_status_message, battery_status),
    d.MAVLINK_MSG_ID_AUTOPILOT_VERSION: (d.MAVLink_autopilot_version_message, autopilot_version),
}

# default stream rates in Hz of simulated time: PX4's offboard ("onboard") link and GCS link
ONBOARD_RATES_HZ = {
    d.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    d.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    d.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    d.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    d.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50.0,
    d.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    d.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 50.0,
    d.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    d.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    d.MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
}
CLIENT_RATES_HZ = {
    d.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    d.MAVLINK_MSG_ID_SYS_STATUS: 5.0,
    d.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    d.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    d.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 50.0,
    d.MAVLINK_MSG_ID_GPS_RAW_INT: 10.0,
    d.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
}
"""The API link's streams with `api_streams="client"`: only what `sitl_bridge.client` reads, the
set and rates px4_params/px4-rc.mavlink gives PX4 for it (the Gymnasium env's choice: about half
the messages of `ONBOARD_RATES_HZ`, so half the packing here and the parsing in MAVSDK)."""
API_STREAMS = {"onboard": ONBOARD_RATES_HZ, "client": CLIENT_RATES_HZ}
"""The API link's stream sets by name (`MavlinkApi` api_streams)."""
GCS_RATES_HZ = {
    d.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    d.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    d.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    d.MAVLINK_MSG_ID_ATTITUDE: 20.0,
    d.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 5.0,
    d.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    d.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
    d.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    d.MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
}
