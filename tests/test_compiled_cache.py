"""The compiled loops' disk cache runs the current code of every module a loop calls."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from harness.compiled import package_stamp

ROOT = Path(__file__).resolve().parents[1]

CALLER = """
import numba
from pkg.callee import value

@numba.njit(cache=True)
def read():
    return value()
"""

CALLEE = """
import numba

@numba.njit(cache=True)
def value():
    return {answer}
"""

RUN = """
import sys
from pathlib import Path
sys.path.insert(0, {root!r})
if {stamped}:
    from harness.compiled import stamp_by_package
    stamp_by_package(Path({pkg!r}))
sys.path.insert(0, {here!r})
from pkg.caller import read
print(read())
"""


def _answer(tmp: Path, stamped: bool) -> int:
    script = RUN.format(root=str(ROOT), pkg=str(tmp / "pkg"), here=str(tmp), stamped=stamped)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300
    )
    assert out.returncode == 0, out.stderr
    return int(out.stdout.split()[-1])


def _package(tmp: Path, answer: int) -> None:
    (tmp / "pkg").mkdir(exist_ok=True)
    (tmp / "pkg" / "__init__.py").write_text("")
    (tmp / "pkg" / "caller.py").write_text(CALLER)
    (tmp / "pkg" / "callee.py").write_text(textwrap.dedent(CALLEE.format(answer=answer)))


@pytest.mark.parametrize("stamped", [False, True], ids=["numba-alone", "stamped-by-package"])
def test_a_cached_loop_runs_the_current_code_of_the_function_it_calls(tmp_path, stamped):
    """numba alone keeps the callee a caller was compiled with (the hazard, shown here);
    stamped by package, the caller recompiles when the callee's module changes."""
    _package(tmp_path, 1)
    assert _answer(tmp_path, stamped) == 1
    _package(tmp_path, 2)  # only callee.py changes
    assert _answer(tmp_path, stamped) == (2 if stamped else 1)


def test_the_package_stamp_changes_with_any_module_and_only_with_content(tmp_path):
    _package(tmp_path, 1)
    first = package_stamp(tmp_path / "pkg")
    (tmp_path / "pkg" / "callee.py").write_text(CALLEE.format(answer=1))  # same bytes
    assert package_stamp(tmp_path / "pkg") == first
    _package(tmp_path, 3)
    assert package_stamp(tmp_path / "pkg") != first
