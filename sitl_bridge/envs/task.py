"""The `task:` section of a scenario file, parsed into typed, validated objects.

A scenario is one YAML file under `worlds/`: the `world:` section (geometry, vehicles, goals,
workspace; read by `sitl_bridge.world`) and the `task:` section read here (what the learner sees,
how it is rewarded, when an episode ends, what an action means). Example::

    task:
      max_steps: 35                 # step limit -> truncated (or max_time_s: simulated seconds)
      start_altitude_m: 2.5         # each episode starts hovering this high above the spawn
      start: {takeoff: false}       # true: take off to it every episode (default: placed there)
      action:                       # type: discrete (default, the thesis's eight codes)
        speed_m_s: 1.0              # every moving action flies this speed ...
        duration_s: 1.0             # ... for this many simulated seconds
        zero_velocity_s: 0.0        # optional hover phase after each action
        frame: world                # world (thesis) | goal (relative to the start-goal line)
        swap_drones: []             # drones whose 0/1 and 2/3 are swapped (the thesis's hack)
      # action: {type: velocity, max_speed_m_s: 2.0, duration_s: 0.1, frame: world, yaw: hold}
      #   continuous: a Box(-1, 1) vector (x, y, z[, yaw rate]) scaled to a velocity setpoint
      #   (envs/actions.py); frame world | goal | body; yaw hold | rate (max_yaw_rate_deg_s)
      observation:                  # concatenated in this order
        - position: {decimals: 0}
        - orientation: {decimals: 0}
        - lidar: [horizontal]
      reward:                       # name: scale, or name: {scale: .., other options}
        closer_to_goal: 10
        goal_reached: 500
        per_step: -5
        crash: -100
      priority: lower_coordinate_yields  # who has right of way (envs/priority.py), the
                                    # `own_priority` / `other_priority` inputs
      end:
        goal_margin_m: 0.0          # reached inside the world's goal box grown by this
        crash_on_lidar: true        # the lidar's crash flag ends the episode as a crash
        crash_on_ground: true       # touching the ground while flying is a crash (not at the goal)
        ground_contact_m: 0.2       # ... when the body centre is this low above the ground
        after_goal: hover           # a drone at its goal: hover there (thesis) | land (leave the airspace)
        conflict_blame: both        # two drones crash into each other: both charged (thesis) | give_way
        conflict_m: 1.0             # ... a crash with another drone's centre this close is a conflict
        min_separation_m: 0.0       # a flying drone this close to another in the air loses separation: a conflict crash (0: off)
      render:                       # camera of render_mode="rgb_array" and videos (all optional)
        width: 512
        height: 384
        camera: follow              # follow (behind and above the drone, along its heading) | scene (the workspace)
        distance_m: null            # default: 4 m (follow), fits the workspace (scene)
        yaw_deg: 30                 # scene camera's yaw (the follow camera takes the drone's heading)
        pitch_deg: -35
        target_m: null              # scene camera's target (default: the workspace centre)
        fov_deg: 60
        lidar_rays: false           # draw the lidar rays
        fps: 10                     # of recorded videos (frames every 0.1 s of simulated time: its own pace)

Unknown keys are errors (typos never pass silently); every error is one line naming the file and
the key path (`sitl_bridge.errors.ConfigError`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl_bridge.envs.features import Feature, parse_observation
from sitl_bridge.envs.priority import PRIORITY_RULES
from sitl_bridge.envs.rewards import RewardTerm, parse_rewards
from sitl_bridge.envs.view import ScenarioLimits
from sitl_bridge.errors import ConfigError, Node
from sitl_bridge.physics.render import CAMERA_MODES, RenderConfig

ACTION_TYPES = ("discrete", "velocity")
"""`task.action.type`: the thesis's eight codes, or a continuous velocity vector."""
ACTION_FRAMES = ("world", "goal")
"""Frames of discrete actions."""
VELOCITY_FRAMES = ("world", "goal", "body")
"""Frames of continuous velocity actions (envs/actions.py says what each axis means)."""
YAW_MODES = ("hold", "rate")
"""`task.action.yaw` of velocity actions: keep the heading, or a 4th component commands a yaw rate."""

_DISCRETE_KEYS = frozenset({"speed_m_s", "zero_velocity_s", "swap_drones"})
_VELOCITY_KEYS = frozenset({"max_speed_m_s", "yaw", "max_yaw_rate_deg_s"})


