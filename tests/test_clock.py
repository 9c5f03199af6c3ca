"""One conversion from simulated seconds to physics steps (`sitl_bridge.world.clock`): the
backends fly the same steps at any physics rate the loader accepts, and the loader refuses a
rate that cannot fly the task's spans exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from sitl_bridge.envs import make_env
from sitl_bridge.errors import ConfigError
from sitl_bridge.world import load_world
from sitl_bridge.world.clock import DEFAULT_STEP_US, nearest_whole_steps_s, whole_steps

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


def with_step(tmp_path: Path, source: str, step_us: int, **action: float) -> Path:
    """A copy of worlds/<source> whose physics runs at `step_us` (and task.action overrides)."""
    data = yaml.safe_load((WORLDS / source).read_text())
    data["world"].setdefault("physics", {})["step_us"] = step_us
    if action:
        data["task"].setdefault("action", {}).update(action)
    path = tmp_path / f"{Path(source).stem}_{step_us}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_whole_steps_is_exact_for_spans_and_rounds_for_polls() -> None:
    assert whole_steps(1.0, 4000) == 250 and whole_steps(1.0, 2000) == 500
    assert whole_steps(0.004, 4000) == 1 and whole_steps(0.0, 4000) == 0
    with pytest.raises(ValueError, match="not a whole number of 3000 us steps"):
        whole_steps(1.0, 3000)
    assert whole_steps(1.0, 3000, exact=False) == 333
    assert whole_steps(0.1, 3000, exact=False) == 33  # 99 ms, the nearest
    assert nearest_whole_steps_s(0.1, 3000) == pytest.approx(0.099)
    assert DEFAULT_STEP_US == load_world(WORLDS / "empty.yaml").physics.step_us == 4000


def test_loader_rejects_a_step_that_does_not_divide_the_actions(tmp_path: Path) -> None:
    path = with_step(tmp_path, "empty.yaml", 3000)  # 1 s actions: 333.3 steps
    with pytest.raises(ConfigError) as info:
        load_world(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: world.physics.step_us: expected ")
    assert "task.action.duration_s (1 s)" in message and message.endswith("got 3000")
    # the hold span counts too; spans it divides are fine
    with pytest.raises(ConfigError, match="zero_velocity_s"):
        load_world(with_step(tmp_path, "obstacle.yaml", 4000, zero_velocity_s=0.25, duration_s=0.6))
    assert load_world(with_step(tmp_path, "window.yaml", 3000, duration_s=0.6)).physics.step_us == 3000


def _fly(env, actions: list[int], seed: int) -> list[np.ndarray]:
    _, info = env.reset(seed=seed)
    positions = [info["position_enu_m"]]
    for action in actions:
        _, _, terminated, truncated, info = env.step(action)
        positions.append(info["position_enu_m"])
        assert info["sim_time_s"] > 0
        if terminated or truncated:
            break
    return positions


def test_direct_and_stub_fly_the_same_episode_at_any_step(tmp_path: Path, free_instances) -> None:
    """A scripted O episode at 500 Hz and 250 Hz physics: `direct` and `stub` agree as closely
    as in test_envs_stub, and the physics rate changes the flight by centimetres only."""
    actions = [3, 5, 5, 3]
    first = free_instances(2)
    flights = {}
    for k, step_us in enumerate((2000, 4000)):
        scenario = with_step(tmp_path, "obstacle.yaml", step_us)
        direct = make_env(scenario, autopilot="direct")
        try:
            assert direct.backend.sim.step_us == step_us
            expected = _fly(direct, actions, seed=2)
        finally:
            direct.close()
        stub = make_env(scenario, autopilot="stub", speed_factor=0.0, instance_base=first + k)
        try:
            got = _fly(stub, actions, seed=2)
            assert stub.backend.session.step_us == step_us
        finally:
            stub.close()
        assert len(got) == len(expected) == len(actions) + 1
        for step, (a, b) in enumerate(zip(expected, got, strict=True)):
            assert np.linalg.norm(a - b) < 0.1, (step_us, step, a, b)
        flights[step_us] = expected
    for a, b in zip(flights[2000], flights[4000], strict=True):
        assert np.linalg.norm(a - b) < 0.1
    start, end = flights[4000][0], flights[4000][-1]
    assert end[1] - start[1] > 1.0 and end[2] - start[2] > 1.5  # it flew north and up
