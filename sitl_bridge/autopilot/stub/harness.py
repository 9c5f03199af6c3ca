"""StubHarness: one vehicle's physics + sensors + StubAutopilot in lockstep, no sockets.

For tests, tools (`tools/stub_response.py`) and quick experiments: the same per-step order as
the simulator's Lockstep (sample sensors at t, autopilot answers, physics steps), minus the
protocol. Time is simulated time only.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sitl_bridge.physics import IrisParams, Simulation
from sitl_bridge.sensors import SensorSuite
from sitl_bridge.world.schema import World

from .autopilot import StubAutopilot
from .modes import HOLD, CommandResult, LandedState
from .params import ParamTable


class StubHarness:
    """Vehicle 0 of `world` flown by a StubAutopilot (see module docstring).

    airframe: physics parameters of the simulated Iris (e.g. more drag); the autopilot is not
    told, just as PX4 would not be.
    """

    def __init__(self, world: World, *, seed: int = 0, ground_truth_estimate: bool = False,
                 params: ParamTable | None = None, airframe: IrisParams | None = None) -> None:
        self.sim = Simulation(world, seed=seed, params=airframe)
        self.sensors = SensorSuite(world.home, seed=seed + 1, step_us=self.sim.step_us)
        self.autopilot = StubAutopilot(0, params, ground_truth_estimate=ground_truth_estimate)

    @property
    def position_ned_m(self) -> np.ndarray:
        """True position (world NED) of the vehicle."""
        return self.sim.state(0).position_ned_m

    def run_for(self, seconds: float, until: Callable[[], bool] | None = None) -> bool:
        """Advance `seconds` of simulated time (stop early when `until()` holds; returns it)."""
        sim, sensors, ap = self.sim, self.sensors, self.autopilot
        for _ in range(max(0, round(seconds * 1e6 / sim.step_us))):
            sim.step([ap.update(sensors.sample(sim.state(0), sim.time_us))])
            if until is not None and until():
                return True
        return until is None

    def fly_velocity(self, velocity_ned_m_s: tuple[float, float, float], seconds: float,
                     refresh_s: float = 0.05) -> None:
        """Hold an offboard velocity setpoint for `seconds`, re-sent every `refresh_s` of
        simulated time like MAVSDK's 20 Hz stream (the first one at once)."""
        ap = self.autopilot
        remaining = seconds
        while remaining > 1e-9:
            ap.set_velocity_setpoint_ned(velocity_ned_m_s)
            chunk = min(refresh_s, remaining)
            self.run_for(chunk)
            remaining -= chunk

    def take_off(self, timeout_s: float = 20.0) -> None:
        """Arm as soon as the estimate allows, take off, wait until holding at altitude."""
        ap = self.autopilot
        if not self.run_for(timeout_s, until=lambda: ap.arm() is CommandResult.ACCEPTED):
            raise RuntimeError("stub never became armable")
        if ap.takeoff() is not CommandResult.ACCEPTED:
            raise RuntimeError("takeoff refused")

        def holding() -> bool:
            return (ap.commander.main_mode, ap.commander.sub_mode) == HOLD and \
                ap.landed_state is LandedState.IN_AIR

        if not self.run_for(timeout_s, until=holding):
            raise RuntimeError("takeoff did not finish")

    def close(self) -> None:
        """Free the physics client."""
        self.sim.close()

    def __enter__(self) -> StubHarness:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
