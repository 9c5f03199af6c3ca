"""Encounter families (`world.encounter`): geometry drawn per episode inside the declared ranges,
reproducible from the seed, checked by the loader, and flown by the envs (late entries held)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from sitl_bridge.errors import ConfigError
from sitl_bridge.world import load_world, realize
from sitl_bridge.world.encounter import SPAWN_SEPARATION_M, SPAWN_Z_M, WALL_NAME, EncounterType
from sitl_bridge.world.sense import SPAWN_CLEARANCE_M, overlaps

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
FAMILIES = ("encounters", "encounters_converging", "encounters_heldout", "encounters_heldout_converging")
SEEDS = range(300)
TOL = 1e-9


def _course(spawn, goal) -> np.ndarray:
    d = np.subtract(goal[:2], spawn[:2])
    return d / np.linalg.norm(d)


def _within(value: float, bounds: tuple[float, float]) -> bool:
    return bounds[0] - TOL <= value <= bounds[1] + TOL


def _type_of(world, layout) -> list[EncounterType]:
    """The declared types the drawn one can be (a mix may list one type twice, other ranges)."""
    return [t for t in world.encounter.types if t.kind == layout.encounter]


def _heading_ok(kind: EncounterType, heading_rad: float) -> bool:
    low, high = kind.heading_deg
    if high - low >= 360.0 - TOL:
        return True
    degrees = math.degrees(heading_rad)
    return any(_within(degrees + turn, kind.heading_deg) for turn in (-720, -360, 0, 360, 720))


def _matches(kind: EncounterType, world, layout) -> bool:
    """Whether `layout` is a draw of `kind`: every measured quantity inside its ranges."""
    s, g = layout.spawn_positions_m, [goal.center_m for goal in layout.goals]
    c = np.array(world.encounter.center_m)
    delays = layout.start_delays_s
    if kind.kind == "overtaking":
        delays_ok = delays[0] == 0.0 and _within(delays[1], kind.start_delay_s)
    else:
        delays_ok = delays.count(0.0) >= 1 and all(d == 0.0 or _within(d, kind.start_delay_s) for d in delays)
    if not delays_ok:
        return False
    u0 = _course(s[0], g[0])
    if not _heading_ok(kind, math.atan2(u0[1], u0[0])) and kind.kind != "converging" and kind.kind != "bottleneck":
        return False
    if kind.kind == "head_on":
        u1 = _course(s[1], g[1])
        left = np.array([-u0[1], u0[0]])
        offset = float(np.dot(np.subtract(s[1][:2], s[0][:2]), left))
        return (np.dot(u0, u1) < -1 + 1e-9 and _within(offset, kind.lateral_offset_m)
                and all(_within(math.dist(a[:2], b[:2]), kind.length_m) for a, b in zip(s, g, strict=True)))
    if kind.kind == "crossing":
        angle = math.degrees(math.acos(float(np.clip(np.dot(u0, _course(s[1], g[1])), -1, 1))))
        # both courses cross at their midpoints, at the centre
        mids = [np.add(a[:2], b[:2]) / 2 for a, b in zip(s, g, strict=True)]
        return (_within(angle, kind.angle_deg) and all(np.allclose(m, c) for m in mids)
                and all(_within(math.dist(a[:2], b[:2]), kind.length_m) for a, b in zip(s, g, strict=True)))
    if kind.kind == "converging":
        ok = True
        for a, b in zip(s, g, strict=True):
            r = math.dist(a[:2], c)
            ok &= _within(r, kind.radius_m) and np.allclose(np.add(a[:2], b[:2]) / 2, c)  # through the centre
        bearings = sorted(math.degrees(math.atan2(a[1] - c[1], a[0] - c[0])) % 360 for a in s)
        n = len(s)
        gaps = [(bearings[(k + 1) % n] - bearings[k]) % 360 for k in range(n)]
        return ok and all(_within(gap, (360 / n - 2 * kind.angle_jitter_deg, 360 / n + 2 * kind.angle_jitter_deg))
                          for gap in gaps)
    if kind.kind == "overtaking":
        u1 = _course(s[1], g[1])
        gap = math.dist(s[0][:2], s[1][:2])
        ahead = float(np.dot(np.subtract(s[1][:2], s[0][:2]), u0))
        return (np.dot(u0, u1) > 1 - 1e-9 and abs(ahead - gap) < 1e-6 and _within(gap, kind.gap_m)
                and _within(math.dist(s[0][:2], g[0][:2]), kind.length_m))
    # bottleneck: the wall through the centre; starts on one side, goals exit_m beyond it
    wall = next(o for o in layout.obstacles if o.name == WALL_NAME)
    normal = np.array([-math.sin(wall.yaw_rad), math.cos(wall.yaw_rad)])  # the heading
    along = np.array([math.cos(wall.yaw_rad), math.sin(wall.yaw_rad)])
    starts = [float(np.dot(np.subtract(a[:2], c), normal)) for a in s]
    ends = [float(np.dot(np.subtract(b[:2], c), normal)) for b in g]
    side = math.copysign(1.0, starts[0])
    return (all(math.copysign(1.0, x) == side and _within(abs(x), kind.distance_m) for x in starts)
            and all(abs(x + side * kind.exit_m) < 1e-6 for x in ends)
            and all(_within(float(np.dot(np.subtract(p[:2], c), along)), kind.lateral_offset_m) for p in (*s, *g))
            and _within(wall.shape.opening.width_m, kind.gap_width_m)
            and _heading_ok(kind, wall.yaw_rad - math.pi / 2))


@pytest.mark.parametrize("family", FAMILIES)
def test_drawn_geometry_respects_the_declared_ranges_over_many_seeds(family: str) -> None:
    world = load_world(WORLDS / f"{family}.yaml")
    counts: dict[str, int] = {}
    for seed in SEEDS:
        layout = realize(world, np.random.default_rng(seed))
        counts[layout.encounter] = counts.get(layout.encounter, 0) + 1
        assert any(_matches(kind, world, layout) for kind in _type_of(world, layout)), (family, seed, layout)
        assert len(layout.spawn_positions_m) == world.encounter.drones == len(layout.start_delays_s)
        for p in (*layout.spawn_positions_m, *(goal.center_m for goal in layout.goals)):
            assert world.workspace.contains(p), (family, seed, p)
            for o in layout.obstacles:  # the bottleneck's wall included
                assert not overlaps(o.spec, p, SPAWN_CLEARANCE_M), (family, seed, o.name, p)
        for goal in layout.goals:  # the whole goal box inside the workspace
            assert all(lo <= c - size / 2 and c + size / 2 <= hi for c, size, lo, hi in
                       zip(goal.center_m, goal.size_m, world.workspace.min_m, world.workspace.max_m, strict=True))
            assert goal.center_m[2] == world.encounter.altitude_m
        spawns = layout.spawn_positions_m
        assert all(p[2] == SPAWN_Z_M for p in spawns)
        assert all(math.dist(a[:2], b[:2]) >= SPAWN_SEPARATION_M - TOL
                   for i, a in enumerate(spawns) for b in spawns[i + 1:])
        for p, yaw, goal in zip(spawns, layout.spawn_yaws_rad, layout.goals, strict=True):  # facing the goal
            assert np.allclose([math.cos(yaw), math.sin(yaw)], _course(p, goal.center_m))
    assert set(counts) == {t.kind for t in world.encounter.types}, counts  # every type drawn


def test_mix_weights_set_how_often_each_type_is_drawn() -> None:
    world = load_world(WORLDS / "encounters_converging.yaml")  # converging 2+1, bottleneck 2
    kinds = [realize(world, np.random.default_rng(seed)).encounter for seed in range(1000)]
    assert abs(kinds.count("converging") / 1000 - 0.6) < 0.05


@pytest.mark.parametrize("family", FAMILIES)
def test_same_seed_same_geometry_other_seeds_differ(family: str) -> None:
    world = load_world(WORLDS / f"{family}.yaml")
    a, b = (realize(world, np.random.default_rng(7)) for _ in range(2))
    assert a == b
    draws = {realize(world, np.random.default_rng(seed)).spawn_positions_m for seed in range(20)}
    assert len(draws) == 20


def test_late_entries_draw_a_delay_for_all_but_one_drone() -> None:
    world = load_world(WORLDS / "encounters_heldout_converging.yaml")
    delayed = [layout for layout in (realize(world, np.random.default_rng(s)) for s in SEEDS)
               if any(layout.start_delays_s)]
    assert delayed
    for layout in delayed:
        assert layout.start_delays_s.count(0.0) == 1
        assert all(1.0 <= d <= 4.0 for d in layout.start_delays_s if d)
    assert {layout.start_delays_s.index(0.0) for layout in delayed} == {0, 1, 2, 3}  # who enters first varies


BASE = {"name": "e", "workspace": {"min": [-8, -8, 0], "max": [8, 8, 6]}}


def _load(tmp_path: Path, encounter: dict, **world: object) -> None:
    path = tmp_path / "e.yaml"
    path.write_text(yaml.safe_dump({"world": {**BASE, **world, "encounter": encounter}}))
    load_world(path)


@pytest.mark.parametrize(("encounter", "extra", "key", "says"), [
    ({"type": "crossing", "angle_deg": [150, 30]}, {}, "world.encounter.angle_deg", "low <= high"),
    ({"type": "crossing", "angle_deg": [0, 90]}, {}, "world.encounter.angle_deg", "5 <= low"),
    ({"type": "crossing", "angle_deg": [30, 190]}, {}, "world.encounter.angle_deg", "high <= 175"),
    ({"mix": [{"type": "head_on", "lateral_offset_m": [1, -1]}]}, {}, "world.encounter.mix[0].lateral_offset_m",
     "low <= high"),
    ({"drones": 1, "type": "converging"}, {}, "world.encounter.drones", ">= 2"),
    ({"drones": 3, "type": "head_on"}, {}, "world.encounter.type", "exactly 2"),
    ({"mix": [{"type": "converging", "radius_m": [4, 9]}]}, {}, "world.encounter.mix[0].type", "fits the workspace"),
    ({"type": "crossing", "length_m": [8, 20]}, {}, "world.encounter.type", "fits the workspace"),
    ({"type": "crossing", "lateral_offset_m": 1}, {}, "world.encounter.lateral_offset_m", "crossing encounter has no"),
    ({"mix": [{"type": "bottleneck", "angle_deg": 30}]}, {}, "world.encounter.mix[0]", "angle_deg"),
    ({"type": "orbit"}, {}, "world.encounter.type", "head_on"),
    ({"type": "head_on", "mix": [{"type": "head_on"}]}, {}, "world.encounter.type", "not both"),
    ({"drones": 2}, {}, "world.encounter", "type:"),
    ({"mix": [{"type": "head_on", "weight": 0}]}, {}, "world.encounter.mix[0].weight", "positive"),
    ({"type": "head_on"}, {"vehicles": []}, "world.vehicles", "beside encounter"),
    ({"type": "head_on", "altitude_m": 7}, {}, "world.encounter.altitude_m", "<= 6"),
    ({"type": "converging", "drones": 3, "radius_m": 5},
     {"obstacles": [{"name": "tower", "shape": "cylinder", "radius": 7, "height": 6, "position": [0, 0, 3]}]},
     "world.encounter", "clear of the obstacles"),
])
def test_bad_encounters_are_one_line_errors_naming_the_key(tmp_path: Path, encounter, extra, key, says) -> None:
    with pytest.raises(ConfigError) as error:
        _load(tmp_path, encounter, **extra)
    message = str(error.value)
    assert "\n" not in message and f"{key}" in message and says in message, message


def test_an_encounter_above_the_ground_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"world.encounter: the encounter's spawns rest on the ground"):
        _load(tmp_path, {"type": "head_on"}, workspace={"min": [-8, -8, 1], "max": [8, 8, 6]})


def test_a_bottleneck_gap_narrower_than_a_drone_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"gap_width_m: expected \[low, high\] with 0.6 <= low"):
        _load(tmp_path, {"type": "bottleneck", "gap_width_m": [0.3, 1]})


def test_worlds_check_passes_on_the_shipped_families(capsys) -> None:
    from tests.test_world import run_check

    assert run_check(*(str(WORLDS / f"{f}.yaml") for f in FAMILIES)) == 0
    out = capsys.readouterr().out
    assert out.count(": ok: ") == len(FAMILIES) and "randomised: encounter (" in out


# -- flown by the envs (direct backend: real pybullet, stub autopilot) ---------------------------
def _single_type_file(tmp_path: Path, family: str, index: int) -> Path:
    """`family`'s scenario with only its `index`-th encounter type (task and all else unchanged)."""
    root = yaml.safe_load((WORLDS / f"{family}.yaml").read_text())
    encounter = root["world"]["encounter"]
    encounter["mix"] = [encounter["mix"][index]]
    path = tmp_path / f"{family}_{index}.yaml"
    path.write_text(yaml.safe_dump(root))
    return path


