"""Real PX4 SITL processes as the autopilots of the simulator (`--autopilot px4`).

One `Px4Autopilot` per vehicle instance N runs `px4 -i N -d <rootfs>` (the `bin/px4` of a
`px4_sitl_default` build, its ROMFS `etc` next to it or given) in its own working directory
`<run_dir>/px4/<N>/` with the environment PX4 expects for an external MAVLink simulator:

- `PX4_SIM_MODEL=gazebo-classic_iris` (airframe 10015: rcS then runs
  `simulator_mavlink start -c 4560+N`, so PX4 connects to our `HilLink`);
- `PX4_SIM_SPEED_FACTOR=F` (omitted for F = 0, where rcS would scale timeouts to 0);
- `PX4_HOME_LAT/LON/ALT` from the world's home;
- the overrides of `px4_params/*.params` (format documented there) as `PX4_PARAM_<NAME>`
  (rcS applies them with `param set` early in boot).

rcS rescales a few failsafe timeouts itself when PX4_SIM_SPEED_FACTOR is set, after the
PX4_PARAM_ values (v1.16: x10, x1, x1, x5; older rcS versions used wrong factors, the thesis's
bug; with F = 0 it would set them to 0). So the `wall` timeouts are also checked over MAVLink
once PX4 is up and corrected with PARAM_SET when they differ: what PX4 runs with is observed.

Readiness is observed, never slept for: the simulator link is connected (`HilLink`), and on
PX4's GCS MAVLink port (UDP 18570+N, which we talk to from an ephemeral port, as QGC does)
a HEARTBEAT arrived, SYS_STATUS reports the pre-arm checks passing (or the console printed
"Ready for takeoff!"), a HOME_POSITION was sent (the estimator has a global position) and the
`wall` timeouts read back as configured.

Parameters persisted by PX4 are deleted before each start (every episode starts identical).
PX4's console goes to `console.log` (rotated, capped); a PX4 that dies is reported with the
tail of its output (`Px4Died`). Processes never outlive us: each runs in its own process
group with a parent-death signal, and `stop()`/atexit kill the whole group.
"""

from sitl_bridge.autopilot.px4.fleet import Px4Fleet, Px4SitlFleet
from sitl_bridge.autopilot.px4.observer import GCS_BASE_PORT, Px4Observation
from sitl_bridge.autopilot.px4.params import (
    MAX_SPEED_ASSUMED,
    PARAMS_DIR,
    Px4Param,
    load_param_overrides,
    read_params,
)
from sitl_bridge.autopilot.px4.process import (
    DEFAULT_AIRFRAME,
    Px4Autopilot,
    Px4Config,
    Px4Died,
    Px4Error,
    find_px4_bin,
    find_rootfs,
    prune_logs,
    px4_server_running,
)

__all__ = [
    "DEFAULT_AIRFRAME",
    "GCS_BASE_PORT",
    "MAX_SPEED_ASSUMED",
    "PARAMS_DIR",
    "Px4Autopilot",
    "Px4Config",
    "Px4Died",
    "Px4Error",
    "Px4Fleet",
    "Px4SitlFleet",
    "Px4Observation",
    "Px4Param",
    "find_px4_bin",
    "find_rootfs",
    "load_param_overrides",
    "prune_logs",
    "px4_server_running",
    "read_params",
]
