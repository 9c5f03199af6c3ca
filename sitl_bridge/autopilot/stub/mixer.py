"""Quad-X mixer: collective thrust and normalised torques -> motor outputs in [0, 1].

PX4 motor order (Part A6 of the protocol sheet): 1 front-right CCW, 2 back-left CCW,
3 front-left CW, 4 back-right CW. Motor outputs follow the simulator's rotor map
(omega = 1000 u + 100 rad/s, thrust = k_f omega^2), which the mixer inverts so that the
controller can think in thrust, like PX4 with a thrust model factor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sitl_bridge.jit import dual


@dataclass(frozen=True)
class QuadGeometry:
    """Airframe constants the mixer and rate controller need (defaults: Gazebo Iris)."""

    # rotor positions in body FRD (x forward, y right), metres, PX4 motor order 1..4
    rotor_xy_frd_m: tuple[tuple[float, float], ...] = ((0.13, 0.22), (-0.13, -0.20), (0.13, -0.22), (-0.13, 0.20))
    # +1: CCW seen from above (yaw torque +k_m T in FRD), -1: CW
    rotor_direction: tuple[int, ...] = (1, 1, -1, -1)
    thrust_coefficient_n_s2: float = 5.84e-6   # k_f: thrust = k_f * omega^2
    moment_constant_m: float = 0.06            # k_m: yaw torque = k_m * thrust
    omega_scale_rad_s: float = 1000.0          # omega = scale * u + offset
    omega_offset_rad_s: float = 100.0
    omega_max_rad_s: float = 1100.0
    mass_kg: float = 1.55
    inertia_kg_m2: tuple[float, float, float] = (0.029125, 0.029125, 0.055225)

    @property
    def rotor_max_thrust_n(self) -> float:
        """Thrust of one rotor at full command."""
        return self.thrust_coefficient_n_s2 * self.omega_max_rad_s**2

    @property
    def hover_thrust(self) -> float:
        """Collective thrust (fraction of the maximum) that balances gravity."""
        return self.mass_kg * 9.80665 / (4.0 * self.rotor_max_thrust_n)


# QuadXMixer.constants layout: per-rotor collective column, per-rotor torque columns (roll,
# pitch, yaw) row by row, then the rotor map (omega max, scale, offset)
_THRUST_COL, _TORQUE_COLS, _OMEGA_MAX, _U_SCALE, _U_OFFSET = 0, 4, 16, 17, 18
MIXER_CONSTANTS = 19


@dual
def _clip01(x: float) -> float:
    return 0.0 if x < 0.0 else 1.0 if x > 1.0 else x


@dual
def _desaturate(r0: float, r1: float, r2: float, r3: float, y0: float, y1: float, y2: float,
                y3: float) -> tuple[float, float, float, float]:
    """Outputs (roll/pitch + collective r, yaw y) out of [0, 1]: give up yaw first, then shift
    the collective (PX4 non-airmode), finally clip to [0, 1]."""
    o0, o1, o2, o3 = r0 + y0, r1 + y1, r2 + y2, r3 + y3
    hi, lo = max(o0, o1, o2, o3), min(o0, o1, o2, o3)
    # Reduce yaw until roll/pitch + collective fit (or yaw is gone).
    spread_rp = max(r0, r1, r2, r3) - min(r0, r1, r2, r3)
    spread = hi - lo
    if spread > 1.0 and spread > spread_rp:
        scale = max(0.0, (1.0 - spread_rp) / (spread - spread_rp)) if spread_rp < 1.0 else 0.0
        o0, o1, o2, o3 = r0 + y0 * scale, r1 + y1 * scale, r2 + y2 * scale, r3 + y3 * scale
        hi, lo = max(o0, o1, o2, o3), min(o0, o1, o2, o3)
    # Shift the collective so that the differential part fits.
    if hi - lo <= 1.0:
        shift = (1.0 - hi) if hi > 1.0 else (-lo if lo < 0.0 else 0.0)
        o0, o1, o2, o3 = o0 + shift, o1 + shift, o2 + shift, o3 + shift
    return _clip01(o0), _clip01(o1), _clip01(o2), _clip01(o3)


@dual
def mix(c: np.ndarray, st: np.ndarray, thrust: float, torque_norm: tuple[float, float, float]
        ) -> tuple[float, float, float, float]:
    """Motor outputs u1..u4 in [0, 1] from the constants `c`; `st[0]` records saturation (1.0).

    Saturation is resolved like PX4's non-airmode allocation: yaw is given up first, then the
    collective shifts to keep roll/pitch authority, finally outputs are clipped.
    """
    t = _TORQUE_COLS
    a0, b0, c0, a1, b1, c1 = c[t], c[t + 1], c[t + 2], c[t + 3], c[t + 4], c[t + 5]
    a2, b2, c2, a3, b3, c3 = c[t + 6], c[t + 7], c[t + 8], c[t + 9], c[t + 10], c[t + 11]
    tx, ty, tz = torque_norm
    k0, k1, k2, k3 = c[_THRUST_COL], c[_THRUST_COL + 1], c[_THRUST_COL + 2], c[_THRUST_COL + 3]
    # collective + roll/pitch, and yaw kept apart so it can be given up first
    r0, r1, r2, r3 = (k0 * thrust + a0 * tx + b0 * ty, k1 * thrust + a1 * tx + b1 * ty,
                      k2 * thrust + a2 * tx + b2 * ty, k3 * thrust + a3 * tx + b3 * ty)
    o0, o1, o2, o3 = r0 + c0 * tz, r1 + c1 * tz, r2 + c2 * tz, r3 + c3 * tz
    saturated = not (0.0 <= o0 <= 1.0 and 0.0 <= o1 <= 1.0 and 0.0 <= o2 <= 1.0 and 0.0 <= o3 <= 1.0)
    st[0] = 1.0 if saturated else 0.0
    if saturated:
        o0, o1, o2, o3 = _desaturate(r0, r1, r2, r3, c0 * tz, c1 * tz, c2 * tz, c3 * tz)
    # normalised rotor thrust (now in [0, 1]) -> motor output through the simulator's rotor map
    omega_max, scale, offset = c[_OMEGA_MAX], c[_U_SCALE], c[_U_OFFSET]
    u0, u1 = (omega_max * math.sqrt(o0) - offset) / scale, (omega_max * math.sqrt(o1) - offset) / scale
    u2, u3 = (omega_max * math.sqrt(o2) - offset) / scale, (omega_max * math.sqrt(o3) - offset) / scale
    return _clip01(u0), _clip01(u1), _clip01(u2), _clip01(u3)


class QuadXMixer:
    """Maps (collective thrust in [0,1], roll/pitch/yaw normalised torque) to motor outputs
    (`mix` with the `constants` vector; `state[0]`: saturated at the last mix)."""

    def __init__(self, geometry: QuadGeometry | None = None) -> None:
        self.geometry = g = geometry or QuadGeometry()
        t_max = g.rotor_max_thrust_n
        # Rows: total thrust (N), roll, pitch, yaw torque (N m) from per-rotor thrusts (N).
        effectiveness = np.array([
            [1.0] * 4,
            [-y for _, y in g.rotor_xy_frd_m],
            [x for x, _ in g.rotor_xy_frd_m],
            [d * g.moment_constant_m for d in g.rotor_direction],
        ])
        # Normalised torque 1 = the torque of half the rotors at full thrust against the others.
        self.max_torque_n_m = tuple(float(np.sum(np.abs(effectiveness[k])) * t_max / 2) for k in (1, 2, 3))
        mix_matrix = np.linalg.inv(effectiveness)  # per-rotor thrust (N) from (T, tau_x, tau_y, tau_z)
        c = self.constants = np.zeros(MIXER_CONSTANTS)
        # Per-rotor normalised thrust (fraction of t_max) per unit of normalised input.
        c[_THRUST_COL:_THRUST_COL + 4] = [float(mix_matrix[i, 0] * 4.0) for i in range(4)]  # collective 1 -> 4 t_max
        c[_TORQUE_COLS:_TORQUE_COLS + 12] = [float(mix_matrix[i, k + 1] * self.max_torque_n_m[k] / t_max)
                                             for i in range(4) for k in range(3)]
        c[_OMEGA_MAX], c[_U_SCALE], c[_U_OFFSET] = g.omega_max_rad_s, g.omega_scale_rad_s, g.omega_offset_rad_s
        self.state = np.zeros(1)

    def collective_for(self, rotor_speed_rad_s: float) -> float:
        """The collective thrust (no torque) whose outputs spin every rotor at `rotor_speed_rad_s`
        (`mix`'s rotor map inverted)."""
        c = self.constants
        per_rotor = (rotor_speed_rad_s / c[_OMEGA_MAX]) ** 2
        return float(per_rotor / np.mean(c[_THRUST_COL:_THRUST_COL + 4]))

    @property
    def saturated(self) -> bool:
        """Whether the last mix had to desaturate."""
        return bool(self.state[0])

    @saturated.setter
    def saturated(self, value: bool) -> None:
        self.state[0] = 1.0 if value else 0.0

    def mix(self, thrust: float, torque_norm: tuple[float, float, float]) -> tuple[float, float, float, float]:
        """Motor outputs u1..u4 in [0, 1] (see `mix`)."""
        tx, ty, tz = torque_norm
        return tuple(float(u) for u in mix(self.constants, self.state, float(thrust),  # type: ignore[return-value]
                                             (float(tx), float(ty), float(tz))))
