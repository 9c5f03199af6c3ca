"""PX4-style cascaded multicopter control, one call per lockstep step.

position P -> velocity PID (acceleration, tilt and thrust limits, anti-windup) -> attitude P
on quaternions with yaw de-weighting -> body-rate PID -> normalised torque for the mixer.
The structure and the default gains mirror PX4's mc_pos_control (PositionControl.cpp),
mc_att_control (AttitudeControl.cpp) and mc_rate_control (RateControl.cpp). All vectors are
NED / FRD tuples (see `vec.py`). The math is written once as `@dual` functions on float64 state
and gain vectors (`sitl_bridge.jit`): the classes call them from Python, and the stub's per-step
kernels (`autopilot.py`, the fused `direct` loop) compile the same functions in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sitl_bridge.jit import dual

from .params import ParamTable
from .vec import (
    Quat,
    Vec3,
    clamp,
    quat_conjugate_multiply,
    quat_from_two_vectors,
    quat_multiply,
    quat_normalize,
    quat_rotate_inverse,
)

GRAVITY_M_S2 = 9.80665
_NAN = float("nan")

# The altitude floor: no setpoint may fly the vehicle into the ground. Below FLOOR_HEIGHT_M above
# the local origin (the stub's ground: the estimator's origin is where the vehicle stood), and
# earlier while it sinks faster than commanded (the height FLOOR_LOOKAHEAD_S ahead counts), the
# tilt limit narrows towards FLOOR_MIN_TILT_RAD, so the thrust holds the height before it pushes
# sideways. A commanded descent (a downward velocity setpoint, landing) is not resisted: it
# sinks as fast as asked and still reaches the ground.
FLOOR_HEIGHT_M = 3.0
FLOOR_LOOKAHEAD_S = 2.0
FLOOR_MIN_TILT_RAD = math.radians(10.0)


@dataclass
class Setpoint:
    """What the position controller tracks; NaN components are not controlled (never inf).

    position_ned_m and velocity_ned_m_s may both be set (velocity is then a feed-forward).
    """

    position_ned_m: Vec3 = (_NAN, _NAN, _NAN)
    velocity_ned_m_s: Vec3 = (_NAN, _NAN, _NAN)
    yaw_rad: float = _NAN
    yaw_rate_rad_s: float = _NAN
    max_velocity_up_m_s: float = _NAN      # overrides MPC_Z_VEL_MAX_UP (takeoff, landing)
    max_velocity_down_m_s: float = _NAN


@dual
def _limit_tilt(body_z: Vec3, max_tilt_rad: float) -> Vec3:
    """Rotate body_z towards world down (0, 0, 1) so its tilt is at most max_tilt_rad."""
    cos_tilt = clamp(body_z[2], -1.0, 1.0)
    if math.acos(cos_tilt) <= max_tilt_rad:
        return body_z
    horizontal = math.hypot(body_z[0], body_z[1])
    if horizontal < 1e-9:
        return (0.0, 0.0, 1.0)
    s = math.sin(max_tilt_rad) / horizontal
    return (body_z[0] * s, body_z[1] * s, math.cos(max_tilt_rad))


@dual
def floor_tilt(tilt_max_rad: float, height_m: float, sink_m_s: float, sink_setpoint_m_s: float) -> float:
    """The tilt limit under the altitude floor (see FLOOR_HEIGHT_M) at `height_m` above the
    origin, sinking at `sink_m_s` (NED z velocity) with `sink_setpoint_m_s` commanded."""
    unwanted_sink = sink_m_s - max(sink_setpoint_m_s, 0.0)
    ahead_m = height_m - max(unwanted_sink, 0.0) * FLOOR_LOOKAHEAD_S
    if ahead_m >= FLOOR_HEIGHT_M:
        return tilt_max_rad
    return min(tilt_max_rad, max(FLOOR_MIN_TILT_RAD, tilt_max_rad * max(ahead_m, 0.0) / FLOOR_HEIGHT_M))


@dual
def body_z_to_attitude(body_z: Vec3, yaw_rad: float) -> Quat:
    """Attitude whose body z axis (FRD, down) is body_z and whose heading is yaw (PX4 bodyzToAttitude)."""
    bz = body_z
    n = math.sqrt(bz[0] ** 2 + bz[1] ** 2 + bz[2] ** 2)
    bz = (0.0, 0.0, 1.0) if n < 1e-09 else (bz[0] / n, bz[1] / n, bz[2] / n)
    y_c = (-math.sin(yaw_rad), math.cos(yaw_rad), 0.0)
    # body_x = y_c x body_z
    bx = (y_c[1] * bz[2] - y_c[2] * bz[1], y_c[2] * bz[0] - y_c[0] * bz[2], y_c[0] * bz[1] - y_c[1] * bz[0])
    if bz[2] < 0.0:
        bx = (-bx[0], -bx[1], -bx[2])
    n = math.sqrt(bx[0] ** 2 + bx[1] ** 2 + bx[2] ** 2)
    bx = (1.0, 0.0, 0.0) if n < 1e-09 else (bx[0] / n, bx[1] / n, bx[2] / n)
    by = (bz[1] * bx[2] - bz[2] * bx[1], bz[2] * bx[0] - bz[0] * bx[2], bz[0] * bx[1] - bz[1] * bx[0])
    # rotation matrix columns bx, by, bz -> quaternion
    r00, r01, r02 = bx[0], by[0], bz[0]
    r10, r11, r12 = bx[1], by[1], bz[1]
    r20, r21, r22 = bx[2], by[2], bz[2]
    tr = r00 + r11 + r22
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = (0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s)
    elif r00 > r11 and r00 > r22:
        s = math.sqrt(1.0 + r00 - r11 - r22) * 2.0
        q = ((r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s)
    elif r11 > r22:
        s = math.sqrt(1.0 + r11 - r00 - r22) * 2.0
        q = ((r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s)
    else:
        s = math.sqrt(1.0 + r22 - r00 - r11) * 2.0
        q = ((r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s)
    return quat_normalize(q)


# PositionControl.state layout: velocity integral (m/s^2), velocity setpoint, thrust setpoint
_VEL_INT, _VEL_SP, _THR_SP = 0, 3, 6
POSITION_STATE = 9
# PositionControl.gains layout (see _load_gains)
(_XY_P, _Z_P, _XY_VEL_MAX, _Z_VEL_MAX_UP, _Z_VEL_MAX_DN, _XY_VEL_P, _XY_VEL_I, _XY_VEL_D, _Z_VEL_P, _Z_VEL_I,
 _Z_VEL_D, _THR_MIN, _THR_MAX, _TO_ACC, _TILT_MAX, _HOVER) = range(16)


@dual
def position_control(st: np.ndarray, g: np.ndarray, dt_s: float, psp: Vec3, vff: Vec3, up_max: float,
                     down_max: float, position_ned_m: Vec3, velocity_ned_m_s: Vec3, accel_ned_m_s2: Vec3) -> Vec3:
    """PX4 PositionControl step on the state `st` with gains `g`: the thrust setpoint in NED,
    normalised (|thrust| = fraction of full collective thrust). NaN setpoint components are
    not controlled (x == x is False only for NaN; setpoints are sanitised to finite-or-NaN)."""
    gain_xy, gain_z, xy_max = g[_XY_P], g[_Z_P], g[_XY_VEL_MAX]
    kp_xy, ki_xy, kd_xy, kp_z, ki_z, kd_z = g[_XY_VEL_P], g[_XY_VEL_I], g[_XY_VEL_D], g[_Z_VEL_P], g[_Z_VEL_I], g[_Z_VEL_D]
    thr_min, thr_max, to_acc, tilt_max_rad, hover = g[_THR_MIN], g[_THR_MAX], g[_TO_ACC], g[_TILT_MAX], g[_HOVER]
    # --- position P (+ velocity feed-forward), PX4 _positionControl
    vx = (psp[0] - position_ned_m[0]) * gain_xy if psp[0] == psp[0] else 0.0
    vy = (psp[1] - position_ned_m[1]) * gain_xy if psp[1] == psp[1] else 0.0
    vz = (psp[2] - position_ned_m[2]) * gain_z if psp[2] == psp[2] else 0.0
    if vff[0] == vff[0]:
        vx += vff[0]
    if vff[1] == vff[1]:
        vy += vff[1]
    if vff[2] == vff[2]:
        vz += vff[2]
    speed_xy = math.sqrt(vx * vx + vy * vy)
    if speed_xy > xy_max:
        vx *= xy_max / speed_xy
        vy *= xy_max / speed_xy
    if up_max != up_max:
        up_max = g[_Z_VEL_MAX_UP]
    if down_max != down_max:
        down_max = g[_Z_VEL_MAX_DN]
    vz = -up_max if vz < -up_max else down_max if vz > down_max else vz
    st[_VEL_SP], st[_VEL_SP + 1], st[_VEL_SP + 2] = vx, vy, vz

    # --- velocity PID -> acceleration, PX4 _velocityControl
    ex, ey, ez = vx - velocity_ned_m_s[0], vy - velocity_ned_m_s[1], vz - velocity_ned_m_s[2]
    acc = (
        kp_xy * ex + st[_VEL_INT] - kd_xy * accel_ned_m_s2[0],
        kp_xy * ey + st[_VEL_INT + 1] - kd_xy * accel_ned_m_s2[1],
        kp_z * ez + st[_VEL_INT + 2] - kd_z * accel_ned_m_s2[2],
    )
    tilt_max_rad = floor_tilt(tilt_max_rad, -position_ned_m[2], velocity_ned_m_s[2], vz)
    thr = _acceleration_control(acc, tilt_max_rad, hover, thr_min)

    # vertical anti-windup: stop integrating into a saturated thrust
    if (thr[2] >= -thr_min and ez >= 0.0) or (thr[2] <= -thr_max and ez <= 0.0):
        ez = 0.0
    # vertical priority: what is left of the thrust goes horizontal
    thr_xy_max = math.sqrt(max(thr_max * thr_max - thr[2] * thr[2], 0.0))
    thr_xy = math.hypot(thr[0], thr[1])
    if thr_xy > thr_xy_max:
        s = thr_xy_max / thr_xy
        thr = (thr[0] * s, thr[1] * s, thr[2])
    # horizontal anti-windup (PX4: tracking anti-reset windup, gain 2 / P)
    if kp_xy > 1e-6:
        arw = 2.0 / kp_xy
        ex -= arw * (acc[0] - thr[0] * to_acc)
        ey -= arw * (acc[1] - thr[1] * to_acc)
    st[_VEL_INT] += ki_xy * ex * dt_s
    st[_VEL_INT + 1] += ki_xy * ey * dt_s
    st[_VEL_INT + 2] = clamp(st[_VEL_INT + 2] + ki_z * ez * dt_s, -GRAVITY_M_S2, GRAVITY_M_S2)
    st[_THR_SP], st[_THR_SP + 1], st[_THR_SP + 2] = thr
    return thr


@dual
def _acceleration_control(acc: Vec3, tilt_max_rad: float, hover: float, thr_min: float) -> Vec3:
    """Acceleration setpoint -> thrust vector, tilt limited (PX4 _accelerationControl)."""
    n = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + GRAVITY_M_S2 * GRAVITY_M_S2)
    body_z = _limit_tilt((-acc[0] / n, -acc[1] / n, GRAVITY_M_S2 / n), tilt_max_rad)
    thrust_ned_z = acc[2] * (hover / GRAVITY_M_S2) - hover
    collective = min(thrust_ned_z / body_z[2], -thr_min)
    return (body_z[0] * collective, body_z[1] * collective, body_z[2] * collective)


class PositionControl:
    """PX4 PositionControl: position P, velocity PID, acceleration -> thrust vector
    (`position_control` on the `state` vector)."""

    def __init__(self, params: ParamTable) -> None:
        self.params = params
        self.state = np.zeros(POSITION_STATE)
        self.state[_THR_SP + 2] = -params["MPC_THR_HOVER"]
        self.gains = np.zeros(16)
        self._gains_version = -1

    def refresh_gains(self) -> None:
        """Re-read the gains if a parameter changed (cheap when none did)."""
        if self._gains_version != self.params.version:
            self._load_gains()

    def _load_gains(self) -> None:
        p = self.params.values
        hover = p["MPC_THR_HOVER"]
        self.gains[:] = (p["MPC_XY_P"], p["MPC_Z_P"], p["MPC_XY_VEL_MAX"], p["MPC_Z_VEL_MAX_UP"], p["MPC_Z_VEL_MAX_DN"],
                         p["MPC_XY_VEL_P_ACC"], p["MPC_XY_VEL_I_ACC"], p["MPC_XY_VEL_D_ACC"],
                         p["MPC_Z_VEL_P_ACC"], p["MPC_Z_VEL_I_ACC"], p["MPC_Z_VEL_D_ACC"],
                         p["MPC_THR_MIN"], p["MPC_THR_MAX"], GRAVITY_M_S2 / max(hover, 1e-3),
                         math.radians(p["MPC_TILTMAX_AIR"]), hover)
        self._gains_version = self.params.version

    @property
    def velocity_integral(self) -> list[float]:
        """m/s^2, NED."""
        return self.state[_VEL_INT:_VEL_INT + 3].tolist()

    @property
    def velocity_setpoint_ned_m_s(self) -> Vec3:
        return tuple(self.state[_VEL_SP:_VEL_SP + 3].tolist())  # type: ignore[return-value]

    @property
    def thrust_setpoint_ned(self) -> Vec3:
        return tuple(self.state[_THR_SP:_THR_SP + 3].tolist())  # type: ignore[return-value]

    def reset(self) -> None:
        """Clear the integrators (on the ground, on mode changes that need it)."""
        self.state[_VEL_INT:_VEL_INT + 3] = 0.0

    def settle_at_hover(self, collective: float) -> None:
        """The integrators as hovering has settled them: at rest, level, on target (no error to
        act on), the vertical integral makes `_acceleration_control`'s thrust `collective`
        (what holds the vehicle up, where MPC_THR_HOVER is only the feed-forward's guess)."""
        hover = self.params["MPC_THR_HOVER"]
        self.state[:] = 0.0
        self.state[_VEL_INT + 2] = clamp(GRAVITY_M_S2 * (hover - collective) / max(hover, 1e-3),
                                         -GRAVITY_M_S2, GRAVITY_M_S2)
        self.state[_THR_SP + 2] = -collective

    def update(self, dt_s: float, sp: Setpoint, position_ned_m: Vec3, velocity_ned_m_s: Vec3,
               accel_ned_m_s2: Vec3) -> Vec3:
        """Thrust setpoint in NED, normalised (|thrust| = fraction of full collective thrust)."""
        self.refresh_gains()
        return position_control(self.state, self.gains, dt_s, sp.position_ned_m, sp.velocity_ned_m_s,
                                sp.max_velocity_up_m_s, sp.max_velocity_down_m_s, position_ned_m, velocity_ned_m_s,
                                accel_ned_m_s2)


# AttitudeControl.gains layout
_YAW_W, _ROLL_P, _PITCH_P, _GAIN_YAW, _MAX_ROLL_RATE, _MAX_PITCH_RATE, _MAX_YAW_RATE = range(7)


@dual
def attitude_control(g: np.ndarray, q: Quat, q_sp: Quat, yaw_rate_ff_rad_s: float) -> Vec3:
    """PX4 AttitudeControl with gains `g`: body-rate setpoint (FRD, rad/s) from q towards q_sp."""
    yaw_w, roll_p, pitch_p, gain_yaw = g[_YAW_W], g[_ROLL_P], g[_PITCH_P], g[_GAIN_YAW]
    lr, lp, ly = g[_MAX_ROLL_RATE], g[_MAX_PITCH_RATE], g[_MAX_YAW_RATE]
    # body z axes in the world (third rotation-matrix columns), written out: every step
    w, x, y, z = q
    ax, ay, az = 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)
    w, x, y, z = q_sp
    bx, by, bz = 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)
    dot = ax * bx + ay * by + az * bz
    if dot < -0.999999:
        qd_red = quat_from_two_vectors((ax, ay, az), (bx, by, bz))  # opposite: any 180 deg axis
    else:
        # quat_from_two_vectors' common case: normalise (1 + a.b, a x b), w > 0 already
        w, x, y, z = 1.0 + dot, ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        n = math.sqrt(w * w + x * x + y * y + z * z)
        qd_red = (w / n, x / n, y / n, z / n)
    if abs(qd_red[1]) > 1.0 - 1e-5 or abs(qd_red[2]) > 1.0 - 1e-5:
        qd_red = q_sp  # upside down: the full attitude is the reduced attitude
    else:
        qd_red = quat_multiply(qd_red, q)
    # the yaw left to do after the tilt, scaled down by the yaw weight
    # (quat_normalize written out: only w and z of the mix are needed)
    w, x, y, z = quat_conjugate_multiply(qd_red, q_sp)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        n = -n
    w, z = w / n, z / n
    w = -1.0 if w < -1.0 else 1.0 if w > 1.0 else w
    z = -1.0 if z < -1.0 else 1.0 if z > 1.0 else z
    # qd = qd_red * (cos, 0, 0, sin): quat_multiply with the zero terms dropped
    cw, sz = math.cos(yaw_w * math.acos(w)), math.sin(yaw_w * math.asin(z))
    a, b, c, d = qd_red
    qe = quat_conjugate_multiply(q, (a * cw - d * sz, b * cw + c * sz, c * cw - b * sz, d * cw + a * sz))
    s = 2.0 if qe[0] >= 0.0 else -2.0   # canonical (shorter) error rotation
    rx, ry, rz = s * qe[1] * roll_p, s * qe[2] * pitch_p, s * qe[3] * gain_yaw
    if yaw_rate_ff_rad_s:
        zb = quat_rotate_inverse(q, (0.0, 0.0, 1.0))
        rx += zb[0] * yaw_rate_ff_rad_s
        ry += zb[1] * yaw_rate_ff_rad_s
        rz += zb[2] * yaw_rate_ff_rad_s
    return (-lr if rx < -lr else lr if rx > lr else rx, -lp if ry < -lp else lp if ry > lp else ry,
            -ly if rz < -ly else ly if rz > ly else rz)


