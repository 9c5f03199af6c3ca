#!/usr/bin/env python3
"""Fly the thesis's 1 s, 1 m/s velocity actions with the stub and compare with real PX4.

Reads the action sequence that PX4 (SIH) flew in `px4-sih-action-response.csv` (LOCAL_POSITION_NED
at ~30 Hz with the action code flown), flies the same sequence with the built-in stub autopilot
on the real physics and sensors (no sockets; offboard setpoints re-sent at 20 Hz of simulated
time like MAVSDK), and prints the per-step displacement of both and a summary per kind of step:
first step from hover, repeated step, vertical step, coasting after a switch to zero velocity.

    python tools/stub_response.py [--csv PATH] [--world worlds/empty.yaml] [--seed 0] [--ground-truth]
                                  [--drag PER_S]
"""

from __future__ import annotations

import argparse
import bisect
import csv
import statistics
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sitl_bridge.autopilot.stub import CommandResult, MainMode  # noqa: E402
from sitl_bridge.autopilot.stub.harness import StubHarness  # noqa: E402
from sitl_bridge.client.actions import Action, action_velocity_ned  # noqa: E402
from sitl_bridge.physics import IrisParams  # noqa: E402
from sitl_bridge.world.loader import load_world  # noqa: E402

DEFAULT_CSV = REPO / "tests" / "data" / "px4-sih-action-response.csv"
"""The real-PX4 (SIH) recording shipped with the repository (a copy of the shared data)."""
STEP_S = 1.0
HOVER = int(Action.HOVER)


@dataclass(frozen=True)
class Step:
    """One 1 s action and the displacement (NED, m) it produced."""

    action: int
    previous: int
    displacement_ned_m: np.ndarray

    @property
    def kind(self) -> str | None:
        """first / repeated / vertical / coast, or None for hover after hover."""
        if self.action == HOVER:
            return "coast" if self.previous not in (HOVER, -1) else None
        if self.action in (Action.UP, Action.DOWN):
            return "vertical"
        return "repeated" if self.previous == self.action else "first"

    @property
    def along_m(self) -> float:
        """Displacement along the commanded direction (the previous one for coasting)."""
        code = self.previous if self.action == HOVER else self.action
        if code < 0 or code == HOVER:
            return float("nan")
        return float(self.displacement_ned_m @ action_velocity_ned(code))


