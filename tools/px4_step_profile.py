"""Where the CPU of one `px4` env step goes: our process per thread, and the PX4 process.

Runs `--steps` env steps of `make_env(<world>, autopilot="px4", speed_factor=0)` with a constant
action (episodes that end are reset, untimed) and reports per env step:

* wall ms and env steps/s (timed `env.step` calls only);
* CPU ms of every thread of this process, by thread name (Python's and MAVSDK's native ones),
  read from the kernel's per-thread CPU clocks (ns, `clock_gettime` on `((~tid) << 3) | 6`),
  and of the PX4 process (its process CPU clock, all its threads);
* with `--count`: what PX4 sends to the MAVLink API port (MAVSDK) and the GCS port per env
  step, messages and bytes by message id, sniffed on the loopback device by a separate process
  (an AF_PACKET socket: needs root; its CPU is not ours nor PX4's, but it shares the cores, so
  time the run without it).

Usage: PX4_BIN=... PYTHONPATH=. python tools/px4_step_profile.py [--world empty.yaml]
       [--steps 60] [--action 7] [--count] [--breakdown N] [--json FILE]
"""

from __future__ import annotations

import argparse
import collections
import json
import multiprocessing as mp
import os
import socket
import struct
import threading
import time
from pathlib import Path
from typing import Any

from method_timers import timed_methods  # tools/ is on sys.path when run as a script

from sitl_bridge.envs import make_env, worlds_dir
from sitl_bridge.ports import API_CLIENT_BASE_PORT, GCS_BIND_BASE_PORT


def thread_clock(tid: int) -> int:
    """The kernel's CPU clock id of thread `tid` of this process (CPUCLOCK_SCHED, per thread)."""
    return ((~tid) << 3) | 6


def process_clock(pid: int) -> int:
    """The kernel's CPU clock id of process `pid` (all its threads)."""
    return ((~pid) << 3) | 2


def thread_cpu_s() -> dict[str, float]:
    """CPU seconds of every live thread of this process, summed by name (`comm`)."""
    named = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = collections.defaultdict(float)
    for entry in os.listdir("/proc/self/task"):
        tid = int(entry)
        try:
            # Python threads by their Python name; the rest are native (MAVSDK's, numpy's...)
            name = named.get(tid) or f"native:{Path(f'/proc/self/task/{tid}/comm').read_text().strip()}:{tid}"
            out[name] += time.clock_gettime(thread_clock(tid))
        except OSError:
            continue  # the thread ended meanwhile
    return dict(out)


def px4_threads_s(pid: int) -> dict[str, float]:
    """CPU seconds (utime + stime, clock ticks) of every thread of process `pid`, by name."""
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = collections.defaultdict(float)
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return {}
    for tid in tids:
        try:
            stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        out[name] += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
    return dict(out)


def _normalise(name: str) -> str:
    # thread names carry instance/ids: group them
    for prefix in ("px4-console", "mavsdk-", "ThreadPoolExecutor"):
        if name.startswith(prefix):
            return prefix.rstrip("-") + "*"
    return name