class AttitudeControl:
    """PX4 AttitudeControl: quaternion P with reduced (tilt-first) attitude and yaw weight
    (`attitude_control` with the `gains` vector)."""

    def __init__(self, params: ParamTable) -> None:
        self.params = params
        self.gains = np.zeros(7)
        self._gains_version = -1

    def refresh_gains(self) -> None:
        """Re-read the gains if a parameter changed (cheap when none did)."""
        if self._gains_version != self.params.version:
            self._load_gains()

    def _load_gains(self) -> None:
        # derived gains and limits, re-read only when a parameter changed
        p = self.params.values
        yaw_w = clamp(p["MC_YAW_WEIGHT"], 0.0, 1.0)
        gain_yaw = p["MC_YAW_P"] / yaw_w if yaw_w > 1e-4 else p["MC_YAW_P"]
        self.gains[:] = (yaw_w, p["MC_ROLL_P"], p["MC_PITCH_P"], gain_yaw, p["MC_ROLLRATE_MAX"] * _DEG,
                         p["MC_PITCHRATE_MAX"] * _DEG, p["MC_YAWRATE_MAX"] * _DEG)
        self._gains_version = self.params.version

    def update(self, q: Quat, q_sp: Quat, yaw_rate_ff_rad_s: float = 0.0) -> Vec3:
        """Body-rate setpoint (FRD, rad/s) from attitude q towards q_sp."""
        self.refresh_gains()
        return attitude_control(self.gains, tuple(q), tuple(q_sp), yaw_rate_ff_rad_s)  # type: ignore[arg-type]


