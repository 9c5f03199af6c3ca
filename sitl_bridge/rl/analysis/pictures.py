"""Pictures of behaviour: one episode drawn as a top view above a side view of its world.

Both views share the horizontal axis, the direction the drones travel (north in every shipped
scenario), so a climb in the side view sits under the obstacle it climbs over in the top view.
Drawn: the workspace box (dashed), the ground footprint and side outline of every obstacle as
placed that episode (wall windows dashed), the goal boxes, moving obstacles' paths and positions,
and each drone's path with its action codes along it (run-length: `3x4` = four steps of action 3)
and its end marked by outcome. The action names under the figure are in the scenario's own
action frame (`rl/common/action_names.py`).

Pure drawing: everything comes in as data (`EpisodePicture`: scenario, layout, traces, movers),
so pictures of logged, greedy or hand-built episodes look the same. `.png` is a still, `.gif`
animates the drones (and movers) step by step.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sitl_bridge.envs.scenario import Scenario
from sitl_bridge.rl.analysis.figure_file import save_figure
from sitl_bridge.rl.common.action_names import ACTION_NAMES_BY_FRAME
from sitl_bridge.rl.evaluation.rollout import Trace
from sitl_bridge.world.layout import Layout, ObstaclePlacement

FORMATS = (".png", ".gif")
OUTCOME_MARKERS = {"goal": "*", "crash": "X", "out": "s", "timeout": "o", "unfinished": "d"}
MARGIN_M = 0.6
"""Space around the workspace (or the farthest point drawn) in both views."""
ALTITUDE_LABEL_M = 0.3
"""The side view labels the runs of actions whose first step changed altitude this much."""
AXIS_LABELS_IN = 0.7
"""Width (inches) the y tick labels and axis name take beside a view (sizes figures to scale)."""
LABEL_CROWD = 0.03
"""Action labels closer than this share of the travel axis' span are stacked, not overlaid."""
MAX_STACKED = 6
"""Labels stacked at one place at most; the next one is drawn as `...`, later ones not at all."""
SIDE_ALPHA = 0.5
"""Obstacles' fill in the side view relative to the top view's."""
_SWAPPED = {0: 1, 1: 0, 2: 3, 3: 2}


@dataclass
class EpisodePicture:
    """What one picture shows: the episode's scenario and drawn layout, every drone's trace."""

    scenario: Scenario
    layout: Layout
    traces: list[Trace]
    movers: dict[str, list[list[float]]] = field(default_factory=dict)
    """Moving obstacle name -> its ENU position after reset and after every step."""
    title: str = ""


def draw_episode(scenario: Scenario, layout: Layout, traces: Sequence[Trace], out: str | Path, *,
                 movers: dict[str, list[list[float]]] | None = None, title: str = "",
                 fps: float = 4.0, dpi: int | None = None) -> Path:
    """Draw one episode to `out`: `.png` (top and side view) or `.gif` (the same, animated one
    frame per action step at `fps`). `dpi` defaults to 110 (PNG) or 80 (GIF). Returns the path."""
    out = Path(out)
    _check_format(out)
    picture = EpisodePicture(scenario, layout, list(traces), dict(movers or {}), title)
    fig, top, side = _episode_figure(picture)
    try:
        if out.suffix.lower() == ".png":
            _draw_views(top, side, picture, upto=None)
            save_figure(fig, out, dpi=dpi or 110)
        else:
            _animate(fig, top, side, picture, out, fps, dpi or 80)
    finally:
        fig.clear()
    return out


