"""Tiny pure-python vector and quaternion helpers for the stub's per-step math.

The controller runs once per 4 ms lockstep step on 3-vectors; plain tuples and floats are
several times faster than numpy at that size. The `@dual` ones compile into the per-step kernels
too (`sitl_bridge.jit`). Quaternions are (w, x, y, z), Hamilton
convention, rotating body (FRD) vectors into the world (NED) frame.
"""

from __future__ import annotations

import math

# The general quaternion algebra lives in the frames module; these names keep the stub's
# call sites short. What follows below is specific to the controllers and estimator.
from sitl_bridge.frames import quat_conjugate_t as quat_conjugate
from sitl_bridge.frames import quat_from_euler_t as quat_from_euler
from sitl_bridge.frames import quat_multiply_t as quat_multiply
from sitl_bridge.frames import quat_rotate_t as quat_rotate
from sitl_bridge.frames import quat_to_euler_t as quat_to_euler
from sitl_bridge.frames import wrap_pi
from sitl_bridge.jit import dual

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

__all__ = [
    "Quat", "Vec3", "clamp", "norm", "quat_conjugate", "quat_conjugate_multiply", "quat_from_euler",
    "quat_from_two_vectors", "quat_multiply", "quat_normalize", "quat_rotate", "quat_rotate_inverse",
    "quat_to_euler", "quat_yaw", "wrap_pi",
]


@dual
def norm(v: Vec3) -> float:
    """Euclidean length."""
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@dual
def clamp(value: float, low: float, high: float) -> float:
    """value limited to [low, high]."""
    return low if value < low else high if value > high else value


@dual
def quat_conjugate_multiply(a: Quat, b: Quat) -> Quat:
    """conjugate(a) * b (the rotation from a to b) without building the conjugate."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw + ax * bx + ay * by + az * bz,
        aw * bx - ax * bw - ay * bz + az * by,
        aw * by + ax * bz - ay * bw - az * bx,
        aw * bz - ax * by + ay * bx - az * bw,
    )


@dual
def quat_normalize(q: Quat) -> Quat:
    """Unit quaternion with positive w (the shorter of the two equivalent rotations)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[0] < 0.0:
        n = -n
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@dual
def quat_rotate_inverse(q: Quat, v: Vec3) -> Vec3:
    """Rotate v by the inverse of q (world -> body when q is the attitude)."""
    # quat_rotate with the conjugate (x, y, z negated) written out: one call, not two
    w, x, y, z = q
    vx, vy, vz = v
    tx = 2.0 * (z * vy - y * vz)
    ty = 2.0 * (x * vz - z * vx)
    tz = 2.0 * (y * vx - x * vy)
    return (
        vx + w * tx - y * tz + z * ty,
        vy + w * ty - z * tx + x * tz,
        vz + w * tz - x * ty + y * tx,
    )


@dual
def quat_yaw(q: Quat) -> float:
    """Heading (yaw) in rad of an attitude quaternion."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


@dual
def quat_from_two_vectors(src: Vec3, dst: Vec3) -> Quat:
    """Shortest rotation taking unit vector src onto unit vector dst."""
    cx = src[1] * dst[2] - src[2] * dst[1]
    cy = src[2] * dst[0] - src[0] * dst[2]
    cz = src[0] * dst[1] - src[1] * dst[0]
    dot = src[0] * dst[0] + src[1] * dst[1] + src[2] * dst[2]
    if dot < -0.999999:
        # Opposite vectors: rotate 180 deg about any axis orthogonal to src.
        axis = (0.0, -src[2], src[1]) if abs(src[0]) < 0.9 else (-src[2], 0.0, src[0])
        n = norm(axis)
        return (0.0, axis[0] / n, axis[1] / n, axis[2] / n)
    return quat_normalize((1.0 + dot, cx, cy, cz))
