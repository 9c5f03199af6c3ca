"""`sitl-bridge bench [--quick|--smoke] [--json FILE]`: every speed figure in one run.

Each case is warmed up, then timed over `reps` repetitions; the median, min and max are
reported. Every speed is a real-time factor (simulated s per wall s) and also a fraction of the
bare pybullet loop measured in the same run (`fraction_of_bare`), so figures taken on different
or differently loaded machines compare. Keys of the JSON file (`KEYS`):

* `physics`: bare pybullet (ground plane + one body, 250 Hz, no Python work): the reference,
  measured before the run and again right before every case; a case's `fraction_of_bare` uses
  the figure measured next to it (`bare_rtf_adjacent`), since a shared machine's load drifts.
* `direct`, `direct_ground_truth`: one `direct` env of the obstacle scenario (sensors + the
  stub's estimator and cascade at 250 Hz; the ground-truth estimator), random actions;
  every single-env case also gives `steps_per_s` (env steps per wall second, resets included).
* `decision_0_1s`: the `direct` case on the continuous version of the scenario
  (`obstacle_continuous.yaml`: random `Box(-1, 1)` velocity actions, one every 0.1 s of
  simulated time, ten times the decisions of `direct`'s 1 s); `of_direct` is its fraction of
  bare divided by `direct`'s (the per-decision overhead's cost; 1 = none).
* `batched`: `make_vec_env(num_envs=N)` of the same scenario, random actions, aggregate over
  the N copies, at N = `Size.num_envs` (16); `by_num_envs` holds every N of
  `Size.batched_num_envs` (1, 4, 16, 64), each timed over `Size.batched_steps` vector steps
  per repetition (each its own real-time factor and fraction of bare).
* `stub`: one env on the full protocol path (HIL TCP + stub + MAVLink UDP + MAVSDK), speed 0.
* `px4`: the same with real PX4 when `PX4_BIN` is set, else `{"skipped": reason}`;
  `episode_starts`: of the episodes that ended in the timed repetitions, how many the next
  started in the air and how many by a PX4 restart (random actions crash often; a restart
  costs ~1.2 s, so the figure depends on how many fell into the timed repetitions).
* `px4_standby`: the same with `standby=True` (a standby PX4 takes over where the flying one
  cannot fly on; `episode_starts.handovers`).
* `reset_s`: wall seconds per `reset()` for each backend measured (median, min, max), called
  again right after a reset (nothing flown in between).
* `episode_reset_s` (in every single-env case): the effective reset between episodes, wall
  seconds from the end of an episode of the random flight to the first action of the next
  (the `reset()` after it): count, median, p95, max over at least `Size.episode_resets` ended
  episodes, warm-up and timed repetitions included (the flight goes on after them until
  there are that many).
* `train_steps_per_s`: DQN training env steps per wall second, updates included (O's settings
  from worlds/obstacle.yaml, one env, no evaluation), with its real-time factor and `updates`;
  `train_vector_steps_per_s`: the same with `num_envs` copies at once (bench/training.py).
* `gym_pybullet_drones`, `pyflyt`: those simulators' standard set-ups (bench/peers.py), measured
  in the same run only when they import, else `{"skipped": reason}` (never installed here).
`--scale X` multiplies every case's simulated seconds, episodes and vector steps (longer,
steadier figures); the default sizes keep each case short.
* `parallel`: `direct` envs in 1 and 2 worker processes, aggregate real-time factor and the
  speed-up from 1 to 2 workers (about 2 on two idle cores); `bare_speedup_2_over_1`, the same
  for the bare pybullet loop (what the machine's cores give two CPU-bound processes), and
  `fraction_of_bare_speedup`, the env's speed-up as a share of it. Every worker runs for the
  same `window_s` wall seconds, started together, `reps` windows after one start.
* `px4_parallel`: the same with `px4` envs, each worker its own PX4 instance (each worker's env
  claims one in 0..9 through `autopilot.allocation`, never shared; `instances` says which), in env steps per
  wall second (`steps_per_s`): one PX4-backed env process against two at once, each of the two
  on its own core as a sweep's workers are (`cores`; `pinned`), `reps` timed windows after one
  PX4 start per worker. Needs `PX4_BIN`, else `{"skipped": reason}`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import os
import platform
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from sitl_bridge.bench import peers
from sitl_bridge.bench.physics import STEP_US, bare_pybullet_rtf, bare_world
from sitl_bridge.cores import pin_to_own_core, pins_workers
from sitl_bridge.data_paths import worlds_dir
from sitl_bridge.physics.bullet import p

SCENARIO = "obstacle.yaml"
CONTINUOUS_SCENARIO = "obstacle_continuous.yaml"
"""`decision_0_1s`'s scenario: `SCENARIO` with continuous velocity actions every 0.1 s."""
KEYS = ("physics", "direct", "direct_ground_truth", "decision_0_1s", "batched", "stub", "px4", "px4_standby",
        "reset_s", "train_steps_per_s", "train_vector_steps_per_s", "gym_pybullet_drones", "pyflyt", "parallel",
        "px4_parallel")


