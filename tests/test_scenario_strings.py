"""Strings in a scenario are bounded per field and read through libyaml: a 10 MB world name is a
one-line error in about a second, and every configuration error is one line whatever the file
holds (a YAML key may contain a line break)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from sitl_bridge import errors
from sitl_bridge.errors import NAME_MAX_CHARS, TEXT_MAX_CHARS, ConfigError
from sitl_bridge.world.loader import load_world

WORLDS = Path(__file__).resolve().parent.parent / "worlds"


def _world_file(tmp_path: Path, **world_fields) -> Path:
    data = yaml.safe_load((WORLDS / "empty.yaml").read_text())
    data["world"].update(world_fields)
    path = tmp_path / "strings.yaml"
    path.write_text(yaml.safe_dump(data, width=1 << 30))
    return path


def test_yaml_goes_through_libyaml_where_pyyaml_has_it() -> None:
    expected = yaml.CSafeLoader if yaml.__with_libyaml__ else yaml.SafeLoader
    assert errors._SafeLoader is expected


def test_a_ten_megabyte_world_name_is_refused_in_one_line_within_seconds(tmp_path: Path) -> None:
    path = _world_file(tmp_path, name="n" * 10_000_000)
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "sitl_bridge", "worlds", "check", str(path)],
                            capture_output=True, text=True, timeout=120)
    elapsed = time.monotonic() - started
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and len(result.stderr) < 400, result.stderr[:400]
    assert f"world.name: expected a string of at most {NAME_MAX_CHARS} characters, got 10000000" in result.stderr
    assert len(result.stdout) < 400
    assert elapsed < 10.0, f"took {elapsed:.1f} s"   # ~1 s with the interpreter's start; 15-47 s before


@pytest.mark.parametrize(("field", "limit"), [("name", NAME_MAX_CHARS), ("description", TEXT_MAX_CHARS)])
def test_strings_are_bounded_per_field(tmp_path: Path, field: str, limit: int) -> None:
    assert getattr(load_world(_world_file(tmp_path, **{field: "x" * limit})), field) == "x" * limit
    with pytest.raises(ConfigError, match=rf"world\.{field}: expected a string of at most {limit} characters"):
        load_world(_world_file(tmp_path, **{field: "x" * (limit + 1)}))


def test_a_huge_unknown_key_is_named_briefly(tmp_path: Path) -> None:
    path = _world_file(tmp_path, **{"k" * 1_000_000: 1})
    with pytest.raises(ConfigError) as caught:
        load_world(path)
    assert "unknown key" in str(caught.value) and len(str(caught.value)) < 1000


_BREAKS = st.sampled_from(["\n", "\r", "\r\n", "\v", "\f", "\x1c", "\x85", "\u2028", "\u2029"])


@settings(max_examples=40, deadline=None)
@given(before=st.text(max_size=8), brk=_BREAKS, after=st.text(max_size=8))
def test_every_config_error_is_one_line(tmp_path_factory, before: str, brk: str, after: str) -> None:
    key = f"k{before}{brk}{after}"
    path = tmp_path_factory.mktemp("breaks") / "w.yaml"
    data = yaml.safe_load((WORLDS / "empty.yaml").read_text())
    data["world"][key] = 1
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as caught:
        load_world(path)
    assert len(str(caught.value).splitlines()) == 1, repr(str(caught.value))
    assert len(str(ConfigError(f"a{brk}b")).splitlines()) == 1