def px4_steps(csv_path: Path) -> list[Step]:
    """1 s steps of the recorded flight: each run of an action code split into 1 s pieces."""
    with open(csv_path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    times = [int(r["time_boot_ms"]) for r in rows]
    actions = [int(r["action"]) for r in rows]
    positions = np.array([[float(r["x_north_m"]), float(r["y_east_m"]), float(r["z_down_m"])] for r in rows])

    def position_at(ms: float) -> np.ndarray:
        i = min(max(bisect.bisect_left(times, ms), 1), len(times) - 1)
        t0, t1 = times[i - 1], times[i]
        w = 0.0 if t1 == t0 else min(max((ms - t0) / (t1 - t0), 0.0), 1.0)
        return positions[i - 1] * (1 - w) + positions[i] * w

    starts = [i for i in range(1, len(rows)) if actions[i] != actions[i - 1]] + [len(rows)]
    steps: list[Step] = []
    previous = -1
    for a, b in zip(starts, starts[1:], strict=False):
        code = actions[a]
        if code < 0:
            continue
        count = max(1, round((times[b - 1] - times[a]) / 1000.0))
        for k in range(count):
            t = times[a] + 1000.0 * k
            steps.append(Step(code, previous, position_at(t + 1000.0) - position_at(t)))
            previous = code
    return steps


def stub_steps(actions: list[int], world_path: Path, seed: int, ground_truth: bool,
               drag_per_s: float | None = None) -> list[Step]:
    """Fly `actions` with the stub from an offboard hover; displacement of its own estimate
    (what LOCAL_POSITION_NED reports, as in the PX4 recording). `drag_per_s`: give the simulated
    Iris this much horizontal drag (m/s^2 per m/s) instead of its rotor drag (~0.36)."""
    airframe = None
    if drag_per_s is not None:
        iris = IrisParams()
        hover_omega_sum = 4 * (iris.hover_input() * iris.input_scaling_rad_s + iris.zero_position_armed_rad_s)
        airframe = replace(iris, rotor_drag_coefficient=drag_per_s * iris.mass_kg / hover_omega_sum)
    with StubHarness(load_world(world_path), seed=seed, ground_truth_estimate=ground_truth,
                     airframe=airframe) as harness:
        ap = harness.autopilot
        harness.take_off()
        ap.set_velocity_setpoint_ned((0.0, 0.0, 0.0))
        if ap.set_mode(MainMode.OFFBOARD, 0) is not CommandResult.ACCEPTED:
            raise RuntimeError("stub refused offboard")
        harness.fly_velocity((0.0, 0.0, 0.0), 3.0)
        steps: list[Step] = []
        previous = -1
        for code in actions:
            start = np.array(ap.estimate.position_ned_m)
            harness.fly_velocity(tuple(action_velocity_ned(code)), STEP_S)
            steps.append(Step(code, previous, np.array(ap.estimate.position_ned_m) - start))
            previous = code
        return steps


def summarize(steps: list[Step]) -> dict[str, list[float]]:
    """Along-axis displacement per kind of step."""
    out: dict[str, list[float]] = {"first": [], "repeated": [], "vertical": [], "coast": []}
    for step in steps:
        if step.kind is not None:
            out[step.kind].append(step.along_m)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--csv", type=Path, default=DEFAULT_CSV, help="PX4 recording (default: tests/data/px4-sih-action-response.csv)")
    parser.add_argument("--world", type=Path, default=REPO / "worlds" / "empty.yaml")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ground-truth", action="store_true", help="stub estimates from ground truth")
    parser.add_argument("--drag", type=float, default=None, metavar="PER_S",
                        help="horizontal drag of the simulated vehicle in m/s^2 per m/s (Iris rotor drag "
                             "is ~0.36; PX4's SIH quad, which made the recording, uses 1.0)")
    args = parser.parse_args(argv)

    if not args.csv.is_file():
        print(f"error: {args.csv}: no such PX4 recording (pass --csv PATH)", file=sys.stderr)
        return 2
    if not args.world.is_file():
        print(f"error: {args.world}: no such world file (pass --world PATH)", file=sys.stderr)
        return 2
    px4 = px4_steps(args.csv)
    stub = stub_steps([s.action for s in px4], args.world, args.seed, args.ground_truth, args.drag)
    names = {int(a): a.name.lower() for a in Action}
    print(f"{'#':>3} {'action':>7} {'kind':>9} | {'PX4 SIH N E D (m)':>24} {'along':>6} | "
          f"{'stub N E D (m)':>24} {'along':>6}")
    for i, (p, s) in enumerate(zip(px4, stub, strict=True)):
        pn, sn = p.displacement_ned_m, s.displacement_ned_m
        print(f"{i:3d} {names[p.action]:>7} {p.kind or '':>9} | {pn[0]:7.2f} {pn[1]:7.2f} {pn[2]:7.2f}  "
              f"{p.along_m:6.2f} | {sn[0]:7.2f} {sn[1]:7.2f} {sn[2]:7.2f}  {s.along_m:6.2f}")
    print("\nalong-axis displacement per 1 s step (mean [min..max], m):")
    expected = {"first": "0.3-0.4", "repeated": "0.6-0.85", "vertical": "0.7-0.85", "coast": "0.2-0.3"}
    ps, ss = summarize(px4), summarize(stub)
    for kind in ps:
        def fmt(values: list[float]) -> str:
            if not values:
                return "-"
            return f"{statistics.mean(values):5.2f} [{min(values):.2f}..{max(values):.2f}] n={len(values)}"
        print(f"  {kind:9s} PX4 {fmt(ps[kind]):28s} stub {fmt(ss[kind]):28s} (PX4 fact sheet: {expected[kind]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