@dataclass(frozen=True)
class Size:
    """How much each case runs: `sim_s` simulated seconds per repetition, `reps` repetitions."""

    name: str
    sim_s: float
    reps: int
    warmup_s: float
    bare_s: float
    num_envs: int
    resets: int
    episode_resets: int
    """Ended episodes whose reset `episode_reset_s` times, at least."""
    train_episodes: int
    parallel_window_s: float
    """Wall seconds of each of `parallel`'s `reps` timed windows (all workers run the whole window)."""
    px4_parallel_window_s: float
    """The same for `px4_parallel`."""
    batched_num_envs: tuple[int, ...]
    """The N of `batched`'s `by_num_envs`."""
    batched_steps: int
    """Vector steps per timed repetition of each N (N env steps each)."""
    peer_sim_s: float
    """Simulated seconds per repetition of each peer simulator."""

    def scaled(self, factor: float) -> Size:
        """This size with every case's simulated seconds, episodes and vector steps times `factor`."""
        if not factor > 0:
            raise ValueError(f"bench --scale: expected a positive number, got {factor!r}")
        return replace(self, sim_s=self.sim_s * factor, bare_s=self.bare_s * factor,
                       train_episodes=max(1, round(self.train_episodes * factor)),
                       batched_steps=max(1, round(self.batched_steps * factor)),
                       peer_sim_s=self.peer_sim_s * factor,
                       parallel_window_s=self.parallel_window_s * factor,
                       px4_parallel_window_s=self.px4_parallel_window_s * factor)


SIZES = {
    "full": Size("full", 100.0, 5, 10.0, 100.0, 16, 10, 50, 40, 5.0, 15.0, (1, 4, 16, 64), 4, 60.0),
    "quick": Size("quick", 30.0, 3, 5.0, 50.0, 16, 5, 10, 12, 2.0, 6.0, (1, 4, 16, 64), 2, 20.0),
    # for the test: seconds, figures meaningless
    "smoke": Size("smoke", 1.0, 2, 1.0, 2.0, 2, 2, 1, 2, 0.1, 0.5, (1, 2), 1, 0.5),
}


def _spread(values: list[float]) -> dict[str, float]:
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def _distribution(values: list[float]) -> dict[str, float]:
    return {"count": len(values), "median": statistics.median(values),
            "p95": float(np.percentile(values, 95)), "max": max(values)}


def _rtf_entry(rtfs: list[float], bare: float, **extra: Any) -> dict[str, Any]:
    entry: dict[str, Any] = {"rtf": _spread(rtfs), "reps": len(rtfs)}
    entry["fraction_of_bare"] = {k: v / bare for k, v in entry["rtf"].items()}
    entry.update(extra)
    return entry


def _scenario(name: str = SCENARIO) -> Path:
    return worlds_dir() / name


def _fly(step: Callable[[], float], sim_s: float) -> float:
    """Real-time factor of calling `step` (which returns the simulated seconds it flew) until
    `sim_s` simulated seconds have passed."""
    flown = 0.0
    start = time.perf_counter()
    while flown < sim_s:
        flown += step()
    return flown / (time.perf_counter() - start)


