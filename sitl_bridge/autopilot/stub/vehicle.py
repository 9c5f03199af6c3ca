"""StubVehicle: a StubAutopilot with its HIL client and MAVLink API, ready to plug in.

This is what `SimSession` creates per vehicle for `autopilot="stub"` (in-process: pass
`vehicle.pump` to Lockstep's pumps) and what `sitl-bridge stub -i N` runs in its own process.
"""

from __future__ import annotations

from .autopilot import StubAutopilot
from .fence import Fence
from .hil_client import HIL_BASE_PORT, HilClient
from .mavlink_api import MavlinkApi
from .params import ParamTable


class StubVehicle:
    """Autopilot + HIL client (TCP 4560+i) + MAVLink API (UDP 14580+i -> 14540+i, GCS 18570+i).

    instance: vehicle instance i; host: where the simulator listens and the API binds.
    api: serve the MAVLink API (False: HIL only, e.g. the `direct`-like speed runs).
    gcs: also serve the GCS link (18570+i -> 14550).
    speed_factor: scales `wall` timeouts of px4_params/*.params (see ParamTable).
    telemetry_batch_wall_s: the API's `batch_wall_s` (in-process, pumped by a lockstep that
        pumps again when it holds; 0 for a stub in its own process).
    api_streams: the API link's stream set (`MavlinkApi` api_streams: "onboard" or "client").
    fence: the world's workspace for position commands (`fence.py`; None: only the reach bound).
    """

    def __init__(self, instance: int, host: str = "127.0.0.1", *, ground_truth_estimate: bool = False,
                 params: ParamTable | None = None, api: bool = True, gcs: bool = True,
                 hil_base_port: int = HIL_BASE_PORT, speed_factor: float | None = None,
                 telemetry_batch_wall_s: float = 0.0, api_streams: str = "onboard",
                 fence: Fence | None = None) -> None:
        if params is None:
            params = ParamTable(speed_factor=speed_factor)
        self.autopilot = StubAutopilot(instance, params, ground_truth_estimate=ground_truth_estimate)
        self.api = MavlinkApi(self.autopilot, instance, host, gcs=gcs,
                              batch_wall_s=telemetry_batch_wall_s, api_streams=api_streams,
                              fence=fence) if api else None
        self.hil = HilClient(self.autopilot, instance, host, hil_base_port, api=self.api)

    @property
    def instance(self) -> int:
        return self.autopilot.instance

    def connect(self, timeout_s: float) -> bool:
        """Connect to the simulator's HIL server (retrying up to timeout_s of wall time)."""
        return self.hil.connect(timeout_s)

    def pump(self) -> int:
        """Non-blocking: answer pending HIL_SENSOR messages and serve the API (Lockstep pump)."""
        return self.hil.pump()

    def reset(self) -> None:
        """Reboot the autopilot in place (`StubAutopilot.reset`: disarmed, fresh estimator and
        controllers, parameters kept) while the HIL connection and the API sockets stay up, so
        the simulator and MAVSDK keep talking to the same ports. Call it while the simulator
        is held (e.g. inside `SimSession.exclusive()`), never between a HIL_SENSOR and its answer."""
        self.autopilot.reset()

    def close(self) -> None:
        """Close the HIL connection and the API sockets."""
        self.hil.close()
        if self.api is not None:
            self.api.close()

    def __enter__(self) -> StubVehicle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
