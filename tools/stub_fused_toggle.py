"""Fused vs per-message stub path in ONE process, alternating blocks (load drift cancels).

Sets up what `tools/stub_step_profile.py` flies (one vehicle hovering in OFFBOARD, MAVSDK
connected), runs the lockstep on this thread and alternates, every `--block` simulated seconds,
between the compiled fast paths on (the stub's `FusedSensorStep`, the link's compiled
HIL_ACTUATOR_CONTROLS read and HIL_SENSOR framing) and off (the per-message paths, as before
them). Reports the thread CPU per physics step and the real-time factor (wall) of each,
medians over the blocks, and their ratios.

"Off" runs the stub's per-message path (`HilClient._fused = None`) and, with `--old-tree`, the
link's `_encode_sensor`, `_handle_bytes` and `_handle_actuators` of that source tree (e.g. a
checkout of main), bound to the live link: the old protocol path in this process. Without it,
the link keeps its compiled HIL_SENSOR framing and its reads go through a stand-in that
declines at once (one Python call, ~0.1 us).

Usage: PYTHONPATH=. python tools/stub_fused_toggle.py [--old-tree DIR] [--blocks 20] [--block 2.0]
[--json F]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import sys
import time
import types
from pathlib import Path
from typing import Any

from sitl_bridge.autopilot.allocation import claim_free_instances
from sitl_bridge.bench.stub import BENCH_INSTANCE_BASE
from sitl_bridge.client.fleet import Fleet
from sitl_bridge.hil import link as link_module
from sitl_bridge.session import SimSession, default_world_path

_DECLINED = (0, 0, 0, 0, 0.0, 0.0, 0.0, 0.0)


def _declines(data: bytes, scratch: object) -> tuple:
    return _DECLINED


def _old_link_methods(tree: Path, link: Any) -> dict[str, Any]:
    """The link methods of `tree`'s `sitl_bridge/hil/link.py`, bound to `link`."""
    spec = importlib.util.spec_from_file_location(
        "_old_hil_link", tree / "sitl_bridge" / "hil" / "link.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return {
        name: types.MethodType(getattr(module.HilLink, name), link)
        for name in ("_encode_sensor", "_handle_bytes", "_handle_actuators")
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--blocks", type=int, default=20, help="blocks per mode")
    parser.add_argument("--block", type=float, default=2.0, help="simulated seconds per block")
    parser.add_argument("--old-tree", type=Path, help="source tree whose link methods 'off' runs")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args()
    compiled_read = link_module.actuator_values
    cpu: dict[str, list[float]] = {"fused": [], "per-message": []}
    rtf: dict[str, list[float]] = {"fused": [], "per-message": []}
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
        link = lockstep.links[0]
        old = _old_link_methods(args.old_tree, link) if args.old_tree else {}
        steps = lockstep.steps_for(args.block)
        with session.exclusive():
            for i in range(2 * args.blocks):
                mode = ("fused", "per-message")[(i + i // 2) % 2]  # ABBA order
                hil._fused = fused if mode == "fused" else None
                for name in old:  # instance attributes shadow the class's methods
                    if mode == "fused":
                        link.__dict__.pop(name, None)
                    else:
                        setattr(link, name, old[name])
                link_module.actuator_values = compiled_read if mode == "fused" or old else _declines
                t0, w0 = time.thread_time(), time.perf_counter()
                lockstep.run_steps(steps)
                cpu[mode].append((time.thread_time() - t0) / steps * 1e6)
                rtf[mode].append(steps * session.step_s / (time.perf_counter() - w0))
        hil._fused = fused
        for name in old:
            link.__dict__.pop(name, None)
        link_module.actuator_values = compiled_read
        fleet.land()
    result = {
        mode: {
            "median_us": statistics.median(v),
            "blocks": v,
            "median_rtf": statistics.median(rtf[mode]),
            "rtf_blocks": rtf[mode],
        }
        for mode, v in cpu.items()
    }
    ratio = result["fused"]["median_us"] / result["per-message"]["median_us"]
    for mode, r in result.items():
        print(
            f"{mode:<12} thread CPU per physics step: median {r['median_us']:.1f} us "
            f"(min {min(r['blocks']):.1f}, max {max(r['blocks']):.1f}, {len(r['blocks'])} blocks); "
            f"real-time factor median {r['median_rtf']:.1f}x"
        )
    rtf_ratio = result["fused"]["median_rtf"] / result["per-message"]["median_rtf"]
    print(f"fused / per-message: thread CPU {ratio:.3f}, real-time factor {rtf_ratio:.3f}")
    if args.json:
        Path(args.json).write_text(
            json.dumps({**result, "ratio": ratio, "rtf_ratio": rtf_ratio}, indent=2) + "\n"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