def _cpu_s() -> tuple[float, float | None]:
    """CPU seconds used so far by this process (all threads) and by its descendants, live or
    ended (Linux /proc; None elsewhere): PX4 runs in children (with `standby`, grandchildren
    under the backend's worker processes), the simulator and MAVSDK here or in those workers."""
    own = time.process_time()
    times = os.times()
    ended = times.children_user + times.children_system
    try:
        tick = os.sysconf("SC_CLK_TCK")
        children: dict[int, list[int]] = {}
        used: dict[int, float] = {}
        for stat in Path("/proc").glob("[0-9]*/stat"):
            with contextlib.suppress(OSError, IndexError, ValueError):
                fields = stat.read_text().rsplit(")", 1)[1].split()
                # after the name: ppid 1; utime, stime 11, 12; reaped children's cutime, cstime 13, 14
                pid = int(stat.parent.name)
                children.setdefault(int(fields[1]), []).append(pid)
                used[pid] = sum(int(f) for f in fields[11:15]) / tick
    except (OSError, ValueError):
        return own, None
    live, stack = 0.0, list(children.get(os.getpid(), ()))
    while stack:
        pid = stack.pop()
        live += used.get(pid, 0.0)
        stack.extend(children.get(pid, ()))
    return own, ended + live


def _cpu_ms_per_step(before: tuple[float, float | None], after: tuple[float, float | None],
                     steps: float) -> dict[str, float] | None:
    if before[1] is None or after[1] is None or steps <= 0:
        return None
    own, children = (after[0] - before[0]) * 1e3 / steps, (after[1] - before[1]) * 1e3 / steps
    return {"this_process": own, "children": children, "total": own + children}


class _RandomFlight:
    """One random action per call (resets included: training pays for them too); returns the
    simulated seconds it flew. Counts the episodes it ended (`episodes_ended`) and times the
    reset after each (`episode_reset_s`)."""

    def __init__(self, env: Any, seed: int = 0) -> None:
        self.env = env
        self.rng = np.random.default_rng(seed)
        action = env.scenario.task.action
        self.step_s = action.step_s
        self.action_size = action.size if action.continuous else 0  # 0: a discrete code
        self.episodes_ended = 0
        self.episode_reset_s: list[float] = []

    def _action(self) -> Any:
        if self.action_size:
            return self.rng.uniform(-1.0, 1.0, self.action_size).astype(np.float32)
        return int(self.rng.integers(8))

    def __call__(self) -> float:
        _, _, terminated, truncated, _ = self.env.step(self._action())
        if terminated or truncated:
            self.episodes_ended += 1
            t0 = time.perf_counter()
            self.env.reset()
            self.episode_reset_s.append(time.perf_counter() - t0)
        return self.step_s


def _ended_and_in_air(flight: _RandomFlight) -> tuple[int, int, int]:
    """Episodes `flight` ended so far, the next episodes its backend started in the air, and
    of those the ones a standby took over (`standby=True`)."""
    backend = flight.env.unwrapped.backend
    return flight.episodes_ended, getattr(backend, "in_air_resets", 0), getattr(backend, "handovers", 0)


def _episode_starts(before: tuple[int, int, int], after: tuple[int, int, int]) -> dict[str, int]:
    """How the episodes ended between two `_ended_and_in_air` counts were followed: in the air
    (px4: PX4 flew on, or a standby PX4 took over) or by an autopilot restart in the foreground
    (a crash, a tumble or a failsafe: about a second each)."""
    ended, in_air, handovers = (a - b for a, b in zip(after, before, strict=True))
    return {"episodes_ended": ended, "in_air": in_air, "handovers": handovers, "restarts": ended - in_air}


def _env_case(backend: str, size: Size, bare: float, estimator: str = "sensors",
              px4_bin: str | None = None, standby: bool = False,
              scenario: str = SCENARIO) -> tuple[dict[str, Any], list[float]]:
    """(figures, reset wall seconds) for one single env on `backend`."""
    from sitl_bridge.bench.stub import BENCH_INSTANCE_BASE
    from sitl_bridge.envs import make_env

    # session backends claim a free instance from here up (px4: in 0..9)
    env = make_env(_scenario(scenario), autopilot=backend, speed_factor=0.0, seed=0, instance_base=BENCH_INSTANCE_BASE,
                   estimator=estimator, px4_bin=px4_bin, standby=standby)
    step = _RandomFlight(env)
    try:
        env.reset(seed=0)
        _fly(step, size.warmup_s)
        before, counts = _cpu_s(), _ended_and_in_air(step)
        rtfs = [_fly(step, size.sim_s) for _ in range(size.reps)]
        cpu = _cpu_ms_per_step(before, _cpu_s(), size.reps * size.sim_s / step.step_s)
        starts = _episode_starts(counts, _ended_and_in_air(step))
        while len(step.episode_reset_s) < size.episode_resets:
            step()
        resets = []
        for _ in range(size.resets):
            t0 = time.perf_counter()
            env.reset()
            resets.append(time.perf_counter() - t0)
    finally:
        env.close()
    extra: dict[str, Any] = {"episode_reset_s": _distribution(step.episode_reset_s)}
    if backend != "direct" and cpu is not None:
        extra["cpu_ms_per_step"] = cpu
    if backend == "px4":
        extra["episode_starts"] = starts
    if standby:
        extra["standby"] = True
    return _rtf_entry(rtfs, bare, backend=backend, estimator=estimator,
                      steps_per_s=_spread([rtf / step.step_s for rtf in rtfs]), **extra), resets