_DEG = math.pi / 180.0
_INTEGRATOR_LIMIT = 0.3  # MC_RR_INT_LIM, MC_PR_INT_LIM, MC_YR_INT_LIM (PX4 defaults, all equal)
_RATE_DOT_TAU_S = 1.0 / (2.0 * math.pi * 30.0)  # PX4 low-passes the angular acceleration at ~30 Hz
_I_FACTOR_RATE_RAD_S = math.radians(400.0)
# RateControl.state layout: integral, last rate, whether there is one, low-passed rate derivative
_INTEGRAL, _LAST_RATE, _HAS_LAST, _RATE_DOT = 0, 3, 6, 7
RATE_STATE = 10


@dual
def _integrate(value: float, f: float, gain_times_error_dt: float) -> float:
    """One axis of PX4's rate integrator: shrunk for large errors (i_factor), clamped."""
    v = value + (f if f > 0.0 else 0.0) * gain_times_error_dt
    return -_INTEGRATOR_LIMIT if v < -_INTEGRATOR_LIMIT else _INTEGRATOR_LIMIT if v > _INTEGRATOR_LIMIT else v


@dual
def rate_control(st: np.ndarray, g: np.ndarray, dt_s: float, rate_frd_rad_s: Vec3, rate_sp_frd_rad_s: Vec3,
                 saturated: bool, landed: bool) -> Vec3:
    """PX4 RateControl step on the state `st` with gains `g` (P x3, I x3, D x3): normalised
    torque (roll, pitch, yaw) in about [-1, 1]; derivative on the measurement."""
    wx, wy, wz = rate_frd_rad_s
    rd = _RATE_DOT
    if st[_HAS_LAST] != 0.0 and dt_s > 0.0:
        # angular acceleration, low-passed
        lr = _LAST_RATE
        alpha = dt_s / (dt_s + _RATE_DOT_TAU_S)
        st[rd] += alpha * ((wx - st[lr]) / dt_s - st[rd])
        st[rd + 1] += alpha * ((wy - st[lr + 1]) / dt_s - st[rd + 1])
        st[rd + 2] += alpha * ((wz - st[lr + 2]) / dt_s - st[rd + 2])
    st[_LAST_RATE], st[_LAST_RATE + 1], st[_LAST_RATE + 2] = wx, wy, wz
    st[_HAS_LAST] = 1.0
    ex, ey, ez = rate_sp_frd_rad_s[0] - wx, rate_sp_frd_rad_s[1] - wy, rate_sp_frd_rad_s[2] - wz
    i = _INTEGRAL
    out = (g[0] * ex + st[i] - g[6] * st[rd], g[1] * ey + st[i + 1] - g[7] * st[rd + 1],
           g[2] * ez + st[i + 2] - g[8] * st[rd + 2])
    if not landed and not saturated:
        # PX4 shrinks the integration for large errors (i_factor), then clamps to the limit
        st[i] = _integrate(st[i], 1.0 - (ex / _I_FACTOR_RATE_RAD_S) ** 2, g[3] * ex * dt_s)
        st[i + 1] = _integrate(st[i + 1], 1.0 - (ey / _I_FACTOR_RATE_RAD_S) ** 2, g[4] * ey * dt_s)
        st[i + 2] = _integrate(st[i + 2], 1.0 - (ez / _I_FACTOR_RATE_RAD_S) ** 2, g[5] * ez * dt_s)
    return out


