"""The `hipode` entry point asks OpenMP for passive waiting before anything imports torch."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import pytest

# Run in the child before the entry point: records the environment at the first import of
# torch and of the CLI module, and writes it to $WATCH_OUT when the process exits.
WATCH = """
import atexit, json, os, sys
seen = {}
class Watch:
    def find_spec(self, name, path=None, target=None):
        if name in ("torch", "hipode_pipeline.cli") and name not in seen:
            seen[name] = [os.environ.get("OMP_WAIT_POLICY"), "torch" in sys.modules]
sys.meta_path.insert(0, Watch())
atexit.register(lambda: open(os.environ["WATCH_OUT"], "w").write(json.dumps(seen)))
"""
CONSOLE_SCRIPT = Path(sys.executable).with_name("hipode")


def _watched_run(launch: str, tmp_path: Path, policy: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if policy is not None:
        env["OMP_WAIT_POLICY"] = policy
    env["WATCH_OUT"] = str(tmp_path / "seen.json")
    code = WATCH + "sys.argv = ['hipode', 'tasks', '--json']\n" + launch
    done = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "hopper-m-r" in {task["task"] for task in json.loads(done.stdout)}
    return json.loads((tmp_path / "seen.json").read_text())


def test_console_script_points_at_the_entry_point():
    (script,) = entry_points(group="console_scripts", name="hipode")
    assert script.value == "hipode_pipeline.__main__:main"


@pytest.mark.skipif(
    not CONSOLE_SCRIPT.exists(), reason="the hipode console script is not installed"
)
def test_installed_console_script_sets_passive_waiting_before_torch_loads(tmp_path):
    launch = f"import runpy; runpy.run_path({str(CONSOLE_SCRIPT)!r}, run_name='__main__')\n"
    seen = _watched_run(launch, tmp_path, policy=None)
    # the CLI (which imports torch) loads only after the policy is set
    assert seen["hipode_pipeline.cli"] == ["PASSIVE", False]
    assert seen["torch"][0] == "PASSIVE"


def test_python_dash_m_keeps_the_users_policy(tmp_path):
    launch = "import runpy; runpy.run_module('hipode_pipeline', run_name='__main__')\n"
    seen = _watched_run(launch, tmp_path, policy="ACTIVE")
    assert seen["hipode_pipeline.cli"] == ["ACTIVE", False]
    assert seen["torch"][0] == "ACTIVE"