@dataclass(frozen=True)
class ActionConfig:
    """What one action means in the simulator: a discrete code (default) or a continuous
    velocity vector (`type: velocity`)."""

    type: str = "discrete"
    """`discrete` (the thesis's `Discrete(8)` table) or `velocity` (a `Box(-1, 1)` vector)."""
    speed_m_s: float = 1.0
    """Speed of every moving action (thesis: 1 m/s)."""
    duration_s: float = 1.0
    """Simulated seconds each action's velocity is held (thesis: 1 s)."""
    zero_velocity_s: float = 0.0
    """Simulated seconds of zero velocity after each action (the thesis's smoother variant)."""
    frame: str = "world"
    """`world`: 0 east, 1 west, 2 south, 3 north. `goal`: 0 right, 1 left, 2 back, 3 forward of
    the horizontal start-goal direction (symmetric head-on scenarios without the swap)."""
    swap_drones: tuple[int, ...] = ()
    """Drone indices whose actions 0/1 and 2/3 are swapped (the thesis's fix for a drone
    facing the other way in a world-frame head-on scenario)."""
    max_speed_m_s: float = 2.0
    """`velocity`: the speed of a unit-norm action (the speed is capped at this)."""
    yaw: str = "hold"
    """`velocity`: `hold` the heading, or `rate`: a 4th component commands a yaw rate."""
    max_yaw_rate_deg_s: float = 45.0
    """`velocity`, `yaw: rate`: the yaw rate of a component of 1 (counter-clockwise from above)."""

    @property
    def continuous(self) -> bool:
        """Whether actions are continuous velocity vectors (`type: velocity`)."""
        return self.type == "velocity"

    @property
    def size(self) -> int:
        """Components of a continuous action: 3 (velocity), 4 with `yaw: rate`; 1 for a code."""
        if not self.continuous:
            return 1
        return 4 if self.yaw == "rate" else 3

    @property
    def step_s(self) -> float:
        """Simulated seconds one env step takes (the decision period)."""
        return self.duration_s + self.zero_velocity_s


AFTER_GOAL = ("hover", "land")
"""What a drone does once at its goal (`end.after_goal`)."""
CONFLICT_BLAME = ("both", "give_way")
"""Who is charged for a crash between drones (`end.conflict_blame`)."""


@dataclass(frozen=True)
class EndConfig:
    """When an episode ends (besides the step limit)."""

    goal_margin_m: float = 0.0
    """The goal is reached inside the world's goal region (a box) grown by this margin."""
    crash_on_lidar: bool = True
    """The lidar's crash flag (something closer than its crash distance) counts as a crash."""
    out_of_workspace: bool = True
    """Leaving the world's workspace bounds ends the episode."""
    crash_on_ground: bool = True
    """Ground contact while flying (body centre below `ground_contact_m`) is a crash, unless the
    drone is inside its goal region (a landing there is not a crash). A drone sliding along the
    ground would otherwise score as flying."""
    ground_contact_m: float = 0.2
    """Height of the body centre above the ground (z = 0) that counts as ground contact (an
    iris resting on the ground has its centre at 0.06 m)."""
    after_goal: str = "hover"
    """What a drone does once it reached its goal, while the others fly on: `hover` there (the
    thesis), or `land` (descend at the action speed), so it leaves the airspace it arrived in; in
    TW a drone hovering at its goal sits in the path of the other drone's climb to the window."""
    conflict_blame: str = "both"
    """Who is charged when drones crash into each other (a crash with another drone's centre
    within `conflict_m`): `both` (the thesis), or `give_way`: only the drones without right of
    way (`task.priority`). Every drone in the conflict stops (outcome `crash`), but one with right
    of way over all drones in it is not charged: its last step is scored as if it had not crashed
    and ends truncated rather than terminated, so its learned values never price in another
    drone's failure to keep clear (the give-way aircraft's duty in the rules of the air)."""
    conflict_m: float = 1.0
    """Distance between drone centres (m) within which a crash counts as a conflict."""
    min_separation_m: float = 0.0
    """Loss of separation: a flying drone whose centre comes closer than this (m) to another drone
    in the airspace (any but one landing at its goal under `after_goal: land`) crashes, a
    conflict charged as `conflict_blame` says, even when they do not touch (0: off, only
    touching counts). Without it two drones can squeeze past each other through a window 0.9 m
    apart, which no traffic rule would accept."""