class RateControl:
    """PX4 RateControl: body-rate PID with derivative on measurement -> normalised torque
    (`rate_control` on the `state` vector)."""

    def __init__(self, params: ParamTable) -> None:
        self.params = params
        self.gains = np.zeros(9)
        self._gains_version = -1
        self.state = np.zeros(RATE_STATE)

    def reset(self) -> None:
        """Clear integrators and the derivative history."""
        self.state[:] = 0.0

    @property
    def integral(self) -> list[float]:
        return self.state[_INTEGRAL:_INTEGRAL + 3].tolist()

    def refresh_gains(self) -> None:
        """Re-read the gains if a parameter changed (cheap when none did)."""
        if self._gains_version != self.params.version:
            self._load_gains()

    def _load_gains(self) -> None:
        p = self.params.values
        self.gains[:] = (p["MC_ROLLRATE_P"], p["MC_PITCHRATE_P"], p["MC_YAWRATE_P"],
                         p["MC_ROLLRATE_I"], p["MC_PITCHRATE_I"], p["MC_YAWRATE_I"],
                         p["MC_ROLLRATE_D"], p["MC_PITCHRATE_D"], p["MC_YAWRATE_D"])
        self._gains_version = self.params.version

    def update(self, dt_s: float, rate_frd_rad_s: Vec3, rate_sp_frd_rad_s: Vec3, saturated: bool,
               landed: bool) -> Vec3:
        """Normalised torque (roll, pitch, yaw) in about [-1, 1]."""
        self.refresh_gains()
        return rate_control(self.state, self.gains, dt_s, tuple(rate_frd_rad_s), tuple(rate_sp_frd_rad_s),  # type: ignore[arg-type]
                            saturated, landed)


@dual
def idle_thrust(st: np.ndarray, g: np.ndarray) -> Vec3:
    """PX4's thrust when it suspects a landing: the integrators cleared, thrust at MPC_THR_MIN."""
    st[_VEL_INT], st[_VEL_INT + 1], st[_VEL_INT + 2] = 0.0, 0.0, 0.0
    return (0.0, 0.0, -g[_THR_MIN])
