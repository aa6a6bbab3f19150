"""``python -m latentdrive`` behaves as the ``latentdrive`` console script."""

import subprocess
import sys


def run_module(*args, cwd):
    return subprocess.run([sys.executable, "-m", "latentdrive", *args], capture_output=True, text=True, cwd=cwd)


def test_scenarios_via_python_m(tmp_path):
    proc = run_module("scenarios", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "roundabout" in proc.stdout


def test_unknown_scenario_via_python_m_is_one_line_exit_2(tmp_path):
    proc = run_module("show", "nosuchscenario", "--out", "x.png", cwd=tmp_path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("latentdrive: error:") and "unknown scenario 'nosuchscenario'" in lines[0]
    assert not (tmp_path / "x.png").exists()
