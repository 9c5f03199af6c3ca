"""The `stub` backend (simulator -> HIL link -> stub autopilot -> MAVLink -> real MAVSDK) agrees with
`direct` on the same seed and actions, and resets in place. Real sockets on free instances."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.envs import make_env, make_parallel_env

WORLDS = Path(__file__).resolve().parents[1] / "worlds"

pytest.importorskip("sitl_bridge.session", reason="the stub backend needs sitl_bridge.session")


def fly(env, actions: list[int], seed: int) -> list[np.ndarray]:
    """Positions after reset and after every action (ground truth, world ENU)."""
    _, info = env.reset(seed=seed)
    positions = [info["position_enu_m"]]
    for action in actions:
        _, _, terminated, truncated, info = env.step(action)
        positions.append(info["position_enu_m"])
        if terminated or truncated:
            break
    return positions


def test_direct_and_stub_agree_on_the_same_seed_and_actions(free_instance: int) -> None:
    actions = [3, 5, 5, 3, 3, 3, 3, 4, 4]  # the thesis's O solution
    direct = make_env(WORLDS / "obstacle.yaml", autopilot="direct")
    try:
        expected = fly(direct, actions, seed=2)
    finally:
        direct.close()
    stub = make_env(WORLDS / "obstacle.yaml", autopilot="stub", speed_factor=0.0,
                    instance_base=free_instance)
    try:
        got = fly(stub, actions, seed=2)
        assert len(got) == len(expected)
        for step, (a, b) in enumerate(zip(expected, got, strict=True)):
            assert np.linalg.norm(a - b) < 0.1, (step, a, b)
        # reset in place: a second episode on the same processes and ports
        again = fly(stub, actions[:3], seed=2)
        for a, b in zip(expected, again, strict=False):
            assert np.linalg.norm(a - b) < 0.1
    finally:
        stub.close()


def test_direct_and_stub_agree_with_the_ground_truth_estimator(free_instance: int) -> None:
    """The labelled speed option: both backends fly the stub on ground truth (the `stub` one
    on HIL_STATE_QUATERNION) and still agree."""
    actions = [3, 5, 5, 3, 3, 3, 3, 4, 4]
    direct = make_env(WORLDS / "obstacle.yaml", autopilot="direct", estimator="ground_truth")
    try:
        assert all(ap.ground_truth_estimate for ap in direct.backend.autopilots)
        expected = fly(direct, actions, seed=2)
    finally:
        direct.close()
    stub = make_env(WORLDS / "obstacle.yaml", autopilot="stub", speed_factor=0.0,
                    instance_base=free_instance, estimator="ground_truth")
    try:
        got = fly(stub, actions, seed=2)
        assert all(ap.ground_truth_estimate for ap in stub.backend.session.autopilots.stubs)
        assert len(got) == len(expected)
        for step, (a, b) in enumerate(zip(expected, got, strict=True)):
            assert np.linalg.norm(a - b) < 0.1, (step, a, b)
    finally:
        stub.close()


def test_ground_truth_estimator_is_refused_for_px4() -> None:
    with pytest.raises(ValueError, match="ground_truth"):
        make_env(WORLDS / "obstacle.yaml", autopilot="px4", estimator="ground_truth")
    with pytest.raises(ValueError, match="estimator"):
        make_env(WORLDS / "obstacle.yaml", autopilot="direct", estimator="kalman")


def test_stub_backend_flies_two_drones_head_on(free_instances) -> None:
    first = free_instances(2)
    env = make_parallel_env(WORLDS / "two_drones_empty.yaml", autopilot="stub",
                            instance_base=first, seed=0)
    try:
        env.reset(seed=0)
        outcomes = {}
        for _ in range(12):
            _, _, terminations, _, infos = env.step({a: 3 for a in env.agents})
            outcomes.update({a: infos[a]["outcome"] for a, done in terminations.items() if done})
            if not env.agents:
                break
        assert outcomes == {"drone0": "crash", "drone1": "crash"}
    finally:
        env.close()


@pytest.mark.px4
def test_px4_backend_flies_and_restarts_between_episodes(px4_bin: str) -> None:
    # the env claims a free instance in 0..9 (PX4 gives those above 9 no API port of their own)
    env = make_env(WORLDS / "empty.yaml", autopilot="px4", px4_bin=px4_bin, instance_base=1)
    try:
        for seed in (0, 1):  # the second reset restarts PX4
            _, info = env.reset(seed=seed)
            assert abs(info["position_enu_m"][2] - 2.56) < 0.3
            start = info["position_enu_m"]
            for _ in range(3):
                _, _, terminated, truncated, info = env.step(3)
                assert not (terminated or truncated)
            moved = info["position_enu_m"] - start
            assert 2.0 < moved[1] < 3.5 and abs(moved[0]) < 0.3  # three times 1 m/s north
    finally:
        env.close()
