"""The package's import contracts (pyproject.toml, [tool.importlinter]): the layering of the
README's layout, no cycles between sibling modules, the simulators' and the BNN study's
inner layering, and the few modules that may import highway-env."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_imports_point_one_way():
    exe = shutil.which("lint-imports") or str(Path(sys.executable).with_name("lint-imports"))
    if not Path(exe).exists():
        pytest.fail("import-linter is a dev dependency: install the package with [dev]")
    proc = subprocess.run([exe], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:]
    # Every contract of pyproject.toml was checked, none skipped.
    n = (ROOT / "pyproject.toml").read_text().count("[[tool.importlinter.contracts]]")
    assert n >= 5 and f"{n} kept, 0 broken" in proc.stdout