def _batched_rtfs(num_envs: int, vector_steps: int, reps: int) -> list[float]:
    """Aggregate real-time factor of `make_vec_env(num_envs)` with random actions, one per
    repetition of `vector_steps` vector steps (after one warm-up step)."""
    from sitl_bridge.envs.vector import make_vec_env

    venv = make_vec_env(_scenario(), num_envs=num_envs, seed=0)
    rng = np.random.default_rng(0)
    step_s = venv.envs[0].unwrapped.scenario.task.action.step_s * num_envs

    def step() -> float:
        venv.step(rng.integers(8, size=num_envs))
        return step_s

    try:
        venv.reset(seed=0)
        step()
        return [_fly(step, vector_steps * step_s) for _ in range(reps)]
    finally:
        venv.close()


def _batched_case(size: Size, bare: float) -> dict[str, Any]:
    design = "SyncVectorEnv of SitlEnv (one client each)"
    by_n = {str(n): _rtf_entry(_batched_rtfs(n, size.batched_steps, size.reps), bare, num_envs=n,
                               vector_steps=size.batched_steps)
            for n in sorted({*size.batched_num_envs, size.num_envs})}
    headline = by_n[str(size.num_envs)]
    return {**headline, "design": design, "by_num_envs": by_n}


def _train_entry(rates: list[float], updates: int, bare: float, **extra: Any) -> dict[str, Any]:
    entry: dict[str, Any] = {"steps_per_s": _spread(rates), "reps": len(rates), "updates": updates, **extra}
    entry["rtf"] = {k: v * _step_s() for k, v in entry["steps_per_s"].items()}
    entry["fraction_of_bare"] = {k: v / bare for k, v in entry["rtf"].items()}
    return entry


def _train_case(size: Size, bare: float) -> dict[str, Any]:
    """DQN env steps per wall second with O's `train:` settings (updates every step), one env."""
    from sitl_bridge.bench.training import train_rates

    return _train_entry(*train_rates(_scenario(), size.train_episodes, size.reps), bare, num_envs=1)


def _train_vector_case(size: Size, bare: float) -> dict[str, Any]:
    """The same with `VECTOR_ENVS` copies flown at once."""
    from sitl_bridge.bench.training import VECTOR_ENVS, train_rates

    rates, updates = train_rates(_scenario(), size.train_episodes, size.reps, VECTOR_ENVS)
    return _train_entry(rates, updates, bare, num_envs=VECTOR_ENVS)


def _peer_case(key: str, size: Size, bare: float) -> dict[str, Any]:
    from sitl_bridge.bench.peers import MEASURE

    rtfs, about = MEASURE[key](size.peer_sim_s, size.warmup_s, size.reps)
    return _rtf_entry(rtfs, bare, **about)


def _fly_windows(step: Callable[[], float], windows: int, window_s: float, barrier, results,
                 instances: tuple[int, ...] = ()) -> None:  # noqa: ANN001 - multiprocessing proxies
    """Call `step` (which returns the simulated seconds it flew) for `windows` timed windows of
    `window_s` wall seconds each, every window started together with the other workers'
    (`barrier`). Puts (window, simulated s, wall start, wall end, instances) per window.

    The windows are fixed in wall time, not in simulated time, so that all workers run for the
    whole window: with a fixed simulated length the worker that finishes first leaves the other
    running alone, and that tail counts as lost parallelism."""
    for window in range(windows):
        barrier.wait(timeout=600)
        start, flown = time.perf_counter(), 0.0
        while time.perf_counter() - start < window_s:
            flown += step()
        results.put((window, flown, start, time.perf_counter(), instances))