@pytest.mark.parametrize("family", ["encounters", "encounters_heldout_converging"])
def test_pettingzoo_parallel_api_test_passes(family: str) -> None:
    from pettingzoo.test import parallel_api_test

    from sitl_bridge.envs import make_parallel_env

    env = make_parallel_env(WORLDS / f"{family}.yaml", seed=0)
    try:
        parallel_api_test(env, num_cycles=8)
        assert env.possible_agents == [f"drone{i}" for i in range(env.scenario.world.encounter.drones)]
    finally:
        env.close()


@pytest.mark.parametrize(("family", "index"), [("encounters", i) for i in range(5)]
                         + [("encounters_converging", 0)])
def test_random_action_episodes_of_each_type_fly_on_the_direct_backend(tmp_path: Path, family: str,
                                                                       index: int) -> None:
    from sitl_bridge.envs import make_parallel_env

    env = make_parallel_env(_single_type_file(tmp_path, family, index), seed=index)
    kind = env.scenario.world.encounter.types[0]
    rng = np.random.default_rng(index)
    try:
        for episode in range(2):
            observations, infos = env.reset(seed=100 + episode)
            layout = env.backend.sim.layout
            assert layout.encounter == kind.kind
            starts = {a: infos[a]["position_enu_m"].copy() for a in env.agents}
            for a, spawn in zip(env.possible_agents, layout.spawn_positions_m, strict=True):
                # every drone starts hovering above its drawn spawn, its goal the drawn one
                assert np.allclose(starts[a][:2], spawn[:2], atol=0.1)
                assert np.allclose(infos[a]["goal_enu_m"], layout.goal_of(env.possible_agents.index(a)).center_m)
            walls = [o for o in layout.obstacles if o.name == WALL_NAME]
            assert len(walls) == (kind.kind == "bottleneck")
            steps, outcomes = 0, {}
            while env.agents:
                # random moves, never a hover (code 7): a held drone that stays put was held
                actions = {a: int(rng.integers(7)) for a in env.agents}
                held = {a for a in env.agents if not infos[a]["entered"]}
                before = {a: infos[a]["position_enu_m"].copy() for a in held}
                observations, rewards, terminations, truncations, infos = env.step(actions)
                steps += 1
                for a in held:
                    assert np.linalg.norm(infos[a]["position_enu_m"] - before[a]) < 0.15, (a, steps)
                    assert infos[a]["action"] is None
                for a in infos:
                    if terminations[a] or truncations[a]:
                        outcomes[a] = infos[a]["outcome"]
            assert set(outcomes) == set(env.possible_agents)
            assert set(outcomes.values()) <= {"goal", "crash", "out", "timeout"}
            assert steps <= env.scenario.task.max_steps
    finally:
        env.close()


