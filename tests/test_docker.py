"""docker/compose.yaml without a Docker engine: it parses, published ports are unique and bound to
127.0.0.1, the PX4 vehicles use distinct instances, and the learner's command runs (1 episode)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).parent.parent
COMPOSE = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())


def published(service: dict) -> list[str]:
    return [p.rsplit(":", 1)[0].split(":", 1)[1] + "/" + (p.split("/")[1] if "/" in p else "tcp")
            for p in service.get("ports", [])]


def test_compose_services_and_ports_do_not_collide() -> None:
    services = COMPOSE["services"]
    assert {"learner-0", "learner-1", "tensorboard", "px4-0", "px4-1"} <= set(services)
    ports = [port for s in services.values() for port in published(s)]
    assert len(ports) == len(set(ports)), ports
    assert all(p.startswith("127.0.0.1:") for s in services.values() for p in s.get("ports", []))
    instances = [s["command"][s["command"].index("--instance-base") + 1] for name, s in services.items()
                 if name.startswith("px4-")]
    assert len(instances) == len(set(instances))
    seeds = [s["command"][s["command"].index("--seed") + 1] for name, s in services.items()
             if name.startswith("learner-")]
    assert len(seeds) == len(set(seeds))  # distinct run directories


def test_learner_entrypoint_runs_outside_docker(tmp_path: Path) -> None:
    command = list(COMPOSE["services"]["learner-0"]["command"])  # with its --watchdog
    command[command.index("/runs")] = str(tmp_path)
    done = subprocess.run([sys.executable, "-m", "sitl_bridge", *command, "--episodes", "1", "--eval-episodes", "0"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    (run_dir,) = tmp_path.glob("*/")
    assert (run_dir / "episodes.jsonl").read_text().count("\n") == 1