def _parallel_worker(options: dict[str, Any], windows: int, window_s: float, warmup_s: float, pin: bool,
                     index: int, barrier, results) -> None:  # noqa: ANN001 - multiprocessing proxies
    """Fly one env with `options` (`EnvOptions` fields) in this worker process (seeded with the
    worker's `index`, so worker 0 flies the same episodes whether alone or with others; with
    `pin`, on its own core: `cores`): warm up, then `_fly_windows`; puts ("failed", text) once
    if anything fails."""
    from sitl_bridge.envs import make_env

    env = None
    if pin:
        pin_to_own_core(index)
    try:
        # session backends claim their own instances (autopilot.allocation): nothing handed in
        env = make_env(_scenario(), speed_factor=0.0, seed=index, **options)
        step = _RandomFlight(env, seed=index)
        env.reset(seed=index)
        _fly(step, warmup_s)  # a PX4 boot and takeoff happen here, before any window
        session = getattr(env.backend, "session", None)  # session backends only (stub, px4)
        instances = tuple(session.instances) if session is not None else ()
        _fly_windows(step, windows, window_s, barrier, results, instances)
    except Exception as exc:  # reported by the parent; the others must not wait for this one
        barrier.abort()
        results.put(("failed", f"{type(exc).__name__}: {exc}"))
    finally:
        if env is not None:
            env.close()


def _bare_worker(windows: int, window_s: float, index: int, barrier, results) -> None:  # noqa: ANN001, ARG001
    """The bare pybullet loop in this worker process, in `_fly_windows` (one simulated second a call)."""
    with bare_world() as (cid, body):
        steps = int(1e6 / STEP_US)

        def step() -> float:
            # back to the start height each simulated second: windows are long enough to land
            p.resetBasePositionAndOrientation(body, (0.0, 0.0, 1e5), (0.0, 0.0, 0.0, 1.0), physicsClientId=cid)
            for _ in range(steps):
                p.stepSimulation(physicsClientId=cid)
            return 1.0

        _fly_windows(step, windows, window_s, barrier, results)


@contextlib.contextmanager
def _together(target: Callable[..., None], args: tuple, workers: int) -> Iterator[Any]:
    """`workers` fresh processes (spawned: no pybullet state copied by fork) each running
    `target(*args, index, barrier, results)` with its index 0, 1, ...; yields the results queue;
    on exit each is joined, or killed when it does not end."""
    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(workers), ctx.Queue()
    procs = [ctx.Process(target=target, args=(*args, index, barrier, results)) for index in range(workers)]
    for proc in procs:
        proc.start()
    try:
        yield results
    finally:
        for proc in procs:
            proc.join(timeout=60)
            if proc.is_alive():
                proc.kill()
                proc.join()


def _windows_rtf(target: Callable[..., None], args: tuple, workers: int,
                 windows: int) -> tuple[list[float], list[tuple[int, ...]]]:
    """Aggregate real-time factor of `workers` processes running `target` (a `_fly_windows`
    worker), per timed window: the sum of each worker's own simulated s per wall s; and the
    instances each worker flew (session backends)."""
    with _together(target, args, workers) as results:
        runs = []
        for _ in range(workers * windows):
            runs.append(results.get(timeout=600))
            if runs[-1][0] == "failed":  # the others stop too (their barrier is broken)
                raise RuntimeError(f"worker: {runs[-1][1]}")
    rtfs = [sum(r[1] / (r[3] - r[2]) for r in runs if r[0] == window) for window in range(windows)]
    return rtfs, [r[4] for r in runs if r[0] == 0]


def _parallel_rtf(workers: int, size: Size, window_s: float,
                  **options: Any) -> tuple[list[float], list[tuple[int, ...]]]:
    """`_windows_rtf` of `workers` env worker processes with env `options` (default `direct`),
    `size.reps` windows after one start each."""
    pin = pins_workers(options.get("autopilot", "direct"), workers)  # as a sweep of such runs does
    return _windows_rtf(_parallel_worker, (options, size.reps, window_s, size.warmup_s, pin), workers, size.reps)


def _parallel_case(size: Size, bare: float) -> dict[str, Any]:
    one, two = (_parallel_rtf(workers, size, size.parallel_window_s)[0] for workers in (1, 2))
    speedup = statistics.median(two) / statistics.median(one)
    bare_one, bare_two = (_windows_rtf(_bare_worker, (size.reps, size.parallel_window_s), workers, size.reps)[0]
                          for workers in (1, 2))
    bare_speedup = statistics.median(bare_two) / statistics.median(bare_one)
    return {"workers_1": _rtf_entry(one, bare), "workers_2": _rtf_entry(two, bare),
            "speedup_2_over_1": speedup, "bare_workers_1": _spread(bare_one), "bare_workers_2": _spread(bare_two),
            "bare_speedup_2_over_1": bare_speedup,
            "fraction_of_bare_speedup": speedup / bare_speedup, "window_s": size.parallel_window_s,
            "cpu_count": os.cpu_count()}


