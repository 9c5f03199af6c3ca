"""`sitl-bridge run` as a user runs it: a subprocess, from another working directory."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_session import pick_mavlink_instances, ports_released

from sitl_bridge.commands.run import speed_factor_arg


def _command(*args: str) -> list[str]:
    return [sys.executable, "-m", "sitl_bridge", "run", *args]


def _session_processes(sid: int) -> list[int]:
    """Pids still alive in session `sid` (the command and anything it started there)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        state, session_id = fields[0], int(fields[3])
        if session_id == sid and state != "Z":
            pids.append(int(entry.name))
    return pids


def wait_until_serving(process: subprocess.Popen, timeout_s: float) -> list[str]:
    """Read `sitl-bridge run` output until a status line shows simulated time advancing (or
    the output ends / `timeout_s` passes); returns the lines read."""
    output: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        if not line:
            break
        output.append(line)
        if line.startswith("t=") and "t=    0.00" not in line:
            break
    return output


def test_speed_factor_argument() -> None:
    assert speed_factor_arg("max") == 0.0
    assert speed_factor_arg("0") == 0.0
    assert speed_factor_arg("3") == 3.0
    assert speed_factor_arg("0.5") == 0.5
    for bad in ("-1", "fast", "nan"):
        with pytest.raises(Exception, match="expected a number"):
            speed_factor_arg(bad)