def _sniff(ports: dict[int, str], stop: Any, result: Any) -> None:
    """Count MAVLink frames (msgid -> [messages, bytes]) sent to the UDP `ports` on lo."""
    from sitl_bridge import mavlink

    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.ntohs(0x0003))
    sock.bind(("lo", 0))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 24)  # lose nothing while busy
    sock.settimeout(0.2)
    counts: dict[str, dict[int, list[int]]] = {label: collections.defaultdict(lambda: [0, 0]) for label in ports.values()}
    datagrams = dict.fromkeys(ports.values(), 0)
    enabled = False
    while not stop.is_set():
        try:
            frame, addr = sock.recvfrom(65536)
        except TimeoutError:
            continue
        if addr[2] == socket.PACKET_OUTGOING:  # lo shows every packet twice
            continue
        if not enabled:
            enabled = result.get("enabled", False)
        if not enabled or len(frame) < 14 + 20 + 8 or frame[12:14] != b"\x08\x00" or frame[23] != 17:
            continue
        ihl = (frame[14] & 0x0F) * 4
        udp = 14 + ihl
        dport = struct.unpack_from("!H", frame, udp + 2)[0]
        label = ports.get(dport)
        if label is None:
            continue
        datagrams[label] += 1
        for parsed in mavlink.FrameParser().feed(bytes(frame[udp + 8:])):
            entry = counts[label][parsed.msgid]
            entry[0] += 1
            entry[1] += len(parsed.raw)
        if result.get("snapshot"):
            result["counts"] = {label: {k: list(v) for k, v in c.items()} for label, c in counts.items()}
            result["datagrams"] = dict(datagrams)
            result["snapshot"] = False
    result["counts"] = {label: {k: list(v) for k, v in c.items()} for label, c in counts.items()}
    result["datagrams"] = dict(datagrams)


# (component, parent or "", object path, method): timed in thread CPU with `--breakdown`
TIMED = (
    ("lockstep.step", "", "lockstep", "step"),
    ("physics (sim.step)", "lockstep.step", "sim", "step"),
    ("sensors (sample_values)", "lockstep.step", "suite", "sample_values"),
    ("ground truth", "lockstep.step", "suite", "ground_truth"),
    ("sim.state", "lockstep.step", "sim", "state"),
    ("HIL encode + send", "lockstep.step", "link", "send_sensor_values"),
    ("HIL send (syscall)", "HIL encode + send", "link", "_send"),
    ("collect answers", "lockstep.step", "lockstep", "_collect_answers"),
    ("wait (select)", "collect answers", "lockstep", "_wait_readable"),
    ("HIL receive + decode", "collect answers", "link", "poll"),
    ("pace", "lockstep.step", "lockstep", "_pace"),
)


def _breakdown(env: Any, steps: int, action: int) -> dict[str, float]:
    """Thread CPU ms per env step of each TIMED component, own time (children subtracted;
    each timed call adds ~1 us of timer cost, attributed to its parent)."""
    session = env.backend.session
    lockstep = session.lockstep
    objects = {"lockstep": lockstep, "sim": lockstep.sim, "suite": lockstep.sensors[0], "link": lockstep.links[0]}
    done = 0
    with timed_methods(objects, TIMED) as (totals, calls):
        while done < steps:
            _, _, term, trunc, _ = env.step(action)
            done += 1
            if term or trunc:
                break  # a reset would rebuild the objects
    own = {name: float(totals[name]) for name in totals}
    for name, parent, *_ in TIMED:
        if parent:
            own[parent] -= totals[name]
    out = {name: round(value / 1e6 / done, 2) for name, value in own.items()}
    out["calls per env step: lockstep.step"] = calls["lockstep.step"] / done
    out["env steps"] = done
    return out


def _px4_pid(env: Any) -> int:
    return env.backend.session.autopilots.px4.autopilots[0].pid