def _px4_parallel_case(size: Size, bare: float, px4_bin: str) -> dict[str, Any]:
    """Env steps/s of one px4 env process against two at once (aggregate), each worker with
    its own PX4; one PX4 start per worker count, `reps` timed windows after it."""
    step_s = _step_s()
    entries = {}
    for workers in (1, 2):
        # Nothing handed out: each worker's env claims its own free PX4 instance in 0..9 and
        # holds it to the end (`autopilot.allocation`); the workers report which.
        rtfs, instances = _parallel_rtf(workers, size, size.px4_parallel_window_s, autopilot="px4", px4_bin=px4_bin)
        steps = [rtf / step_s for rtf in rtfs]
        entries[f"workers_{workers}"] = _rtf_entry(rtfs, bare, steps_per_s=_spread(steps),
                                                   instances=[list(i) for i in instances],
                                                   pinned=pins_workers("px4", workers))
    speedup = entries["workers_2"]["rtf"]["median"] / entries["workers_1"]["rtf"]["median"]
    return {**entries, "speedup_2_over_1": speedup, "step_s": step_s, "window_s": size.px4_parallel_window_s,
            "cpu_count": os.cpu_count()}


def _step_s() -> float:
    """Simulated seconds per env step (one action) of the bench's scenario."""
    from sitl_bridge.envs import load_scenario

    return load_scenario(str(_scenario())).task.action.step_s