def test_demo_at_full_speed_exits_zero(tmp_path: Path) -> None:
    base = pick_mavlink_instances(1)
    result = subprocess.run(
        _command("--speed-factor", "0", "--demo", "--duration", "40", "--instance-base", str(base)),
        cwd=tmp_path, capture_output=True, text=True, timeout=240,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    out = result.stdout
    for direction in ("east", "west", "south", "north", "up", "down"):
        assert f"vehicle {base} {direction}" in out, out
    assert "landed and disarmed" in out and "demo done" in out
    assert ports_released(base)


def test_fixed_duration_without_demo(tmp_path: Path) -> None:
    base = pick_mavlink_instances(1)
    result = subprocess.run(
        _command("--speed-factor", "max", "--duration", "2", "--instance-base", str(base)),
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "t=    2.00 s" in result.stdout
    assert f"[{base}] Hold disarmed" in result.stdout


def test_bad_world_is_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("world:\n  name: bad\n  vehicles: 3\n")
    result = subprocess.run(_command(str(bad), "--duration", "1"), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0], result.stderr


@pytest.mark.parametrize(("stub_process", "sig"), [
    (False, signal.SIGINT), (True, signal.SIGINT), (False, signal.SIGTERM),
], ids=["in-process", "stub-processes", "sigterm"])
def test_ctrl_c_leaves_no_process_or_port_behind(stub_process: bool, sig: int) -> None:
    base = pick_mavlink_instances(2)
    args = ["--speed-factor", "1", "--vehicles", "2", "--instance-base", str(base)]
    if stub_process:
        args.append("--stub-process")
    process = subprocess.Popen(_command(*args), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True, start_new_session=True)
    output = []
    try:
        output = wait_until_serving(process, 60)
        assert any(line.startswith("t=") for line in output), "".join(output)
        process.send_signal(sig)
        rest, _ = process.communicate(timeout=30)
        output.append(rest)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == 130, "".join(output)
    assert "Traceback" not in "".join(output)
    assert _session_processes(process.pid) == []
    assert ports_released(base) and ports_released(base + 1)


def test_external_autopilot_started_by_hand_flies_the_demo(tmp_path: Path) -> None:
    """`run --autopilot external` waits like Gazebo; a stub started on its own plugs in."""
    base = pick_mavlink_instances(1)
    run = subprocess.Popen(_command("--autopilot", "external", "--speed-factor", "0", "--demo",
                                    "--instance-base", str(base)),
                           cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    stub = subprocess.Popen([sys.executable, "-m", "sitl_bridge", "stub", "-i", str(base), "--once"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        out, _ = run.communicate(timeout=240)
        assert run.returncode == 0, out
        assert "waiting for autopilots" in out and "landed and disarmed" in out
        assert stub.wait(timeout=30) == 0  # --once: it exits when the simulator goes
    finally:
        for process in (run, stub):
            if process.poll() is None:
                process.kill()
                process.wait()
    assert ports_released(base)


def test_bench_stub_runs_and_reports_both_cases(capsys) -> None:
    import argparse

    from sitl_bridge.bench import stub

    assert stub.run(argparse.Namespace(seconds=0.2)) == 0
    out = capsys.readouterr().out
    for vehicles in (1, 2):
        for phase in ("ground", "flying"):
            assert f"{vehicles} vehicle(s) {phase}" in out, out


def test_external_mavsdk_script_flies_a_free_running_simulator() -> None:
    """What a user's MAVSDK script sees: `sitl-bridge run` free-running at 5x, the client with
    no simulation clock (its waits are wall-time polls of telemetry)."""
    from sitl_bridge.client import OffboardClient

    base = pick_mavlink_instances(1)
    process = subprocess.Popen(_command("--speed-factor", "5", "--quiet", "--instance-base", str(base)),
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        with OffboardClient(base) as client:  # connect() waits up to 30 s of wall time
            assert client.clock is None and client.autopilot_type() == "PX4"
            client.wait_healthy(timeout_s=30)
            client.arm()
            assert client.takeoff(2.5, timeout_s=30) == pytest.approx(2.5, abs=0.3)
            client.start_offboard()
            assert client.flight_mode() == "OFFBOARD"
            client.hold()
            client.land(timeout_s=60)
        process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=30)
        assert process.returncode == 130, err
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert ports_released(base)


def test_trained_policy_flies_through_mavsdk(tmp_path: Path) -> None:
    """`run --policy`: a trained network flies its scenario through the stub's MAVLink API."""
    world = str(Path(__file__).resolve().parent.parent / "worlds" / "empty.yaml")
    train = subprocess.run(
        [sys.executable, "-m", "sitl_bridge", "train", world, "--episodes", "2", "--out", str(tmp_path),
         "--batch-size", "16", "--layers", "2", "--hidden-units", "16", "--eval-every", "0",
         "--eval-episodes", "0", "--no-progress"],
        capture_output=True, text=True, timeout=240)
    assert train.returncode == 0, train.stdout + train.stderr
    (run_dir,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    base = pick_mavlink_instances(1)
    result = subprocess.run(
        _command(world, "--policy", str(run_dir), "--episodes", "2", "--speed-factor", "0",
                 "--instance-base", str(base)),
        cwd=tmp_path, capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "episode 0 drone 0:" in result.stdout and "episode 1 drone 0:" in result.stdout
    assert "(2 episodes)" in result.stdout
    assert ports_released(base)
    # the same network as a policy-only export, the run slimmed: flies the same episode
    slim = subprocess.run([sys.executable, "-m", "sitl_bridge", "export", str(run_dir), "--slim"],
                          capture_output=True, text=True, timeout=120)
    assert slim.returncode == 0, slim.stderr
    again = subprocess.run(
        _command(world, "--policy", str(run_dir / "policy.safetensors"), "--episodes", "1", "--speed-factor", "0",
                 "--instance-base", str(base)),
        cwd=tmp_path, capture_output=True, text=True, timeout=240)
    assert again.returncode == 0, again.stdout + again.stderr
    first = next(line for line in result.stdout.splitlines() if line.startswith("episode 0 drone 0:"))
    assert first in again.stdout
    assert ports_released(base)


def test_policy_for_another_scenario_is_a_clear_error(tmp_path: Path) -> None:
    repo = Path(__file__).resolve().parent.parent
    train = subprocess.run(
        [sys.executable, "-m", "sitl_bridge", "train", str(repo / "worlds" / "empty.yaml"), "--episodes", "1",
         "--out", str(tmp_path), "--batch-size", "16", "--layers", "2", "--hidden-units", "16",
         "--eval-every", "0", "--eval-episodes", "0", "--no-progress"],
        capture_output=True, text=True, timeout=240)
    assert train.returncode == 0, train.stdout + train.stderr
    (run_dir,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    result = subprocess.run(
        _command(str(repo / "worlds" / "window.yaml"), "--policy", str(run_dir), "--speed-factor", "0",
                 "--instance-base", str(pick_mavlink_instances(1))),
        cwd=tmp_path, capture_output=True, text=True, timeout=240)
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr and "observation" in result.stderr