def draw_grid(episodes: Sequence[EpisodePicture], out: str | Path, titles: Sequence[str] | None = None, *,
              columns: int = 3, dpi: int = 110) -> Path:
    """A grid of episodes (e.g. typical greedy episodes of a scenario) as one PNG, each cell a
    top view above a side view; `titles` (default: each picture's own) head the cells."""
    from matplotlib.figure import Figure

    out = Path(out)
    if out.suffix.lower() != ".png":
        raise ValueError(f"{out}: a grid is a .png")
    if not episodes:
        raise ValueError("draw_grid: no episodes to draw")
    titles = list(titles) if titles is not None else [e.title for e in episodes]
    if len(titles) != len(episodes):
        raise ValueError(f"draw_grid: {len(episodes)} episodes but {len(titles)} titles")
    columns = max(1, min(columns, len(episodes)))
    rows = math.ceil(len(episodes) / columns)
    views = [_Views.of(e) for e in episodes]
    # one cell's proportions from the largest world, so every cell has room for its own
    along = max(v.span(v.along) for v in views)
    across = max(v.span(v.across) for v in views)
    height = max(v.span(2) for v in views)
    cell_w = 4.2
    cell_h = (cell_w - AXIS_LABELS_IN) * (across + height) / along + 0.9  # + title and tick labels
    fig = Figure(figsize=(cell_w * columns, cell_h * rows + 0.5), layout="constrained")
    _attach_canvas(fig)
    grid = fig.add_gridspec(2 * rows, columns, height_ratios=[across, height] * rows)
    try:
        for k, (picture, title) in enumerate(zip(episodes, titles, strict=True)):
            r, c = divmod(k, columns)
            top = fig.add_subplot(grid[2 * r, c])
            side = fig.add_subplot(grid[2 * r + 1, c], sharex=top)
            _draw_views(top, side, picture, upto=None, compact=True)
            top.set_title(title, fontsize=8)
        # wrapped to the figure's width (one narrow cell would cut it off); ~18 characters per inch at 7 pt
        width = int(18 * cell_w * columns)
        legend = "\n".join(textwrap.fill(line, width) for line in action_legend(episodes[0].scenario).splitlines())
        fig.supxlabel(legend, fontsize=7)
        save_figure(fig, out, dpi=dpi)
    finally:
        fig.clear()
    return out


def _check_format(out: Path) -> None:
    if out.suffix.lower() not in FORMATS:
        raise ValueError(f"{out}: expected a .png or .gif file name, got {out.suffix or 'no suffix'!r}")