@dataclass(frozen=True)
class TaskConfig:
    """The parsed `task:` section of one scenario file."""

    max_steps: int
    """Steps after which an episode is truncated (from `max_time_s` when the file gives that)."""
    start_altitude_m: float
    """Each episode starts with the drone hovering this high above its spawn point (the thesis
    took off before every episode)."""
    action: ActionConfig
    observation: tuple[Feature, ...]
    rewards: tuple[RewardTerm, ...]
    end: EndConfig
    source: str = ""
    render: RenderConfig = RenderConfig()
    """Camera of `render_mode="rgb_array"` (and recorded videos)."""
    priority: str = "lower_coordinate_yields"
    """Right-of-way rule behind the `own_priority`/`other_priority` inputs (`envs/priority.py`)."""
    start_with_takeoff: bool = False
    """`start: {takeoff: true}`: every episode flies its take-off to the start altitude (the
    thesis's start); default: placed hovering there with no take-off flown (`direct`, `stub`;
    `px4` after its first episode, see `envs.backends.base`)."""
    max_time_s: float | None = None
    """The file's `max_time_s` (simulated seconds per episode), None when it gave `max_steps`."""

    @property
    def observation_size(self) -> int:
        """Length of one drone's observation vector."""
        return sum(f.size for f in self.observation)


def _parse_action(node: Node, num_drones: int) -> ActionConfig:
    node.reject_unknown({"type", "duration_s", "frame", *_DISCRETE_KEYS, *_VELOCITY_KEYS})
    kind = node.get("type", "discrete").string(ACTION_TYPES)
    if kind == "velocity":
        return _parse_velocity_action(node)
    for key in sorted(_VELOCITY_KEYS):
        if node.has(key):
            raise ConfigError(f"{node.source}: {node.get(key).path}: only with `type: velocity` "
                              "(discrete actions fly speed_m_s)")
    swap: list[int] = []
    for item in node.get("swap_drones", []).list():
        swap.append(item.integer(minimum=0, maximum=num_drones - 1))
    if swap and node.get("frame", "world").value == "goal":
        # The goal frame already turns each drone's actions with its own travel direction;
        # swapping on top would mirror them again.
        raise node.get("swap_drones").error("[] with `frame: goal` (swap_drones is for the world frame)")
    return ActionConfig(
        speed_m_s=node.get("speed_m_s", 1.0).number(positive=True, maximum=20.0),
        duration_s=node.get("duration_s", 1.0).number(positive=True, maximum=60.0),
        zero_velocity_s=node.get("zero_velocity_s", 0.0).number(non_negative=True, maximum=60.0),
        frame=node.get("frame", "world").string(ACTION_FRAMES),
        swap_drones=tuple(swap),
    )


def _parse_velocity_action(node: Node) -> ActionConfig:
    for key in sorted(_DISCRETE_KEYS):
        if node.has(key):
            raise ConfigError(f"{node.source}: {node.get(key).path}: only with `type: discrete` "
                              "(velocity actions use max_speed_m_s; each decision is held duration_s)")
    return ActionConfig(
        type="velocity",
        max_speed_m_s=node.get("max_speed_m_s", ActionConfig.max_speed_m_s).number(positive=True, maximum=20.0),
        duration_s=node.get("duration_s", 1.0).number(positive=True, maximum=60.0),
        frame=node.get("frame", "world").string(VELOCITY_FRAMES),
        yaw=node.get("yaw", "hold").string(YAW_MODES),
        max_yaw_rate_deg_s=node.get("max_yaw_rate_deg_s", ActionConfig.max_yaw_rate_deg_s).number(
            positive=True, maximum=360.0),
    )


def _parse_end(node: Node) -> EndConfig:
    node.reject_unknown({"goal_margin_m", "crash_on_lidar", "out_of_workspace", "crash_on_ground",
                         "ground_contact_m", "after_goal", "conflict_blame", "conflict_m",
                         "min_separation_m"})
    return EndConfig(
        goal_margin_m=node.get("goal_margin_m", 0.0).number(non_negative=True, maximum=1000.0),
        crash_on_lidar=node.get("crash_on_lidar", True).boolean(),
        out_of_workspace=node.get("out_of_workspace", True).boolean(),
        crash_on_ground=node.get("crash_on_ground", True).boolean(),
        ground_contact_m=node.get("ground_contact_m", 0.2).number(non_negative=True, maximum=5.0),
        after_goal=node.get("after_goal", "hover").string(AFTER_GOAL),
        conflict_blame=node.get("conflict_blame", "both").string(CONFLICT_BLAME),
        conflict_m=node.get("conflict_m", 1.0).number(positive=True, maximum=100.0),
        min_separation_m=node.get("min_separation_m", 0.0).number(non_negative=True, maximum=100.0),
    )


