"""A ground station against the stub: real MAVProxy (the `gcs` extra) on the GCS port (UDP 14550),
as a user would start it: it sees the vehicle and no phantom 1:1, no fence breach, and all parameters."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from sitl_bridge.autopilot.stub.modes import system_id_for
from sitl_bridge.autopilot.stub.params import ParamTable

MAVPROXY = shutil.which("mavproxy.py")
pytestmark = pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy not installed (pip install -e '.[gcs]')")


def test_mavproxy_sees_one_vehicle_without_fence_breach_and_fetches_parameters(free_instance: int,
                                                                              tmp_path: Path) -> None:
    simulator = subprocess.Popen(
        [sys.executable, "-m", "sitl_bridge", "run", "--speed-factor", "1", "--duration", "40",
         "--instance-base", str(free_instance), "--quiet"],
        cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        result = subprocess.run(
            [MAVPROXY, "--master=udpin:127.0.0.1:14550", "--daemon", "--non-interactive",
             # our vehicle, not another simulator's on this machine (all GCS links send to 14550)
             f"--target-system={system_id_for(free_instance)}", "--cmd=param fetch"],
            cwd=tmp_path, capture_output=True, text=True, timeout=25)
        output = result.stdout + result.stderr
    except subprocess.TimeoutExpired as exc:  # MAVProxy runs until stopped: read what it said
        output = (exc.stdout or b"").decode() + (exc.stderr or b"").decode()
    finally:
        simulator.terminate()
        simulator.wait(timeout=30)
    sysid = system_id_for(free_instance)
    detected = [line for line in output.splitlines() if line.startswith("Detected vehicle")]
    assert f"Detected vehicle {sysid}:1 on link 0" in detected, output
    # No phantom 1:1 beside it (other simulators on this machine may legitimately show up too:
    # every instance's GCS link sends to 14550, and tests take instances from 20 on).
    assert "Detected vehicle 1:1 on link 0" not in detected, output
    assert "fence breach" not in output
    # every parameter the stub serves: its PX4 defaults and the px4_params/ overrides
    assert f"Received {len(ParamTable())} parameters" in output, output
