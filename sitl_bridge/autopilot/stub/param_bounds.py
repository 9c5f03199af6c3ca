"""Ranges of the stub's parameters from PX4 v1.16's parameter metadata (`@min`/`@max` in the
modules' `*_params.c`, `min:`/`max:` in their `module.yaml`); a PARAM_SET outside its range is
clamped to it, so an absurd value (MPC_XY_VEL_MAX = 1e9) cannot make the controllers blow up.
Parameters PX4 gives no range here are only required to be finite."""

from __future__ import annotations

import math

PX4_PARAM_BOUNDS: dict[str, tuple[float, float]] = {
    "MAV_SYS_ID": (1, 250), "MAV_COMP_ID": (1, 250), "MAV_TYPE": (0, 22), "SYS_AUTOSTART": (0, 9999999),
    "SENS_BOARD_ROT": (-1, 40),
    "COM_OF_LOSS_T": (0, 60), "COM_RC_IN_MODE": (0, 4), "COM_RCL_EXCEPT": (0, 7), "COM_DL_LOSS_T": (5, 300),
    "NAV_DLL_ACT": (0, 6), "NAV_RCL_ACT": (1, 6), "NAV_ACC_RAD": (0.05, 200.0),
    "MIS_TAKEOFF_ALT": (0, math.inf), "RTL_RETURN_ALT": (0, math.inf), "RTL_DESCEND_ALT": (0, math.inf),
    "MPC_XY_P": (0, 2), "MPC_Z_P": (0.1, 1.5),
    "MPC_XY_VEL_P_ACC": (1.2, 5), "MPC_XY_VEL_I_ACC": (0, 60), "MPC_XY_VEL_D_ACC": (0.1, 2),
    "MPC_Z_VEL_P_ACC": (2, 15), "MPC_Z_VEL_I_ACC": (0.2, 3), "MPC_Z_VEL_D_ACC": (0, 2),
    "MPC_XY_VEL_MAX": (0, 20), "MPC_XY_CRUISE": (3, 20), "MPC_Z_VEL_MAX_UP": (0.5, 8), "MPC_Z_VEL_MAX_DN": (0.5, 4),
    "MPC_ACC_HOR": (2, 15), "MPC_ACC_HOR_MAX": (2, 15), "MPC_ACC_UP_MAX": (2, 15), "MPC_ACC_DOWN_MAX": (2, 15),
    "MPC_TILTMAX_AIR": (20, 89), "MPC_TILTMAX_LND": (5, 89),
    "MPC_THR_HOVER": (0.1, 0.8), "MPC_THR_MIN": (0.05, 0.5), "MPC_THR_MAX": (0, 1),
    "MPC_TKO_SPEED": (1, 5), "MPC_LAND_SPEED": (0.6, math.inf), "MPC_LAND_ALT1": (0, 122), "MPC_LAND_ALT2": (0, 122),
    "MPC_YAWRAUTO_MAX": (5, 360),
    "MC_ROLL_P": (0, 12), "MC_PITCH_P": (0, 12), "MC_YAW_P": (0, 5), "MC_YAW_WEIGHT": (0, 1),
    "MC_ROLLRATE_MAX": (0, 1800), "MC_PITCHRATE_MAX": (0, 1800), "MC_YAWRATE_MAX": (0, 1800),
    "MC_ROLLRATE_P": (0.01, 0.5), "MC_ROLLRATE_I": (0, math.inf), "MC_ROLLRATE_D": (0, 0.01),
    "MC_PITCHRATE_P": (0.01, 0.6), "MC_PITCHRATE_I": (0, math.inf), "MC_PITCHRATE_D": (0, math.inf),
    "MC_YAWRATE_P": (0, 0.6), "MC_YAWRATE_I": (0, math.inf), "MC_YAWRATE_D": (0, math.inf),
    "LNDMC_Z_VEL_MAX": (0, math.inf), "LNDMC_TRIG_TIME": (0.1, 10.0),
    "BAT1_CAPACITY": (-1, 100000),
}


def clamp_to_px4_range(name: str, value: float) -> float:
    """`value` limited to PX4's metadata range of `name` (unchanged when PX4 gives none)."""
    low, high = PX4_PARAM_BOUNDS.get(name, (-math.inf, math.inf))
    return min(max(value, low), high)