def _attach_canvas(fig: Any) -> None:
    """Agg canvas on a bare Figure: no pyplot, no global backend switch."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)


# -- which axes show what ------------------------------------------------------------------


@dataclass(frozen=True)
class _Views:
    """The axis the drones travel along (0 east, 1 north) and the limits of both views."""

    along: int
    low: np.ndarray
    high: np.ndarray

    @property
    def across(self) -> int:
        return 1 - self.along

    def span(self, axis: int) -> float:
        return float(self.high[axis] - self.low[axis])

    @classmethod
    def of(cls, picture: EpisodePicture) -> _Views:
        world, layout = picture.scenario.world, picture.layout
        travel = np.zeros(2)
        for i, spawn in enumerate(layout.spawn_positions_m):
            goal = layout.goal_of(i)
            if goal is not None:
                travel += np.abs(np.asarray(goal.center_m[:2]) - np.asarray(spawn[:2]))
        lo, hi = np.asarray(world.workspace.min_m, float), np.asarray(world.workspace.max_m, float)
        if abs(travel[0] - travel[1]) < 1e-6:  # no travel direction: the workspace's longer side
            along = 0 if hi[0] - lo[0] >= hi[1] - lo[1] else 1
        else:
            along = int(np.argmax(travel))
        points = [np.asarray(p, float) for t in picture.traces for p in t.positions_enu_m]
        points += [np.asarray(p, float) for path in picture.movers.values() for p in path]
        if points:  # a drone that left the workspace stays in the picture
            stack = np.vstack(points)
            lo, hi = np.minimum(lo, stack.min(axis=0)), np.maximum(hi, stack.max(axis=0))
        margin = np.array([MARGIN_M, MARGIN_M, MARGIN_M])
        low = lo - margin
        low[2] = min(lo[2], 0.0) - 0.3  # the ground line shows
        return cls(along, low, hi + margin)

    def top(self, xyz: Any) -> tuple[float, float]:
        return float(xyz[self.along]), float(xyz[self.across])

    def side(self, xyz: Any) -> tuple[float, float]:
        return float(xyz[self.along]), float(xyz[2])


_AXIS_NAMES = ("east x (m)", "north y (m)")


def _episode_figure(picture: EpisodePicture) -> tuple[Any, Any, Any]:
    """A figure with the top view above the side view, both to scale, sharing the travel axis."""
    from matplotlib.figure import Figure

    views = _Views.of(picture)
    along, across, height = views.span(views.along), views.span(views.across), views.span(2)
    width = 8.0
    plot_h = (width - AXIS_LABELS_IN) * (across + height) / along
    if plot_h > 10.0:  # a narrow, deep world: shrink the width instead of growing past a page
        width, plot_h = AXIS_LABELS_IN + (width - AXIS_LABELS_IN) * 10.0 / plot_h, 10.0
    fig = Figure(figsize=(max(width, 6.0), plot_h + 1.6), layout="constrained")
    _attach_canvas(fig)
    grid = fig.add_gridspec(2, 1, height_ratios=[across, height])
    top = fig.add_subplot(grid[0])
    side = fig.add_subplot(grid[1], sharex=top)
    return fig, top, side


# -- drawing -------------------------------------------------------------------------------


def _draw_views(top: Any, side: Any, picture: EpisodePicture, *, upto: int | None,
                compact: bool = False) -> None:
    """Everything of one episode on a top and a side axis; `upto`: only the first `upto` steps
    (animation frames), None: the whole episode."""
    views = _Views.of(picture)
    _draw_static(top, side, picture, views, compact)
    _draw_moving(top, side, picture, views, upto, compact)


def _draw_static(top: Any, side: Any, picture: EpisodePicture, views: _Views, compact: bool) -> None:
    """What stays put during an episode: axes, workspace, static obstacles, goals."""
    world = picture.scenario.world
    for ax in (top, side):
        ax.clear()
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlim(views.low[views.along], views.high[views.along])
        ax.set_axisbelow(True)  # the grid under the workspace's dashed edges
        ax.grid(True, color="0.92", linewidth=0.6)
        ax.tick_params(labelsize=6 if compact else 8)
    top.set_ylim(views.low[views.across], views.high[views.across])
    side.set_ylim(views.low[2], views.high[2])
    if views.along == 1:
        top.invert_yaxis()  # seen from above with north to the right, east is down
    fontsize = 6 if compact else 8
    top.set_ylabel(_AXIS_NAMES[views.across], fontsize=fontsize)
    side.set_ylabel("up z (m)", fontsize=fontsize)
    side.set_xlabel(_AXIS_NAMES[views.along], fontsize=fontsize)
    if not compact:
        top.set_title("top view", fontsize=9, loc="left")
        seen_from = "east" if views.along == 1 else "south"
        side.set_title(f"side view (seen from the {seen_from})", fontsize=9, loc="left")
        top.figure.supxlabel(action_legend(picture.scenario), fontsize=7)
    _draw_workspace(top, side, views, world.workspace.min_m, world.workspace.max_m)
    for placement in picture.layout.obstacles:
        if placement.name not in picture.movers:
            _draw_obstacle(top, side, views, placement, placement.position_m)
    for goal in picture.layout.goals:
        _draw_box(top, side, views, goal.center_m, goal.size_m, face=(0.2, 0.7, 0.3, 0.18),
                  edge=(0.1, 0.5, 0.2, 0.9), zorder=2.8)
        # the name in the box's corner that is up-left on screen (the centre is where drones end)
        a, c = views.along, views.across
        upper = goal.center_m[c] + (-1 if views.along == 1 else 1) * goal.size_m[c] / 2
        top.annotate(goal.name, (goal.center_m[a] - goal.size_m[a] / 2, upper), xytext=(2, -2),
                     textcoords="offset points", fontsize=fontsize - 1, color=(0.1, 0.45, 0.2),
                     ha="left", va="top", zorder=2.9)


def _draw_moving(top: Any, side: Any, picture: EpisodePicture, views: _Views, upto: int | None,
                 compact: bool) -> None:
    """What moves: movers and drones (as far as step `upto`), their legend and the title."""
    if not compact and picture.title:
        top.figure.suptitle(picture.title, fontsize=10)
    for placement in picture.layout.obstacles:
        path = np.asarray(picture.movers.get(placement.name, []), float)
        if len(path):
            now = path[min(len(path) - 1, upto if upto is not None else len(path) - 1)]
            _draw_mover(top, side, views, placement, path, now)
    placed: tuple[list, list] = ([], [])  # action labels so far, top and side view
    handles = [_draw_trace(top, side, views, trace, upto, compact, placed) for trace in picture.traces]
    if not compact and handles:
        top.legend(handles=handles, fontsize=7, loc="upper left", framealpha=0.85)
    elif compact:
        side.annotate(_outcomes(picture.traces), (0.01, 0.97), xycoords="axes fraction", fontsize=6,
                      va="top", color="0.25", zorder=8,
                      bbox={"boxstyle": "round,pad=0.15", "facecolor": "white", "alpha": 0.8, "linewidth": 0})


def _draw_workspace(top: Any, side: Any, views: _Views, low: Sequence[float], high: Sequence[float]) -> None:
    from matplotlib.patches import Rectangle

    a, c = views.along, views.across
    style = {"fill": False, "edgecolor": "0.45", "linestyle": "--", "linewidth": 0.9, "zorder": 1}
    top.add_patch(Rectangle((low[a], low[c]), high[a] - low[a], high[c] - low[c], **style))
    side.add_patch(Rectangle((low[a], low[2]), high[a] - low[a], high[2] - low[2], **style))
    side.axhspan(views.low[2], 0.0, color=(0.55, 0.45, 0.35, 0.35), zorder=0.5, linewidth=0)  # ground


def _footprint(center: Sequence[float], half_x: float, half_y: float, yaw: float,
               offset: Sequence[float] = (0.0, 0.0)) -> np.ndarray:
    """Corners (4 x 2, ENU x/y) of a rectangle of half sizes `half_x`/`half_y` in a body frame
    turned by `yaw` (rad), whose centre sits `offset` (body frame) from `center`."""
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[-half_x, -half_y], [half_x, -half_y], [half_x, half_y], [-half_x, half_y]])
    local = local + np.asarray(offset[:2], float)
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.asarray(center[:2], float)


def _color(placement: ObstaclePlacement, alpha: float) -> tuple[float, float, float, float]:
    r, g, b, _ = placement.spec.color_rgba
    return (r, g, b, alpha)


def _draw_obstacle(top: Any, side: Any, views: _Views, placement: ObstaclePlacement,
                   center: Sequence[float], alpha: float = 0.6, zorder: float = 2.0) -> None:
    """Footprint (top) and outline (side) of a static obstacle as placed this episode."""
    from matplotlib.patches import Circle, Polygon, Rectangle

    shape, yaw = placement.shape, placement.yaw_rad
    edge = tuple(0.6 * v for v in placement.spec.color_rgba[:3])
    style = {"facecolor": _color(placement, alpha), "edgecolor": edge, "linewidth": 0.7, "zorder": zorder}
    # fainter from the side: walls seen face-on there would hide everything behind them
    side_style = {**style, "facecolor": _color(placement, alpha * SIDE_ALPHA)}
    if shape.kind in ("cylinder", "sphere"):
        radius = shape.radius_m or 0.0
        top.add_patch(Circle(views.top(center), radius, **style))
        if shape.kind == "sphere":
            side.add_patch(Circle(views.side(center), radius, **side_style))
        else:
            h = shape.height_m or 0.0
            side.add_patch(Rectangle((center[views.along] - radius, center[2] - h / 2), 2 * radius, h, **side_style))
        return
    if shape.kind == "wall":
        boxes = shape.wall_boxes()
    else:  # box, mesh (its bounding box)
        sx, sy, sz = shape.size_m or (0.0, 0.0, 0.0)
        boxes = [((sx / 2, sy / 2, sz / 2), (0.0, 0.0, 0.0))]
    for (hx, hy, hz), (ox, oy, oz) in boxes:
        corners = _footprint(center, hx, hy, yaw, (ox, oy))
        top.add_patch(Polygon([views.top((x, y, 0.0)) for x, y in corners], closed=True, **style))
        lo, hi = corners[:, views.along].min(), corners[:, views.along].max()
        side.add_patch(Rectangle((lo, center[2] + oz - hz), hi - lo, 2 * hz, **side_style))
    if shape.kind == "wall" and shape.opening is not None:
        _draw_opening(top, side, views, placement, center)


def _draw_opening(top: Any, side: Any, views: _Views, placement: ObstaclePlacement, center: Sequence[float]) -> None:
    """A wall's window: dashed, over the wall, in both views (seen edge-on it would be hidden)."""
    from matplotlib.patches import Polygon, Rectangle

    shape, o = placement.shape, placement.shape.opening
    assert o is not None and shape.size_m is not None
    thickness, height = shape.size_m[1], shape.size_m[2]
    corners = _footprint(center, o.width_m / 2, thickness / 2, placement.yaw_rad, (o.offset_m, 0.0))
    style = {"facecolor": (1, 1, 1, 0.75), "edgecolor": "0.2", "linestyle": "--", "linewidth": 0.8, "zorder": 2.2}
    top.add_patch(Polygon([views.top((x, y, 0.0)) for x, y in corners], closed=True, **style))
    lo, hi = corners[:, views.along].min(), corners[:, views.along].max()
    bottom = center[2] - height / 2 + o.bottom_m
    side.add_patch(Rectangle((lo, bottom), max(hi - lo, 0.15), o.height_m, **style))


