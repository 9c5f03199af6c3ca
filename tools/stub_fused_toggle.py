"""Fused vs per-message stub path in ONE process, alternating blocks (load drift cancels).

Sets up what `tools/stub_step_profile.py` flies (one vehicle hovering in OFFBOARD, MAVSDK
connected), runs the lockstep on this thread and alternates, every `--block` simulated seconds,
between the compiled fast paths on (the stub's `FusedSensorStep`, the link's compiled
HIL_ACTUATOR_CONTROLS read) and off (the per-message paths, as before them). Reports the thread
CPU per physics step of each (median over the blocks) and their ratio. "Off" sends the link's
reads through a stand-in that declines at once (one Python call, ~0.1 us, more than before).

Usage: PYTHONPATH=. python tools/stub_fused_toggle.py [--blocks 20] [--block 2.0] [--json F]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from sitl_bridge.autopilot.allocation import claim_free_instances
from sitl_bridge.bench.stub import BENCH_INSTANCE_BASE
from sitl_bridge.client.fleet import Fleet
from sitl_bridge.hil import link as link_module
from sitl_bridge.session import SimSession, default_world_path

_DECLINED = (0, 0, 0, 0, 0.0, 0.0, 0.0, 0.0)


def _declines(data: bytes, scratch: object) -> tuple:
    return _DECLINED


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--blocks", type=int, default=20, help="blocks per mode")
    parser.add_argument("--block", type=float, default=2.0, help="simulated seconds per block")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args()
    compiled_read = link_module.actuator_values
    cpu: dict[str, list[float]] = {"fused": [], "per-message": []}
    with (
        claim_free_instances(1, BENCH_INSTANCE_BASE) as claim,
        SimSession(
            default_world_path(),
            autopilot="stub",
            speed_factor=0,
            instance_base=claim,
            num_vehicles=1,
        ) as session,
        Fleet.for_session(session) as fleet,
    ):
        fleet.wait_healthy()
        fleet.arm()
        fleet.takeoff(2.5)
        fleet.start_offboard()
        session.run_for(2.0)
        hil = session.autopilots.vehicles[0].hil  # type: ignore[attr-defined]
        fused = hil._fused
        lockstep = session.lockstep
        assert lockstep is not None and fused is not None
        steps = lockstep.steps_for(args.block)
        with session.exclusive():
            for i in range(2 * args.blocks):
                mode = ("fused", "per-message")[(i + i // 2) % 2]  # ABBA order
                hil._fused = fused if mode == "fused" else None
                link_module.actuator_values = compiled_read if mode == "fused" else _declines
                t0 = time.thread_time()
                lockstep.run_steps(steps)
                cpu[mode].append((time.thread_time() - t0) / steps * 1e6)
        hil._fused = fused
        link_module.actuator_values = compiled_read
        fleet.land()
    result = {mode: {"median_us": statistics.median(v), "blocks": v} for mode, v in cpu.items()}
    ratio = result["fused"]["median_us"] / result["per-message"]["median_us"]
    for mode, r in result.items():
        print(
            f"{mode:<12} thread CPU per physics step: median {r['median_us']:.1f} us "
            f"(min {min(r['blocks']):.1f}, max {max(r['blocks']):.1f}, {len(r['blocks'])} blocks)"
        )
    print(f"fused / per-message: {ratio:.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps({**result, "ratio": ratio}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