def measure(size: Size, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Every figure of `KEYS` for `size`; a case that fails is reported under its key as
    `{"failed": "..."}` instead of stopping the others."""
    result: dict[str, Any] = {"size": size.name, "scenario": SCENARIO, "machine": platform.node(),
                              "cpu_count": os.cpu_count(), "load_avg_1m": os.getloadavg()[0]}
    # The reference is re-measured right before every case and each case's fractions use that
    # adjacent figure: the load of a shared machine changes within one run.
    bares = [bare_pybullet_rtf(size.bare_s)[0] for _ in range(size.reps)]
    result["physics"] = _rtf_entry(bares, statistics.median(bares))
    log(f"  physics (bare pybullet): {statistics.median(bares):.0f}x real time")
    resets: dict[str, Any] = {}
    px4_bin = os.environ.get("PX4_BIN")
    cases: list[tuple[str, Callable[[float], Any]]] = [
        ("direct", lambda bare: _env_case("direct", size, bare)),
        ("direct_ground_truth", lambda bare: _env_case("direct", size, bare, estimator="ground_truth")),
        ("decision_0_1s", lambda bare: _env_case("direct", size, bare, scenario=CONTINUOUS_SCENARIO)),
        ("batched", lambda bare: _batched_case(size, bare)),
        ("stub", lambda bare: _env_case("stub", size, bare)),
        ("px4", lambda bare: _env_case("px4", size, bare, px4_bin=px4_bin)),
        ("px4_standby", lambda bare: _env_case("px4", size, bare, px4_bin=px4_bin, standby=True)),
        ("train_steps_per_s", lambda bare: _train_case(size, bare)),
        ("train_vector_steps_per_s", lambda bare: _train_vector_case(size, bare)),
        ("gym_pybullet_drones", lambda bare: _peer_case("gym_pybullet_drones", size, bare)),
        ("pyflyt", lambda bare: _peer_case("pyflyt", size, bare)),
        ("parallel", lambda bare: _parallel_case(size, bare)),
        ("px4_parallel", lambda bare: _px4_parallel_case(size, bare, px4_bin or "")),
    ]
    for key, case in cases:
        skipped = "PX4_BIN not set" if key.startswith("px4") and not px4_bin else \
            peers.missing(key) if key in peers.PEERS else None
        if skipped:
            result[key] = {"skipped": skipped}
            log(f"  {key}: skipped ({skipped})")
            continue
        t0 = time.perf_counter()
        try:
            adjacent = [bare_pybullet_rtf(size.bare_s)[0] for _ in range(size.reps)]
            bares += adjacent
            figures = case(statistics.median(adjacent))
        except Exception as exc:  # a failing case is a result to report, not a crash
            result[key] = {"failed": f"{type(exc).__name__}: {exc}"}
            log(f"  {key}: FAILED: {type(exc).__name__}: {exc}")
            continue
        if isinstance(figures, tuple):
            figures, reset_s = figures
            if key not in ("direct_ground_truth", "decision_0_1s"):
                resets[key] = _spread(reset_s)
        figures["bare_rtf_adjacent"] = statistics.median(adjacent)
        if key == "decision_0_1s" and "fraction_of_bare" in result.get("direct", {}):
            figures["of_direct"] = (figures["fraction_of_bare"]["median"]
                                    / result["direct"]["fraction_of_bare"]["median"])
        result[key] = figures
        log(f"  {key}: {_summary(figures)}  ({time.perf_counter() - t0:.0f} s)")
    result["reset_s"] = resets
    result["physics"] = _rtf_entry(bares, statistics.median(bares))  # every bare measurement of the run
    log("  reset_s: " + ", ".join(f"{k} {v['median']:.3f} s" for k, v in resets.items()))
    return result


def _summary(figures: dict[str, Any]) -> str:
    if "workers_2" in figures and "steps_per_s" in figures["workers_2"]:
        return (f"1 worker {figures['workers_1']['steps_per_s']['median']:.1f} env steps/s, 2 workers "
                f"{figures['workers_2']['steps_per_s']['median']:.1f} aggregate, "
                f"speed-up {figures['speedup_2_over_1']:.2f}")
    if "workers_2" in figures:
        return (f"1 worker {figures['workers_1']['rtf']['median']:.0f}x, 2 workers "
                f"{figures['workers_2']['rtf']['median']:.0f}x aggregate, "
                f"speed-up {figures['speedup_2_over_1']:.2f} (bare pybullet's "
                f"{figures['bare_speedup_2_over_1']:.2f})")
    rtf, frac = figures["rtf"], figures["fraction_of_bare"]
    text = (f"{rtf['median']:.1f}x real time (min {rtf['min']:.1f}, max {rtf['max']:.1f}); "
            f"{frac['median']:.3f} of bare")
    if "steps_per_s" in figures:
        text = f"{figures['steps_per_s']['median']:.1f} steps/s, " + text
    if "by_num_envs" in figures:
        text += "; by N: " + ", ".join(f"{n}: {e['rtf']['median']:.1f}x ({e['fraction_of_bare']['median']:.3f})"
                                       for n, e in figures["by_num_envs"].items())
    if "cpu_ms_per_step" in figures:
        cpu = figures["cpu_ms_per_step"]
        text += (f"; CPU per env step {cpu['total']:.0f} ms ({cpu['this_process']:.0f} here, "
                 f"{cpu['children']:.0f} in child processes)")
    if "episode_starts" in figures:
        starts = figures["episode_starts"]
        handed = f" ({starts['handovers']} by the standby)" if starts["handovers"] else ""
        text += (f"; {starts['episodes_ended']} episodes ended: {starts['in_air']} next started in the air{handed}, "
                 f"{starts['restarts']} by a restart")
    if "episode_reset_s" in figures:
        resets = figures["episode_reset_s"]
        text += (f"; reset after an episode {resets['median']:.3f} s median, p95 {resets['p95']:.3f} s "
                 f"({resets['count']} resets)")
    return text


def run(args: argparse.Namespace) -> int:
    """Measure at the chosen size, print a summary, write `--json` if given."""
    size = SIZES["smoke" if getattr(args, "smoke", False) else "quick" if getattr(args, "quick", False) else "full"]
    scale = getattr(args, "scale", 1.0)
    if scale != 1.0:
        size = size.scaled(scale)
    print(f"bench ({size.name}): {SCENARIO}, {size.reps} repetitions of {size.sim_s:g} simulated s "
          f"per case after {size.warmup_s:g} s warm-up; real-time factor = simulated s / wall s", flush=True)
    start = time.perf_counter()
    result = measure(size, log=lambda line: print(line, flush=True))
    result["wall_s"] = time.perf_counter() - start
    if getattr(args, "json", None):
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
        print(f"written: {args.json}")
    failed = [k for k in KEYS if isinstance(result.get(k), dict) and "failed" in result[k]]
    return 1 if failed else 0
