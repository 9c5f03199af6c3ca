"""The stub's parameter table: PX4 names, PX4 types (INT32 / REAL32), PX4 defaults.

The MAVLink parameter protocol (`mavlink_api.py`) serves this table; the controller and the
commander read their gains and limits from it, so a PARAM_SET changes behaviour immediately.
Files in `px4_params/*.params` (QGroundControl format, or `NAME VALUE` lines) are merged in at
start-up so every parameter PX4 would report is also reported here.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from sitl_bridge.data_paths import px4_params_dir

log = logging.getLogger(__name__)

MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9

#: Default location of the shipped PX4 parameter overrides (see sitl_bridge.data_paths).
PX4_PARAMS_DIR = px4_params_dir()

_I = MAV_PARAM_TYPE_INT32
_F = MAV_PARAM_TYPE_REAL32

# name: (PX4 default, type). Values are PX4 v1.14-1.16 defaults unless a comment says otherwise.
PX4_DEFAULTS: dict[str, tuple[float, int]] = {
    # system / identity
    "MAV_SYS_ID": (1, _I),
    "MAV_COMP_ID": (1, _I),
    "MAV_TYPE": (2, _I),
    "SYS_AUTOSTART": (10015, _I),
    "SYS_HITL": (0, _I),
    "CAL_ACC0_ID": (1310988, _I),   # non-zero: calibrated (what PX4 SITL reports)
    "CAL_GYRO0_ID": (1310988, _I),
    "CAL_MAG0_ID": (197388, _I),
    "CAL_BARO0_ID": (6620172, _I),
    "SENS_BOARD_ROT": (0, _I),
    # commander
    "COM_ARM_WO_GPS": (1, _I),
    "COM_DISARM_LAND": (2.0, _F),     # s after landing
    "COM_DISARM_PRFLT": (10.0, _F),   # s after arming without takeoff
    "COM_OF_LOSS_T": (1.0, _F),       # s of simulated time without offboard setpoint
    "COM_OBL_RC_ACT": (0, _I),        # 0 position (no RC: hold), 3 return, 4 land, 5 hold, 7 disarm
    "COM_RC_IN_MODE": (4, _I),
    "COM_RCL_EXCEPT": (4, _I),
    "COM_DL_LOSS_T": (10, _I),
    "COM_LOW_BAT_ACT": (0, _I),
    "NAV_DLL_ACT": (0, _I),
    "NAV_RCL_ACT": (2, _I),
    "MIS_TAKEOFF_ALT": (2.5, _F),     # m above home
    "NAV_ACC_RAD": (2.0, _F),
    "RTL_RETURN_ALT": (30.0, _F),
    "RTL_DESCEND_ALT": (10.0, _F),
    # multicopter position control (mc_pos_control)
    "MPC_XY_P": (0.95, _F),
    "MPC_Z_P": (1.0, _F),
    "MPC_XY_VEL_P_ACC": (1.8, _F),
    "MPC_XY_VEL_I_ACC": (0.4, _F),
    "MPC_XY_VEL_D_ACC": (0.2, _F),
    "MPC_Z_VEL_P_ACC": (4.0, _F),
    "MPC_Z_VEL_I_ACC": (2.0, _F),
    "MPC_Z_VEL_D_ACC": (0.0, _F),
    "MPC_XY_VEL_MAX": (12.0, _F),
    "MPC_XY_CRUISE": (5.0, _F),
    "MPC_Z_VEL_MAX_UP": (3.0, _F),
    "MPC_Z_VEL_MAX_DN": (1.5, _F),
    "MPC_ACC_HOR": (3.0, _F),
    "MPC_ACC_HOR_MAX": (5.0, _F),
    "MPC_ACC_UP_MAX": (4.0, _F),
    "MPC_ACC_DOWN_MAX": (3.0, _F),
    "MPC_TILTMAX_AIR": (45.0, _F),    # deg
    "MPC_TILTMAX_LND": (12.0, _F),    # deg
    "MPC_THR_HOVER": (0.54, _F),      # Iris: 1.55 kg * g / 28.3 N max thrust
    "MPC_THR_MIN": (0.12, _F),
    "MPC_THR_MAX": (1.0, _F),
    "MPC_TKO_SPEED": (1.5, _F),
    "MPC_LAND_SPEED": (0.7, _F),
    "MPC_LAND_ALT1": (10.0, _F),
    "MPC_LAND_ALT2": (5.0, _F),
    "MPC_USE_HTE": (1, _I),
    "MPC_YAWRAUTO_MAX": (45.0, _F),   # deg/s
    # multicopter attitude / rate control (mc_att_control, mc_rate_control)
    "MC_ROLL_P": (6.5, _F),
    "MC_PITCH_P": (6.5, _F),
    "MC_YAW_P": (2.8, _F),
    "MC_YAW_WEIGHT": (0.4, _F),
    "MC_ROLLRATE_MAX": (220.0, _F),   # deg/s
    "MC_PITCHRATE_MAX": (220.0, _F),
    "MC_YAWRATE_MAX": (200.0, _F),
    # rate PIDs output normalised torque like PX4; the mixer scales it by the airframe's
    # maximum torque about each axis (see mixer.QuadGeometry).
    "MC_ROLLRATE_P": (0.15, _F),
    "MC_ROLLRATE_I": (0.2, _F),
    "MC_ROLLRATE_D": (0.003, _F),
    "MC_PITCHRATE_P": (0.15, _F),
    "MC_PITCHRATE_I": (0.2, _F),
    "MC_PITCHRATE_D": (0.003, _F),
    "MC_YAWRATE_P": (0.2, _F),
    "MC_YAWRATE_I": (0.1, _F),
    "MC_YAWRATE_D": (0.0, _F),
    # land detector
    "LNDMC_Z_VEL_MAX": (0.5, _F),
    "LNDMC_XY_VEL_MAX": (1.5, _F),
    "LNDMC_TRIG_TIME": (1.0, _F),
    # estimator (EKF2 names the stub's filter honours)
    "EKF2_HGT_REF": (0, _I),          # 0 baro, 1 GPS
    "EKF2_GPS_DELAY": (10.0, _F),     # ms (informational)
    # battery (the stub reports a steady full pack)
    "BAT1_N_CELLS": (4, _I),
    "BAT1_V_CHARGED": (4.05, _F),
    "BAT1_CAPACITY": (-1.0, _F),
}


def encode_param_value(value: float, param_type: int) -> bytes:
    """The 4 bytes of PARAM_VALUE.param_value: PX4 copies INT32 bits into the float field.

    Bytes, not a Python float: an int whose bits form a signalling NaN would be altered by a
    float round trip (CPUs quiet NaNs when widening to double)."""
    if param_type == MAV_PARAM_TYPE_INT32:
        return struct.pack("<i", int(value))
    return struct.pack("<f", value)


def decode_param_value(raw: bytes, param_type: int) -> float:
    """Inverse of `encode_param_value` for the first 4 bytes of a PARAM_SET/PARAM_VALUE payload."""
    if param_type == MAV_PARAM_TYPE_INT32:
        return float(struct.unpack_from("<i", raw)[0])
    return float(struct.unpack_from("<f", raw)[0])


@dataclass
class Param:
    """One parameter: PX4 name (at most 16 chars), value, MAV_PARAM_TYPE. Change values through
    `ParamTable.set` (it keeps the fast `values` view in step)."""

    name: str
    value: float
    param_type: int

    @property
    def wire_bytes(self) -> bytes:
        """param_value as PX4 puts it in PARAM_VALUE (bytewise for INT32)."""
        return encode_param_value(self.value, self.param_type)


class ParamTable:
    """Ordered parameters with PX4 names and types; index order is stable for PARAM_VALUE.

    px4_params_dir: `*.params` files applied over the defaults, in name order (the same
        overrides sitl-bridge gives real PX4, so both autopilots behave alike); None: none.
    speed_factor: for `NAME SECONDS wall [MAX]` lines, the timeout is multiplied by this
        (0 = as fast as possible counts as 30) and capped at MAX, so that it stays SECONDS of
        wall time; None leaves such values unscaled.
    """

    def __init__(self, defaults: dict[str, tuple[float, int]] | None = None,
                 *, px4_params_dir: Path | None = PX4_PARAMS_DIR, speed_factor: float | None = None) -> None:
        self._params: dict[str, Param] = {}
        self._names: list[str] = []
        #: name -> value, kept in step with the table: the controllers' fast read path
        self.values: dict[str, float] = {}
        #: bumped on every change, so per-step code can cache derived gains until it moves
        self.version = 0
        for name, (value, param_type) in (defaults if defaults is not None else PX4_DEFAULTS).items():
            self._add(name, value, param_type)
        if px4_params_dir is not None:
            for path in sorted(Path(px4_params_dir).glob("*.params")):
                for entry in read_params_file(path):
                    value = entry.value
                    if entry.wall and speed_factor is not None:
                        factor = speed_factor if speed_factor > 0 else 30.0
                        value *= factor
                        if entry.wall_max is not None:
                            value = min(value, entry.wall_max)
                    known = self._params.get(entry.name)
                    self._add(entry.name, value, known.param_type if known else entry.param_type)

    def _add(self, name: str, value: float, param_type: int) -> None:
        if param_type == MAV_PARAM_TYPE_INT32:
            value = float(int(value))
        self.values[name] = float(value)
        self.version += 1
        if name in self._params:
            self._params[name].value = float(value)
            self._params[name].param_type = param_type
            return
        self._params[name] = Param(name, float(value), param_type)
        self._names.append(name)

    def __len__(self) -> int:
        return len(self._names)

    def __contains__(self, name: object) -> bool:
        return name in self._params

    def __iter__(self) -> Iterator[Param]:
        return (self._params[n] for n in self._names)

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def get(self, name: str) -> Param | None:
        """The Param called `name`, or None."""
        return self._params.get(name)

    def index_of(self, name: str) -> int:
        """Position of `name` in the table (PARAM_VALUE.param_index)."""
        return self._names.index(name)

    def at(self, index: int) -> Param | None:
        """The Param at `index`, or None when out of range."""
        return self._params[self._names[index]] if 0 <= index < len(self._names) else None

    def set(self, name: str, value: float) -> Param:
        """Set an existing parameter (INT32 values are truncated); KeyError if unknown."""
        param = self._params[name]
        if not math.isfinite(value):
            raise ValueError(f"{name}: value must be finite, got {value}")
        param.value = float(int(value)) if param.param_type == MAV_PARAM_TYPE_INT32 else float(value)
        self.values[name] = param.value
        self.version += 1
        return param

    def add(self, name: str, value: float, param_type: int) -> Param:
        """Add (or overwrite) a parameter; for tests and airframe-specific tables."""
        self._add(name, value, param_type)
        return self._params[name]


@dataclass(frozen=True)
class ParamFileEntry:
    """One line of a `.params` file."""

    name: str
    value: float
    param_type: int
    wall: bool = False              # a timeout meant in wall-clock seconds
    wall_max: float | None = None   # cap after scaling by the speed factor


def read_params_file(path: Path) -> Iterable[ParamFileEntry]:
    """Entries of a `.params` file: QGC lines (`sysid compid NAME value type`, tab separated)
    or sitl-bridge lines (`NAME VALUE [wall [MAX]]`, `#` comments)."""
    for line_no, raw in enumerate(Path(path).read_text().splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.split()
        try:
            if len(fields) == 5 and fields[0].isdigit() and fields[1].isdigit():
                entry = ParamFileEntry(fields[2], float(fields[3]), int(fields[4]))
            elif len(fields) in (2, 3, 4) and (len(fields) == 2 or fields[2] == "wall"):
                text = fields[1]
                is_int = text.lstrip("-").isdigit()
                entry = ParamFileEntry(
                    fields[0], float(text), MAV_PARAM_TYPE_INT32 if is_int else MAV_PARAM_TYPE_REAL32,
                    wall=len(fields) >= 3, wall_max=float(fields[3]) if len(fields) == 4 else None)
            else:
                raise ValueError("unknown line format")
        except ValueError:
            log.warning("%s:%d: unreadable parameter line %r skipped", path, line_no, raw)
            continue
        if entry.param_type not in (MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32) or len(entry.name) > 16:
            log.warning("%s:%d: parameter %r (type %d) not served", path, line_no, entry.name, entry.param_type)
            continue
        yield entry
