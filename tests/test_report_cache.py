"""The report's caches are keyed on what a scenario says, not on how its file is written."""

from pathlib import Path

from sitl_bridge.rl.experiments.report_cache import world_digest

ROOT = Path(__file__).resolve().parent.parent


def test_a_comment_edit_keeps_the_digest_and_a_value_edit_changes_it(tmp_path: Path) -> None:
    original = (ROOT / "worlds" / "obstacle.yaml").read_text()
    commented = tmp_path / "commented.yaml"
    commented.write_text("# a note a reader added\n" + original.replace("\n", "  # why\n", 3))
    assert world_digest(commented) == world_digest(ROOT / "worlds" / "obstacle.yaml")
    changed = tmp_path / "changed.yaml"
    changed.write_text(original + "extra_value: 1\n")
    assert world_digest(changed) != world_digest(ROOT / "worlds" / "obstacle.yaml")


def test_the_committed_caches_match_the_shipped_scenarios() -> None:
    """Every world digest in the committed caches of the thesis and generalization reports is
    the digest of a scenario in the repository, so rebuilding those reports from the committed
    runs flies nothing again."""
    import json

    digests = {world_digest(p) for folder in ("worlds", "experiments") for p in (ROOT / folder).rglob("*.yaml")}
    reports = [ROOT / "docs" / "results", ROOT / "docs" / "results" / "generalization"]
    caches = [p for report in reports for kind in ("backends", "rules", "trees") for p in (report / kind).glob("*.json")]
    assert caches
    for cache in caches:
        key = json.loads(cache.read_text())["key"]
        worlds = [key["world"]] if "world" in key else list(key.get("worlds", {}).values())
        assert worlds and set(worlds) <= digests, cache
