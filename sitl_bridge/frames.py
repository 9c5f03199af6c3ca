"""Frame conventions: the only module that converts between ENU/NED and FLU/FRD.

Conventions used everywhere in sitl-bridge:

* World frames: ENU (x east, y north, z up; pybullet's world) and NED (x north, y east, z down;
  PX4's local frame).
* Body frames: FLU (x forward, y left, z up; pybullet's body) and FRD (x forward, y right,
  z down; PX4's body).
* Quaternions are (w, x, y, z), Hamilton convention, and `q_a_b` rotates vectors expressed in
  frame b into frame a: ``v_a = q_a_b * v_b * conj(q_a_b)``. pybullet uses (x, y, z, w): convert
  with `quaternion_from_pybullet` / `quaternion_to_pybullet`.
* Euler angles are intrinsic Z-Y-X (yaw, pitch, roll), in radians, as PX4 reports them in NED/FRD.

The public functions take any 3-/4-sequence (tuple, list, numpy array) and return numpy arrays.
The `*_xyz` / `*_t` variants take and return plain floats / tuples: they are for the per-step hot
paths (physics, sensors), where numpy's per-call overhead would dominate; the `@dual` ones are
also compiled into the per-step kernels (`sitl_bridge.jit`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from sitl_bridge.jit import dual

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

_SQRT1_2 = math.sqrt(0.5)
#: Rotates ENU vectors into NED (pi about the (1, 1, 0) axis): Gazebo's q_ENU_to_NED.
Q_NED_ENU: Quat = (0.0, _SQRT1_2, _SQRT1_2, 0.0)
#: Rotates FLU vectors into FRD (pi about x): Gazebo's q_FLU_to_FRD.
Q_FRD_FLU: Quat = (0.0, 1.0, 0.0, 0.0)


# --------------------------------------------------------------------------------------------
# vectors: world ENU <-> NED, body FLU <-> FRD (each mapping is its own inverse)
# --------------------------------------------------------------------------------------------
@dual
def enu_to_ned_xyz(x: float, y: float, z: float) -> Vec3:
    """ENU (east, north, up) -> NED (north, east, down), plain floats."""
    return (y, x, -z)


ned_to_enu_xyz = enu_to_ned_xyz  # the swap is an involution


@dual
def flu_to_frd_xyz(x: float, y: float, z: float) -> Vec3:
    """FLU (forward, left, up) -> FRD (forward, right, down), plain floats."""
    return (x, -y, -z)


frd_to_flu_xyz = flu_to_frd_xyz


def enu_to_ned(v: Sequence[float]) -> np.ndarray:
    """A vector (or an (N, 3) array of vectors) from world ENU to world NED."""
    a = np.asarray(v, dtype=float)
    return np.stack((a[..., 1], a[..., 0], -a[..., 2]), axis=-1)


def ned_to_enu(v: Sequence[float]) -> np.ndarray:
    """A vector (or an (N, 3) array of vectors) from world NED to world ENU."""
    return enu_to_ned(v)


def flu_to_frd(v: Sequence[float]) -> np.ndarray:
    """A vector (or an (N, 3) array of vectors) from body FLU to body FRD."""
    a = np.asarray(v, dtype=float)
    return np.stack((a[..., 0], -a[..., 1], -a[..., 2]), axis=-1)


def frd_to_flu(v: Sequence[float]) -> np.ndarray:
    """A vector (or an (N, 3) array of vectors) from body FRD to body FLU."""
    return flu_to_frd(v)


def yaw_enu_to_ned(yaw_enu_rad: float) -> float:
    """Heading: ENU yaw (from east, counter-clockwise) -> NED yaw (from north, clockwise), in (-pi, pi]."""
    return wrap_pi(math.pi / 2.0 - yaw_enu_rad)


def yaw_ned_to_enu(yaw_ned_rad: float) -> float:
    """Heading: NED yaw (from north, clockwise) -> ENU yaw (from east, counter-clockwise), in (-pi, pi]."""
    return wrap_pi(math.pi / 2.0 - yaw_ned_rad)


@dual
def wrap_pi(angle_rad: float) -> float:
    """Wrap an angle into (-pi, pi] (the one definition; the stub's controllers use it too)."""
    wrapped = math.pi - (math.pi - angle_rad) % (2.0 * math.pi)
    return wrapped if wrapped > -math.pi else math.pi  # % can round up to 2 pi itself


# --------------------------------------------------------------------------------------------
# quaternions, plain-float hot path
# --------------------------------------------------------------------------------------------
@dual
def quat_multiply_t(a: Sequence[float], b: Sequence[float]) -> Quat:
    """Hamilton product a * b of two (w, x, y, z) quaternions, plain floats."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_conjugate_t(q: Sequence[float]) -> Quat:
    """Conjugate (the inverse of a unit quaternion), plain floats."""
    w, x, y, z = q
    return (w, -x, -y, -z)


@dual
def quat_rotate_t(q: Sequence[float], v: Sequence[float]) -> Vec3:
    """Rotate vector v by unit quaternion q (v' = q v q*), plain floats."""
    w, x, y, z = q
    vx, vy, vz = v
    # t = 2 * cross(q.xyz, v); v' = v + w t + cross(q.xyz, t)
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (
        vx + w * tx + (y * tz - z * ty),
        vy + w * ty + (z * tx - x * tz),
        vz + w * tz + (x * ty - y * tx),
    )


@dual
def quat_rotate_inverse_t(q: Sequence[float], v: Sequence[float]) -> Vec3:
    """Rotate vector v by the inverse of unit quaternion q (v' = q* v q), plain floats."""
    w, x, y, z = q
    return quat_rotate_t((w, -x, -y, -z), v)


@dual
def quat_enu_flu_to_ned_frd_t(q_enu_flu: Sequence[float]) -> Quat:
    """Attitude ENU/FLU (pybullet) -> NED/FRD (PX4): q_ned_frd = q_NED_ENU * q_enu_flu * q_FRD_FLU^-1.

    Expanded by hand (both constant quaternions are pi rotations) for the per-step path; the
    generic form is `quat_multiply(quat_multiply(Q_NED_ENU, q), quat_conjugate(Q_FRD_FLU))`.
    """
    w, x, y, z = q_enu_flu
    s = _SQRT1_2
    # q_NED_ENU * q = s*(0,1,1,0) * (w,x,y,z)
    a = (s * (-x - y), s * (w + z), s * (w - z), s * (y - x))
    # ... * conj(0,1,0,0) = ... * (0,-1,0,0)
    aw, ax, ay, az = a
    return (ax, -aw, -az, ay)


def quat_ned_frd_to_enu_flu_t(q_ned_frd: Sequence[float]) -> Quat:
    """Attitude NED/FRD (PX4) -> ENU/FLU (pybullet): the inverse of `quat_enu_flu_to_ned_frd_t`."""
    s = _SQRT1_2
    # q_enu_flu = q_NED_ENU^-1 * q_ned_frd * q_FRD_FLU; both constants are their own inverse up to sign
    q = quat_multiply_t((0.0, -s, -s, 0.0), q_ned_frd)
    return quat_multiply_t(q, Q_FRD_FLU)


@dual
def quat_to_euler_t(q: Sequence[float]) -> Vec3:
    """(roll, pitch, yaw) in rad, Z-Y-X intrinsic, from a (w, x, y, z) quaternion; plain floats."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    sinp = 2.0 * (w * y - z * x)
    pitch = math.asin(1.0 if sinp > 1.0 else -1.0 if sinp < -1.0 else sinp)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return (roll, pitch, yaw)


@dual
def quat_from_euler_t(roll: float, pitch: float, yaw: float) -> Quat:
    """(w, x, y, z) quaternion from Z-Y-X intrinsic Euler angles in rad; plain floats."""
    cr, sr = math.cos(roll * 0.5), math.sin(roll * 0.5)
    cp, sp = math.cos(pitch * 0.5), math.sin(pitch * 0.5)
    cy, sy = math.cos(yaw * 0.5), math.sin(yaw * 0.5)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


@dual
def quat_to_matrix_t(q: Sequence[float]) -> tuple[float, ...]:
    """Row-major 3x3 rotation matrix (9 floats) of a unit (w, x, y, z) quaternion."""
    w, x, y, z = q
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return (
        1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy),
        2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx),
        2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy),
    )


# --------------------------------------------------------------------------------------------
# quaternions, numpy API
# --------------------------------------------------------------------------------------------
def _q(q: Sequence[float]) -> tuple[float, ...]:
    return tuple(float(c) for c in q)


def quat_multiply(a: Sequence[float], b: Sequence[float]) -> np.ndarray:
    """Hamilton product a * b of two (w, x, y, z) quaternions."""
    return np.array(quat_multiply_t(_q(a), _q(b)))


def quat_conjugate(q: Sequence[float]) -> np.ndarray:
    """Conjugate of a (w, x, y, z) quaternion."""
    return np.array(quat_conjugate_t(_q(q)))


def quat_normalize(q: Sequence[float]) -> np.ndarray:
    """Unit quaternion with w >= 0 (q and -q are the same rotation)."""
    a = np.asarray(q, dtype=float)
    a = a / np.linalg.norm(a)
    return -a if a[0] < 0.0 else a


def quat_rotate(q: Sequence[float], v: Sequence[float]) -> np.ndarray:
    """Rotate vector v by unit quaternion q."""
    return np.array(quat_rotate_t(_q(q), _q(v)))


def quat_rotate_inverse(q: Sequence[float], v: Sequence[float]) -> np.ndarray:
    """Rotate vector v by the inverse of unit quaternion q."""
    return np.array(quat_rotate_inverse_t(_q(q), _q(v)))


def quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    """3x3 rotation matrix of a unit (w, x, y, z) quaternion."""
    return np.array(quat_to_matrix_t(_q(q))).reshape(3, 3)


def quat_enu_flu_to_ned_frd(q_enu_flu: Sequence[float]) -> np.ndarray:
    """Attitude from pybullet's ENU/FLU to PX4's NED/FRD (both (w, x, y, z))."""
    return np.array(quat_enu_flu_to_ned_frd_t(_q(q_enu_flu)))


def quat_ned_frd_to_enu_flu(q_ned_frd: Sequence[float]) -> np.ndarray:
    """Attitude from PX4's NED/FRD to pybullet's ENU/FLU (both (w, x, y, z))."""
    return np.array(quat_ned_frd_to_enu_flu_t(_q(q_ned_frd)))


def quat_to_euler(q: Sequence[float]) -> np.ndarray:
    """(roll, pitch, yaw) in rad, Z-Y-X intrinsic."""
    return np.array(quat_to_euler_t(_q(q)))


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(w, x, y, z) quaternion from Z-Y-X intrinsic Euler angles in rad."""
    return np.array(quat_from_euler_t(roll, pitch, yaw))


def quaternion_from_pybullet(q_xyzw: Sequence[float]) -> np.ndarray:
    """pybullet's (x, y, z, w) -> our (w, x, y, z)."""
    x, y, z, w = q_xyzw
    return np.array((w, x, y, z), dtype=float)


def quaternion_to_pybullet(q_wxyz: Sequence[float]) -> tuple[float, float, float, float]:
    """Our (w, x, y, z) -> pybullet's (x, y, z, w)."""
    w, x, y, z = (float(c) for c in q_wxyz)
    return (x, y, z, w)


def yaw_quaternion_enu_flu(yaw_enu_rad: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) attitude ENU/FLU of a level body with the given ENU yaw."""
    return (math.cos(yaw_enu_rad * 0.5), 0.0, 0.0, math.sin(yaw_enu_rad * 0.5))