def test_a_late_entry_is_held_for_its_delay_then_flies(tmp_path: Path) -> None:
    from sitl_bridge.envs import make_parallel_env

    env = make_parallel_env(_single_type_file(tmp_path, "encounters", 2), seed=0)  # overtaking: leader waits
    try:
        for seed in range(3):
            _, infos = env.reset(seed=seed)
            delay = env.backend.sim.layout.start_delays_s[1]
            assert 3.0 <= delay <= 5.0 and infos["drone1"]["entered"] is False and infos["drone0"]["entered"]
            held_steps = math.ceil(delay / env.scenario.task.action.duration_s - 1e-9)
            start = infos["drone1"]["position_enu_m"].copy()
            for step in range(held_steps + 1):
                assert infos["drone1"]["entered"] is (step >= held_steps)
                # the follower hovers (flying on, it would hit the waiting leader); the leader is told to go
                _, _, _, _, infos = env.step({"drone0": 7, "drone1": 6})
                moved = float(np.linalg.norm(infos["drone1"]["position_enu_m"] - start))
                assert (moved < 0.15) is (step < held_steps), (seed, step, moved)
    finally:
        env.close()


def test_an_encounter_world_keeps_its_drone_count() -> None:
    from sitl_bridge.world import with_vehicle_count

    world = load_world(WORLDS / "encounters_converging.yaml")
    assert with_vehicle_count(world, 3) == world
    with pytest.raises(ConfigError, match=r"world.encounter.drones: the encounter places 3 drones every episode, not 4"):
        with_vehicle_count(world, 4)