def profile(world: str, steps: int, action: int, warmup: int, count: bool, seed: int = 0,
            breakdown: int = 0) -> dict[str, Any]:
    """Run the env and return the per-env-step figures (see module docstring)."""
    env = make_env(worlds_dir() / world, autopilot="px4", speed_factor=0.0, seed=seed)
    sniffer = None
    manager = stop = shared = None
    try:
        env.reset(seed=seed)
        instance = env.backend.session.instances[0]
        px4_pid = _px4_pid(env)
        if count:
            manager = mp.Manager()
            stop = manager.Event()
            shared = manager.dict()
            ports = {API_CLIENT_BASE_PORT + instance: "api", GCS_BIND_BASE_PORT + instance: "gcs_to_px4",
                     14550: "gcs"}
            sniffer = mp.get_context("spawn").Process(target=_sniff, args=(ports, stop, shared), daemon=True)
            sniffer.start()
            time.sleep(1.0)
        for _ in range(warmup):
            _, _, term, trunc, _ = env.step(action)
            if term or trunc:
                env.reset()
        if count:
            shared["enabled"] = True
        wall = 0.0
        ours0 = thread_cpu_s()
        ours_cpu = 0.0
        px4_cpu = 0.0
        per_thread: dict[str, float] = collections.defaultdict(float)
        px4_threads: dict[str, float] = collections.defaultdict(float)
        done = 0
        resets = 0
        while done < steps:
            before = thread_cpu_s()
            px4_before = px4_threads_s(px4_pid)
            c0 = time.clock_gettime(process_clock(os.getpid()))
            p0 = time.clock_gettime(process_clock(px4_pid))
            t0 = time.perf_counter()
            _, _, term, trunc, _ = env.step(action)
            wall += time.perf_counter() - t0
            px4_cpu += time.clock_gettime(process_clock(px4_pid)) - p0
            ours_cpu += time.clock_gettime(process_clock(os.getpid())) - c0
            after = thread_cpu_s()
            for name, value in px4_threads_s(px4_pid).items():
                px4_threads[name] += value - px4_before.get(name, 0.0)
            for name, value in after.items():
                per_thread[_normalise(name)] += value - before.get(name, 0.0)
            done += 1
            if term or trunc:
                if count:
                    shared["enabled"] = False
                env.reset()
                resets += 1
                px4_pid = _px4_pid(env)  # a restart (not in the air) starts another PX4
                if count:
                    shared["enabled"] = True
        del ours0
        result: dict[str, Any] = {
            "world": world, "action": action, "steps": done, "resets": resets,
            "wall_ms": 1e3 * wall / done, "steps_per_s": done / wall,
            "ours_cpu_ms": 1e3 * ours_cpu / done, "px4_cpu_ms": 1e3 * px4_cpu / done,
            "threads_cpu_ms": {k: round(1e3 * v / done, 2) for k, v in sorted(per_thread.items(), key=lambda kv: -kv[1])},
            "px4_threads_cpu_ms": {k: round(1e3 * v / done, 2)
                                   for k, v in sorted(px4_threads.items(), key=lambda kv: -kv[1]) if v > 0},
        }
        if breakdown:
            env.reset()
            result["breakdown_cpu_ms"] = _breakdown(env, breakdown, action)
        if count:
            shared["snapshot"] = True
            time.sleep(0.5)
            stop.set()
            sniffer.join(5)
            from sitl_bridge import mavlink
            links = {}
            for label, by_id in dict(shared.get("counts", {})).items():
                rows = []
                for msgid, (n, nbytes) in sorted(by_id.items(), key=lambda kv: -kv[1][0]):
                    cls = mavlink.message_class(int(msgid))
                    rows.append({"msg": cls.msgname if cls else str(msgid), "id": int(msgid),
                                 "per_step": round(n / done, 1), "bytes_per_step": round(nbytes / done)})
                links[label] = {"messages_per_step": round(sum(r["per_step"] for r in rows), 1),
                                "bytes_per_step": sum(r["bytes_per_step"] for r in rows),
                                "datagrams_per_step": round(dict(shared.get("datagrams", {})).get(label, 0) / done, 1),
                                "by_message": rows}
            result["mavlink"] = links
        return result
    finally:
        if stop is not None:
            stop.set()
        if sniffer is not None:
            sniffer.join(5)
            if sniffer.is_alive():
                sniffer.terminate()
        if manager is not None:
            manager.shutdown()
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--world", default="empty.yaml")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--action", type=int, default=7, help="constant action (7: hover)")
    parser.add_argument("--count", action="store_true", help="sniff MAVLink on lo (root)")
    parser.add_argument("--breakdown", type=int, default=0, metavar="N",
                        help="then N more env steps with the lockstep's parts timed (thread CPU)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    result = profile(args.world, args.steps, args.action, args.warmup, args.count, breakdown=args.breakdown)
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text)


if __name__ == "__main__":
    main()