def _draw_mover(top: Any, side: Any, views: _Views, placement: ObstaclePlacement, path: np.ndarray,
                now: np.ndarray) -> None:
    """A moving obstacle: its path (dotted) and itself where it is now."""
    color = _color(placement, 0.9)
    for ax, project in ((top, views.top), (side, views.side)):
        xs, ys = zip(*(project(p) for p in path), strict=True)
        ax.plot(xs, ys, linestyle=":", linewidth=0.7, color=color, alpha=0.45, zorder=2.5)
    _draw_obstacle(top, side, views, placement, now, alpha=0.8, zorder=2.6)


def _draw_box(top: Any, side: Any, views: _Views, center: Sequence[float], size: Sequence[float], *,
              face: tuple, edge: tuple, zorder: float) -> None:
    from matplotlib.patches import Rectangle

    a, c = views.along, views.across
    style = {"facecolor": face, "edgecolor": edge, "linewidth": 1.0, "zorder": zorder}
    top.add_patch(Rectangle((center[a] - size[a] / 2, center[c] - size[c] / 2), size[a], size[c], **style))
    side.add_patch(Rectangle((center[a] - size[a] / 2, center[2] - size[2] / 2), size[a], size[2], **style))


def run_lengths(actions: Sequence[int]) -> list[tuple[int, int, int]]:
    """(first step, action, repeats) of every run of equal actions: `6 6 3` -> (0, 6, 2), (2, 3, 1)."""
    runs: list[tuple[int, int, int]] = []
    for step, code in enumerate(actions):
        if runs and runs[-1][1] == code:
            first, _, n = runs[-1]
            runs[-1] = (first, code, n + 1)
        else:
            runs.append((step, int(code), 1))
    return runs


