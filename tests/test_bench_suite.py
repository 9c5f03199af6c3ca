"""`sitl-bridge bench --smoke --json`: the one-run bench writes every key (speed itself is
the bench's business, never a unit test's)."""

from __future__ import annotations

import json
import subprocess
import sys


def test_bench_smoke_json_has_every_key(tmp_path, monkeypatch) -> None:
    from sitl_bridge.bench.suite import KEYS

    monkeypatch.delenv("PX4_BIN", raising=False)
    out = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "-m", "sitl_bridge", "bench", "--smoke", "--json", str(out)],
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads(out.read_text())
    for key in KEYS:
        assert key in result, key
    assert result["px4"] == {"skipped": "PX4_BIN not set"}
    bare = result["physics"]["rtf"]["median"]
    assert bare > 0 and result["physics"]["fraction_of_bare"]["median"] == 1.0
    for key in ("direct", "direct_ground_truth", "batched", "stub", "train_steps_per_s"):
        entry = result[key]
        assert set(entry["rtf"]) == {"median", "min", "max"}, key
        assert entry["rtf"]["min"] <= entry["rtf"]["median"] <= entry["rtf"]["max"], key
        assert entry["fraction_of_bare"]["median"] == entry["rtf"]["median"] / entry["bare_rtf_adjacent"], key
    assert result["train_steps_per_s"]["updates"] > 0  # DQN updates were part of the timing
    assert set(result["reset_s"]) == {"direct", "stub"}
    assert result["parallel"]["speedup_2_over_1"] > 0
