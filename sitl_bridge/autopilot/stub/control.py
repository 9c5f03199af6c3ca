"""PX4-style cascaded multicopter control, one call per lockstep step.

position P -> velocity PID (acceleration, tilt and thrust limits, anti-windup) -> attitude P
on quaternions with yaw de-weighting -> body-rate PID -> normalised torque for the mixer.
The structure and the default gains mirror PX4's mc_pos_control (PositionControl.cpp),
mc_att_control (AttitudeControl.cpp) and mc_rate_control (RateControl.cpp). All vectors are
NED / FRD tuples (see `vec.py`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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


class PositionControl:
    """PX4 PositionControl: position P, velocity PID, acceleration -> thrust vector."""

    def __init__(self, params: ParamTable) -> None:
        self.params = params
        self.velocity_integral = [0.0, 0.0, 0.0]   # m/s^2
        self.velocity_setpoint_ned_m_s: Vec3 = (0.0, 0.0, 0.0)
        self.thrust_setpoint_ned: Vec3 = (0.0, 0.0, -params["MPC_THR_HOVER"])
        self._gains_version = -1
        self._gains: tuple[float, ...] = ()

    def _load_gains(self) -> None:
        # re-read only when a parameter changed: eighteen dict look-ups per call add up
        p = self.params.values
        hover = p["MPC_THR_HOVER"]
        self._gains = (p["MPC_XY_P"], p["MPC_Z_P"], p["MPC_XY_VEL_MAX"], p["MPC_Z_VEL_MAX_UP"], p["MPC_Z_VEL_MAX_DN"],
                       p["MPC_XY_VEL_P_ACC"], p["MPC_XY_VEL_I_ACC"], p["MPC_XY_VEL_D_ACC"],
                       p["MPC_Z_VEL_P_ACC"], p["MPC_Z_VEL_I_ACC"], p["MPC_Z_VEL_D_ACC"],
                       p["MPC_THR_MIN"], p["MPC_THR_MAX"], GRAVITY_M_S2 / max(hover, 1e-3),
                       math.radians(p["MPC_TILTMAX_AIR"]), hover)
        self._gains_version = self.params.version

    def reset(self) -> None:
        """Clear the integrators (on the ground, on mode changes that need it)."""
        self.velocity_integral = [0.0, 0.0, 0.0]

    def update(self, dt_s: float, sp: Setpoint, position_ned_m: Vec3, velocity_ned_m_s: Vec3,
               accel_ned_m_s2: Vec3) -> Vec3:
        """Thrust setpoint in NED, normalised (|thrust| = fraction of full collective thrust)."""
        if self._gains_version != self.params.version:
            self._load_gains()
        (gain_xy, gain_z, xy_max, up_max_param, down_max_param, kp_xy, ki_xy, kd_xy, kp_z, ki_z, kd_z,
         thr_min, thr_max, to_acc, tilt_max_rad, hover) = self._gains
        # --- position P (+ velocity feed-forward), PX4 _positionControl. NaN = not controlled
        # (x == x is False only for NaN; setpoints are sanitised to finite-or-NaN on entry).
        psp, vff = sp.position_ned_m, sp.velocity_ned_m_s
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
        up_max = sp.max_velocity_up_m_s
        if up_max != up_max:
            up_max = up_max_param
        down_max = sp.max_velocity_down_m_s
        if down_max != down_max:
            down_max = down_max_param
        vz = -up_max if vz < -up_max else down_max if vz > down_max else vz
        vel_sp = (vx, vy, vz)
        self.velocity_setpoint_ned_m_s = vel_sp

        # --- velocity PID -> acceleration, PX4 _velocityControl
        err = [vx - velocity_ned_m_s[0], vy - velocity_ned_m_s[1], vz - velocity_ned_m_s[2]]
        vi = self.velocity_integral
        acc = (
            kp_xy * err[0] + vi[0] - kd_xy * accel_ned_m_s2[0],
            kp_xy * err[1] + vi[1] - kd_xy * accel_ned_m_s2[1],
            kp_z * err[2] + vi[2] - kd_z * accel_ned_m_s2[2],
        )
        thr = self._acceleration_control(acc, tilt_max_rad, hover, thr_min)

        # vertical anti-windup: stop integrating into a saturated thrust
        if (thr[2] >= -thr_min and err[2] >= 0.0) or (thr[2] <= -thr_max and err[2] <= 0.0):
            err[2] = 0.0
        # vertical priority: what is left of the thrust goes horizontal
        thr_xy_max = math.sqrt(max(thr_max * thr_max - thr[2] * thr[2], 0.0))
        thr_xy = math.hypot(thr[0], thr[1])
        if thr_xy > thr_xy_max:
            s = thr_xy_max / thr_xy
            thr = (thr[0] * s, thr[1] * s, thr[2])
        # horizontal anti-windup (PX4: tracking anti-reset windup, gain 2 / P)
        if kp_xy > 1e-6:
            arw = 2.0 / kp_xy
            err[0] -= arw * (acc[0] - thr[0] * to_acc)
            err[1] -= arw * (acc[1] - thr[1] * to_acc)
        vi[0] += ki_xy * err[0] * dt_s
        vi[1] += ki_xy * err[1] * dt_s
        vi[2] = clamp(vi[2] + ki_z * err[2] * dt_s, -GRAVITY_M_S2, GRAVITY_M_S2)
        self.thrust_setpoint_ned = thr
        return thr

    @staticmethod
    def _acceleration_control(acc: Vec3, tilt_max_rad: float, hover: float, thr_min: float) -> Vec3:
        """Acceleration setpoint -> thrust vector, tilt limited (PX4 _accelerationControl)."""
        n = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + GRAVITY_M_S2 * GRAVITY_M_S2)
        body_z = (-acc[0] / n, -acc[1] / n, GRAVITY_M_S2 / n)
        body_z = _limit_tilt(body_z, tilt_max_rad)
        thrust_ned_z = acc[2] * (hover / GRAVITY_M_S2) - hover
        collective = min(thrust_ned_z / body_z[2], -thr_min)
        return (body_z[0] * collective, body_z[1] * collective, body_z[2] * collective)


class AttitudeControl:
    """PX4 AttitudeControl: quaternion P with reduced (tilt-first) attitude and yaw weight."""

    def __init__(self, params: ParamTable) -> None:
        self.params = params
        self._gains_version = -1
        self._gains: tuple[float, ...] = ()

    def _load_gains(self) -> None:
        # derived gains and limits, re-read only when a parameter changed
        p = self.params.values
        yaw_w = clamp(p["MC_YAW_WEIGHT"], 0.0, 1.0)
        gain_yaw = p["MC_YAW_P"] / yaw_w if yaw_w > 1e-4 else p["MC_YAW_P"]
        self._gains = (yaw_w, p["MC_ROLL_P"], p["MC_PITCH_P"], gain_yaw, p["MC_ROLLRATE_MAX"] * _DEG,
                       p["MC_PITCHRATE_MAX"] * _DEG, p["MC_YAWRATE_MAX"] * _DEG)
        self._gains_version = self.params.version

    def update(self, q: Quat, q_sp: Quat, yaw_rate_ff_rad_s: float = 0.0) -> Vec3:
        """Body-rate setpoint (FRD, rad/s) from attitude q towards q_sp."""
        if self._gains_version != self.params.version:
            self._load_gains()
        yaw_w, roll_p, pitch_p, gain_yaw, lr, lp, ly = self._gains
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


_DEG = math.pi / 180.0


class RateControl:
    """PX4 RateControl: body-rate PID with derivative on measurement -> normalised torque."""

    _INTEGRATOR_LIMIT = (0.3, 0.3, 0.3)  # MC_RR_INT_LIM, MC_PR_INT_LIM, MC_YR_INT_LIM
    _RATE_DOT_TAU_S = 1.0 / (2.0 * math.pi * 30.0)  # PX4 low-passes the angular acceleration at ~30 Hz

    def __init__(self, params: ParamTable) -> None:
        self.params = params
        self._gains_version = -1
        self._gains: tuple[float, ...] = ()
        self.reset()

    def reset(self) -> None:
        """Clear integrators and the derivative history."""
        self.integral = [0.0, 0.0, 0.0]
        self._last_rate: Vec3 | None = None
        self._rate_dot = [0.0, 0.0, 0.0]

    def _load_gains(self) -> None:
        # re-read only when a parameter changed: nine dict look-ups per step add up
        p = self.params.values
        self._gains = (p["MC_ROLLRATE_P"], p["MC_PITCHRATE_P"], p["MC_YAWRATE_P"],
                       p["MC_ROLLRATE_I"], p["MC_PITCHRATE_I"], p["MC_YAWRATE_I"],
                       p["MC_ROLLRATE_D"], p["MC_PITCHRATE_D"], p["MC_YAWRATE_D"])
        self._gains_version = self.params.version

    def update(self, dt_s: float, rate_frd_rad_s: Vec3, rate_sp_frd_rad_s: Vec3, saturated: bool,
               landed: bool) -> Vec3:
        """Normalised torque (roll, pitch, yaw) in about [-1, 1]."""
        if self._gains_version != self.params.version:
            self._load_gains()
        kp_x, kp_y, kp_z, ki_x, ki_y, ki_z, kd_x, kd_y, kd_z = self._gains
        wx, wy, wz = rate_frd_rad_s
        last = self._last_rate
        rd = self._rate_dot
        if last is not None and dt_s > 0.0:
            # angular acceleration, low-passed
            alpha = dt_s / (dt_s + self._RATE_DOT_TAU_S)
            rd[0] += alpha * ((wx - last[0]) / dt_s - rd[0])
            rd[1] += alpha * ((wy - last[1]) / dt_s - rd[1])
            rd[2] += alpha * ((wz - last[2]) / dt_s - rd[2])
        self._last_rate = rate_frd_rad_s
        ex, ey, ez = rate_sp_frd_rad_s[0] - wx, rate_sp_frd_rad_s[1] - wy, rate_sp_frd_rad_s[2] - wz
        integ = self.integral
        out = (kp_x * ex + integ[0] - kd_x * rd[0], kp_y * ey + integ[1] - kd_y * rd[1],
               kp_z * ez + integ[2] - kd_z * rd[2])
        if not landed and not saturated:
            # per axis, written out (every step): PX4 shrinks the integration for large
            # errors (i_factor), then clamps to the integrator limit
            lim_x, lim_y, lim_z = self._INTEGRATOR_LIMIT
            f = 1.0 - (ex / _I_FACTOR_RATE_RAD_S) ** 2
            v = integ[0] + (f if f > 0.0 else 0.0) * (ki_x * ex * dt_s)
            integ[0] = -lim_x if v < -lim_x else lim_x if v > lim_x else v
            f = 1.0 - (ey / _I_FACTOR_RATE_RAD_S) ** 2
            v = integ[1] + (f if f > 0.0 else 0.0) * (ki_y * ey * dt_s)
            integ[1] = -lim_y if v < -lim_y else lim_y if v > lim_y else v
            f = 1.0 - (ez / _I_FACTOR_RATE_RAD_S) ** 2
            v = integ[2] + (f if f > 0.0 else 0.0) * (ki_z * ez * dt_s)
            integ[2] = -lim_z if v < -lim_z else lim_z if v > lim_z else v
        return out


_I_FACTOR_RATE_RAD_S = math.radians(400.0)