def _draw_trace(top: Any, side: Any, views: _Views, trace: Trace, upto: int | None, compact: bool,
                placed: tuple[list, list]) -> Any:
    """One drone's path with its action codes; returns its legend handle."""
    from matplotlib.lines import Line2D

    color = f"C{trace.drone % 10}"
    path = np.asarray(trace.positions_enu_m, float).reshape(-1, 3)
    shown = path if upto is None else path[: upto + 1]
    done = upto is None or upto >= len(path) - 1
    for ax, project in ((top, views.top), (side, views.side)):
        if not len(shown):
            continue
        if upto is not None and len(path) > 1:  # what is still to come, faintly
            xs, ys = zip(*(project(p) for p in path), strict=True)
            ax.plot(xs, ys, color=color, alpha=0.15, linewidth=1.0, zorder=3)
        xs, ys = zip(*(project(p) for p in shown), strict=True)
        ax.plot(xs, ys, color=color, linewidth=1.6, marker=".", markersize=3.5, zorder=4)
        ax.plot(xs[0], ys[0], marker="o", color=color, markersize=5, markeredgecolor="k",
                markeredgewidth=0.5, zorder=5)
        if done:
            marker = OUTCOME_MARKERS.get(trace.outcome, "o")
            ax.plot(xs[-1], ys[-1], marker=marker, color=color, markersize=11 if marker == "*" else 7,
                    markeredgecolor="k", markeredgewidth=0.6, zorder=6)
        else:  # the drone now
            ax.plot(xs[-1], ys[-1], marker="o", color=color, markersize=7, markeredgecolor="k", zorder=6)
        _label_actions(ax, project, path, trace, upto, color, compact, altitude_only=ax is side,
                       placed=placed[ax is side], near=LABEL_CROWD * views.span(views.along))
    return Line2D([], [], color=color, marker=OUTCOME_MARKERS.get(trace.outcome, "o"), markeredgecolor="k",
                  markeredgewidth=0.5, label=f"drone {trace.drone}: {trace.outcome} after {trace.steps} steps, "
                                             f"reward {trace.reward:.0f}")


