"""Goal-seeking exploration (`train: guided_explore_episodes`, envs/path_guide.py): the guide
reaches the goal round obstacles in the real simulator, the option fills the first episodes with
goals, and it is off by default and checked."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_rl_helpers import tiny_config

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory
from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.training.run_dir import RunSpec
from sitl_bridge.rl.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]
PILLARS = ROOT / "experiments" / "generalization" / "pillars.yaml"
OBSTACLE = ROOT / "worlds" / "obstacle.yaml"


@pytest.mark.parametrize("world", [PILLARS, OBSTACLE])
def test_the_guide_flies_round_the_obstacles_to_the_goal(world: Path) -> None:
    """Held from the start, the straight line ("toward goal") crashes into the obstacle; the
    guide gets round it (pillars: a gap, then over the beam; O: over the block)."""
    env = DronesEnv(scenario_env_factory(world)(0))
    try:
        for seed in (1, 2):
            env.reset(seed)
            actions, result = [], None
            while env.live:
                actions.append(env.guided_action(0))
                result = env.step({0: actions[-1]})
            assert result is not None and result.infos[0]["outcome"] == "goal", (seed, actions)
            assert len(actions) <= 20
        env.reset(1)
        while env.live:
            result = env.step({0: 6})  # toward goal
        assert result.infos[0]["outcome"] == "crash"
    finally:
        env.close()


def test_guided_episodes_reach_the_goal_and_later_ones_are_plain(tmp_path: Path) -> None:
    config = tiny_config(episodes=3, epsilon_max=1.0, epsilon_min=1.0, guided_explore_episodes=2,
                         guided_explore_share=1.0, batch_size=8, replay_capacity=200)
    with Trainer.start(tmp_path, RunSpec(world=str(OBSTACLE)), config, scenario_env_factory(OBSTACLE),
                       progress=False) as trainer:
        trainer.train()
        run_dir = trainer.run_dir
    outcomes = [r["outcome"] for r in read_records(run_dir / "episodes.jsonl")]
    assert outcomes[:2] == ["goal", "goal"]  # every step guided: straight over the block
    assert len(outcomes) == 3


def test_the_option_is_off_by_default_and_checked() -> None:
    assert tiny_config().guided_explore_episodes == 0
    with pytest.raises(ConfigError, match="guided_explore_episodes"):
        tiny_config(guided_explore_episodes=5, num_envs=2)
    with pytest.raises(ConfigError, match="guided_explore_share"):
        tiny_config(guided_explore_share=1.5)
