"""Crash semantics: ground contact while flying is a crash, on the real simulator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from sitl_bridge.client.actions import Action
from sitl_bridge.envs import make_env

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


def _descend_and_slide(env) -> tuple[list[float], list[str | None]]:
    """Fly down to the ground, then east along it; heights and outcomes per step."""
    env.reset(seed=0)
    heights, outcomes = [], []
    plan = [Action.DOWN] * 3 + [Action.EAST] * 13
    for action in plan:
        _, _, terminated, truncated, info = env.step(int(action))
        heights.append(float(info["position_enu_m"][2]))
        outcomes.append(info["outcome"])
        if terminated or truncated:
            break
    return heights, outcomes


def _scenario(tmp_path: Path, crash_on_ground: bool | None) -> Path:
    root = yaml.safe_load((WORLDS / "empty.yaml").read_text())
    root["task"]["max_steps"] = 40
    root["world"]["workspace"]["max"][0] = 20  # room to slide 13 m east
    root["task"].setdefault("end", {})
    if crash_on_ground is not None:
        root["task"]["end"]["crash_on_ground"] = crash_on_ground
    path = tmp_path / "ground.yaml"
    path.write_text(yaml.safe_dump(root))
    return path


def test_descending_to_the_ground_and_sliding_is_a_crash(tmp_path: Path) -> None:
    env = make_env(_scenario(tmp_path, None), seed=0)  # default: on
    heights, outcomes = _descend_and_slide(env)
    env.close()
    assert outcomes[-1] == "crash"
    assert heights[-1] < 0.2
    assert len(outcomes) <= 3  # ends when it reaches the ground, not after sliding along it


def test_ground_contact_can_be_turned_off_per_scenario(tmp_path: Path) -> None:
    env = make_env(_scenario(tmp_path, False), seed=0)
    heights, outcomes = _descend_and_slide(env)
    env.close()
    # The thesis's semantics: the drone slides along the ground at ~0.1 m for 13 steps unscored.
    assert len(outcomes) == 16 and all(o is None for o in outcomes)
    assert max(heights[3:]) < 0.3
    assert np.isfinite(heights).all()