def _label_actions(ax: Any, project: Any, path: np.ndarray, trace: Trace, upto: int | None, color: str,
                   compact: bool, altitude_only: bool, placed: list[tuple[float, float]], near: float) -> None:
    """The action code at the start of every run of equal actions (`3x4`: four steps of 3); with
    `altitude_only` (side view) only runs that change altitude, the others pile up there. A label
    closer than `near` (m) to ones already `placed` on this axis goes below them."""
    if trace.actions and isinstance(trace.actions[0], list):
        return  # continuous commands: no codes to label (the path itself shows them)
    dx, dy = (4, 4) if trace.drone % 2 == 0 else (4, -10)
    for first, code, n in run_lengths(trace.actions):
        if upto is not None and first >= upto:
            break
        if first + 1 >= len(path):
            break
        if altitude_only and abs(path[first + 1][2] - path[first][2]) < ALTITUDE_LABEL_M:
            continue
        a, b = project(path[first]), project(path[first + 1])
        where = ((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)
        text = str(code) if n == 1 else f"{code}x{n}"
        crowd = sum(1 for x, y in placed if abs(x - where[0]) < near and abs(y - where[1]) < near)
        placed.append(where)
        if crowd > MAX_STACKED:
            continue  # an oscillation's labels would run off the picture: the stack ends in "..."
        label = ax.annotate("..." if crowd == MAX_STACKED else text, where, xytext=(dx, dy - 8 * crowd),
                            textcoords="offset points", fontsize=5 if compact else 6.5, color=color, zorder=7,
                            fontweight="bold",
                            bbox={"boxstyle": "round,pad=0.12", "facecolor": "white", "alpha": 0.7, "linewidth": 0})
        label.set_in_layout(False)  # a label beside the axes never resizes the figure's layout


def _action_names(frame: str, swapped: bool) -> str:
    names = ACTION_NAMES_BY_FRAME.get(frame, ACTION_NAMES_BY_FRAME["world"])
    return ", ".join(f"{code} {names[_SWAPPED.get(code, code) if swapped else code]}" for code in range(len(names)))


def action_legend(scenario: Scenario) -> str:
    """`actions (world frame): 0 east, 1 west, ...` plus drones whose 0/1 and 2/3 are swapped."""
    action = scenario.task.action
    text = f"actions ({action.frame} frame): {_action_names(action.frame, False)}"
    for drone in action.swap_drones:
        text += f"\ndrone {drone} (swap_drones): {_action_names(action.frame, True)}"
    return text


def _outcomes(traces: Sequence[Trace]) -> str:
    return "; ".join(f"drone {t.drone}: {t.outcome}, {t.steps} steps" for t in traces)


def _animate(fig: Any, top: Any, side: Any, picture: EpisodePicture, out: Path, fps: float, dpi: int) -> None:
    """One frame per action step (the last one held a second longer), written with Pillow. The
    world is drawn once as a background (in the layout of the fullest frame); each frame blits
    only what moves onto it."""
    from PIL import Image

    steps = max((len(t.positions_enu_m) for t in picture.traces), default=1)
    steps = max(steps, *(len(p) for p in picture.movers.values())) if picture.movers else steps
    views = _Views.of(picture)
    base = picture.title
    fig.set_dpi(dpi)
    _draw_static(top, side, picture, views, compact=False)
    kept = {ax: set(ax.get_children()) for ax in (top, side)}

    def moving(k: int) -> list[Any]:
        """Step k's moving artists (the previous step's removed), lowest first."""
        for ax, static in kept.items():
            for artist in [a for a in ax.get_children() if a not in static]:
                artist.remove()
        picture.title = f"{base}  (step {k} of {steps - 1})" if base else f"step {k} of {steps - 1}"
        _draw_moving(top, side, picture, views, k, compact=False)
        new = [a for ax, static in kept.items() for a in ax.get_children() if a not in static]
        return sorted(new, key=lambda a: a.get_zorder())

    try:
        moving(steps - 1)
        fig.canvas.draw()  # the constrained layout, settled with the legend and every label
        fig.set_layout_engine("none")
        for artist in moving(0):  # the background: the world without anything that moves
            artist.remove()
        fig.suptitle("")
        fig.canvas.draw()
        background = fig.canvas.copy_from_bbox(fig.bbox)
        size = fig.canvas.get_width_height()
        frames = []
        for k in range(steps):
            artists = moving(k)
            title = fig.suptitle(picture.title, fontsize=10)
            fig.canvas.restore_region(background)
            for artist in artists:
                fig.draw_artist(artist)
            fig.draw_artist(title)
            frames.append(Image.frombuffer("RGBA", size, bytes(fig.canvas.buffer_rgba())).convert("RGB"))
    finally:
        picture.title = base
    step_ms = int(round(1000.0 / fps))
    durations = [step_ms] * (len(frames) - 1) + [step_ms + 1000]
    frames[0].save(out, format="GIF", save_all=True, append_images=frames[1:], duration=durations, loop=0)
