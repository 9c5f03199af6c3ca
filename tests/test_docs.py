"""The documentation as a newcomer meets it: a short README whose links resolve, whose install
line is the one CI uses, whose quickstart runs command by command, and a docs site that builds
with `mkdocs build --strict` (a broken link or a missing page fails it)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from test_run_command import _session_processes, wait_until_serving
from test_session import pick_mavlink_instances, ports_released

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MAX_README_LINES = 200


def _section(markdown: str, title: str) -> str:
    """The text of the `## title` section (up to the next `## ` heading)."""
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", markdown, re.S | re.M)
    assert match, f"README has no '## {title}' section"
    return match.group(1)


def _code_blocks(markdown: str, language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```", markdown, re.S | re.M)


def _readme_install_line() -> str:
    block = _code_blocks(_section(README.read_text(), "Install"), "sh")[0]
    return block.strip().splitlines()[0]


def _mkdocs_build(config: Path, site: Path) -> subprocess.CompletedProcess:
    for module in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python"):
        pytest.importorskip(module, reason=f"{module} is not installed (pip install -e '.[test]' brings it)")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(site)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=280)


def test_docs_site_builds_strictly(tmp_path: Path) -> None:
    result = _mkdocs_build(ROOT / "mkdocs.yml", tmp_path / "site")
    assert result.returncode == 0, result.stdout + result.stderr
    # The generated scenario manuals hold every shipped scenario; the API pages their docstrings.
    manuals = (tmp_path / "site" / "scenario-manuals" / "index.html").read_text()
    for world in sorted((ROOT / "worlds").glob("*.yaml")):
        assert f"worlds/{world.name}" in manuals, world.name
    assert "Observation (per drone" in manuals
    assert 'id="sitl_bridge.envs.make_env"' in (tmp_path / "site" / "api" / "envs" / "index.html").read_text()
    assert not (tmp_path / "site" / "results").exists(), "docs/results must stay out of the site"


def test_strict_build_fails_on_a_broken_link_and_a_missing_page(tmp_path: Path) -> None:
    """The same configuration over a copy of the pages with one link broken and one page gone."""
    docs = tmp_path / "docs"
    shutil.copytree(ROOT / "docs", docs, ignore=shutil.ignore_patterns("results", "hooks"))
    (docs / "benchmarks.md").unlink()
    index = docs / "index.md"
    index.write_text(index.read_text() + "\n[gone](no-such-page.md)\n")
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    config["docs_dir"] = str(docs)
    config["hooks"] = [str(ROOT / "docs" / "hooks" / "scenario_manuals.py")]
    (mkdocstrings,) = [p["mkdocstrings"] for p in config["plugins"] if isinstance(p, dict) and "mkdocstrings" in p]
    mkdocstrings["handlers"]["python"]["paths"] = [str(ROOT)]
    (tmp_path / "mkdocs.yml").write_text(yaml.safe_dump(config))
    result = _mkdocs_build(tmp_path / "mkdocs.yml", tmp_path / "site")
    output = result.stdout + result.stderr
    assert result.returncode != 0, output
    assert "no-such-page.md" in output and "benchmarks.md" in output, output


def test_readme_is_short() -> None:
    lines = len(README.read_text().splitlines())
    assert lines <= MAX_README_LINES, f"README.md has {lines} lines; the rest belongs on the docs site (docs/)"


def test_readme_relative_links_resolve() -> None:
    targets = re.findall(r"\]\(([^)\s]+)\)", README.read_text())
    relative = [t for t in targets if not re.match(r"[a-z]+:", t) and not t.startswith("#")]
    assert relative, "README links to no docs page"
    missing = [t for t in relative if not (ROOT / t.split("#", 1)[0]).exists()]
    assert not missing, f"README links to missing files: {missing}"


def test_readme_install_line_is_the_ci_install_line() -> None:
    line = _readme_install_line()
    assert 'pip install -e ".[test]"' in line, line
    ci_installs = [entry.strip() for entry in (ROOT / ".ci" / "run").read_text().splitlines()
                   if "pip install" in entry and "-e" in entry.split()]
    assert ci_installs == [line], f".ci/run installs with {ci_installs}, the README with {line!r}"


def _is_server(command: str) -> bool:
    """`sitl-bridge run` without anything that ends it: it serves until Ctrl-C."""
    words = command.split()
    return words[:2] == ["sitl-bridge", "run"] and not {"--demo", "--duration", "--policy"} & set(words)


def _run_quickstart_command(command: str, cwd: Path, env: dict[str, str]) -> str:
    """Run one README command in bash (`sitl-bridge` is this checkout's `python -m sitl_bridge`);
    a `run` gets a free vehicle instance of its own and must leave no process or port behind."""
    instance = None
    if command.startswith("sitl-bridge run"):
        instance = pick_mavlink_instances(1)
        command += f" --instance-base {instance}"
    script = 'sitl-bridge() { "$QUICKSTART_PYTHON" -m sitl_bridge "$@"; }\n' + command
    process = subprocess.Popen(["bash", "-c", script], cwd=cwd, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        if _is_server(command):
            lines = wait_until_serving(process, timeout_s=60)
            output = "".join(lines)
            assert lines and lines[-1].startswith("t="), f"{command}: simulated time never advanced\n{output}"
            os.killpg(process.pid, signal.SIGINT)  # Ctrl-C: to the whole group, as a terminal sends it
            rest, _ = process.communicate(timeout=30)
            output += rest
            assert process.returncode in (130, -signal.SIGINT), f"{command}: exit {process.returncode}\n{output}"
        else:
            output, _ = process.communicate(timeout=180)
            assert process.returncode == 0, f"{command}: exit {process.returncode}\n{output}"
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    deadline = time.monotonic() + 10
    while _session_processes(process.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _session_processes(process.pid), f"{command}: left processes behind"
    if instance is not None:
        assert ports_released(instance), f"{command}: left ports of instance {instance} open"
    return output


@pytest.mark.timeout(420)
def test_every_quickstart_command_runs(tmp_path: Path) -> None:
    """Each shell line and Python block of the README's quickstart, in order, in a fresh folder
    that has the shipped `worlds/` (as a clone's root has)."""
    quickstart = _section(README.read_text(), "Quickstart")
    (tmp_path / "worlds").symlink_to(ROOT / "worlds")
    env = dict(os.environ, QUICKSTART_PYTHON=sys.executable, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
    steps = [("python", block) for block in _code_blocks(quickstart, "python")]
    order = {block: quickstart.index(block) for _, block in steps}
    for block in _code_blocks(quickstart, "sh"):
        for line in block.strip().splitlines():
            steps.append(("sh", line))
            order[line] = quickstart.index(line)
    steps.sort(key=lambda step: order[step[1]])
    assert [kind for kind, _ in steps].count("sh") >= 5, steps

    for kind, text in steps:
        if kind == "python":
            result = subprocess.run([sys.executable, "-c", text], cwd=tmp_path, env=env,
                                    capture_output=True, text=True, timeout=120)
            assert result.returncode == 0, f"quickstart Python block failed:\n{text}\n{result.stderr}"
        else:
            _run_quickstart_command(text, tmp_path, env)
    (run_dir,) = (tmp_path / "runs").glob("obstacle__o__0__*")
    assert (run_dir / "learning_curves.png").stat().st_size > 0