def _parse_render(node: Node) -> RenderConfig:
    node.reject_unknown({"width", "height", "camera", "distance_m", "yaw_deg", "pitch_deg", "target_m",
                         "fov_deg", "lidar_rays", "fps"})
    d = RenderConfig()
    target = node.get("target_m", None)
    return RenderConfig(
        width=node.get("width", d.width).integer(minimum=16, maximum=4096),
        height=node.get("height", d.height).integer(minimum=16, maximum=4096),
        camera=node.get("camera", d.camera).string(CAMERA_MODES),
        distance_m=None if node.get("distance_m", None).value is None else
        node.get("distance_m").number(positive=True, maximum=1000.0),
        yaw_deg=node.get("yaw_deg", d.yaw_deg).number(minimum=-360.0, maximum=360.0),
        pitch_deg=node.get("pitch_deg", d.pitch_deg).number(minimum=-89.0, maximum=89.0),
        target_m=None if target.value is None else tuple(target.vector(3)),  # type: ignore[arg-type]
        fov_deg=node.get("fov_deg", d.fov_deg).number(minimum=5.0, maximum=150.0),
        lidar_rays=node.get("lidar_rays", d.lidar_rays).boolean(),
        fps=node.get("fps", d.fps).integer(minimum=1, maximum=240),
    )


MAX_EPISODE_STEPS = 100_000


def _parse_episode_limit(node: Node, action: ActionConfig) -> tuple[int, float | None]:
    """`max_steps`, or `max_time_s` turned into steps of the decision period (rounded up: the
    episode ends at the first decision that reaches it), so changing the rate needs no re-tune."""
    if node.has("max_steps") and node.has("max_time_s"):
        raise ConfigError(f"{node.source}: task.max_time_s: give max_steps or max_time_s, not both")
    if not node.has("max_time_s"):
        return node.get("max_steps").integer(minimum=1, maximum=MAX_EPISODE_STEPS), None
    limit = node.get("max_time_s")
    seconds = limit.number(positive=True, maximum=1e6)
    steps = math.ceil(seconds / action.step_s - 1e-9)
    if steps > MAX_EPISODE_STEPS:
        raise limit.error(f"at most {MAX_EPISODE_STEPS} decisions of {action.step_s:g} s", seconds)
    return max(1, steps), seconds


def parse_task(node: Node, limits: ScenarioLimits) -> TaskConfig:
    """Parse a `task:` node (its path should be `task`) for a world with the given limits."""
    if node.value is None:
        raise ConfigError(f"{node.source}: task: required section is missing")
    node.reject_unknown({"max_steps", "max_time_s", "start_altitude_m", "start", "action", "observation",
                         "reward", "end", "render", "priority"})
    start = node.get("start", {})
    start.reject_unknown({"takeoff"})
    observation = parse_observation(node.get("observation"), limits)
    action = _parse_action(node.get("action", {}), limits.num_drones)
    max_steps, max_time_s = _parse_episode_limit(node, action)
    rewards = tuple(parse_rewards(node.get("reward"), action.step_s))
    smooth = next((t for t in rewards if t.name == "smoothness"), None)
    if smooth is not None and not action.continuous:
        raise ConfigError(f"{node.source}: task.reward.smoothness: only with `task.action.type: velocity` "
                          "(it reads the change of the continuous action)")
    return TaskConfig(
        max_steps=max_steps,
        max_time_s=max_time_s,
        start_altitude_m=node.get("start_altitude_m", 2.5).number(minimum=0.3, maximum=100.0),
        start_with_takeoff=start.get("takeoff", False).boolean(),
        action=action,
        observation=tuple(observation),
        rewards=rewards,
        end=_parse_end(node.get("end", {})),
        source=node.source,
        render=_parse_render(node.get("render", {})),
        priority=node.get("priority", PRIORITY_RULES[0]).string(PRIORITY_RULES),
    )
