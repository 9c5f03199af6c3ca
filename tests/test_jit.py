"""`sitl_bridge.jit`: a kernel's disk cache follows every source it uses, not only its own file
(numba alone would keep a stale compiled kernel after an edit of a helper in another module)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

HELPER = '''
from sitl_bridge.jit import dual

@dual
def scale(x):
    return x * {factor}
'''

KERNEL = '''
import helper
from sitl_bridge.jit import kernel

@kernel(helper)
def twice_scaled(x):
    return 2.0 * helper.scale(x)
'''


def _run(tmp_path: Path) -> str:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(Path(__file__).resolve().parents[1])])}
    env.pop("NUMBA_CACHE_DIR", None)  # the cache next to the sources, in tmp_path
    out = subprocess.run([sys.executable, "-c", "import user; print(user.twice_scaled(1.5))"], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=120, check=True)
    return out.stdout.strip()


def test_a_kernel_recompiles_when_a_module_it_uses_changes(tmp_path: Path) -> None:
    (tmp_path / "helper.py").write_text(HELPER.format(factor=3.0))
    (tmp_path / "user.py").write_text(KERNEL)
    assert _run(tmp_path) == "9.0"
    assert list((tmp_path / "__pycache__").glob("user.twice_scaled*.nbi")), "the kernel was not cached"
    assert _run(tmp_path) == "9.0"  # from the cache
    (tmp_path / "helper.py").write_text(HELPER.format(factor=5.0))  # only the helper changes
    assert _run(tmp_path) == "15.0"


def test_dual_functions_stay_plain_python() -> None:
    from sitl_bridge.frames import quat_rotate_t, wrap_pi

    assert type(wrap_pi).__name__ == "function" and type(quat_rotate_t).__name__ == "function"
    assert quat_rotate_t((1.0, 0.0, 0.0, 0.0), (1.0, 2.0, 3.0)) == (1.0, 2.0, 3.0)


def _run_with_stderr(tmp_path: Path) -> str:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(Path(__file__).resolve().parents[1])])}
    env.pop("NUMBA_CACHE_DIR", None)
    out = subprocess.run([sys.executable, "-c", "import user; print(user.twice_scaled(1.5))"], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=120, check=True)
    return out.stderr


def test_a_real_compile_says_so_in_one_line_and_a_warm_run_says_nothing(tmp_path: Path) -> None:
    from sitl_bridge.compile_notice import NOTICE

    (tmp_path / "helper.py").write_text(HELPER.format(factor=3.0))
    (tmp_path / "user.py").write_text(KERNEL)
    assert _run_with_stderr(tmp_path).splitlines() == [NOTICE]  # cold cache: compiles
    assert _run_with_stderr(tmp_path) == ""  # warm: loads the cached kernel
