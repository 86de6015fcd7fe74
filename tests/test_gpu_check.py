"""bench/gpu_check.sh --dry-run: the GPU check's whole path (stage one, the speed probe of the
stacked update, K seeds trained) on CPU, tiny."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_gpu_check_dry_run_goes_end_to_end(tmp_path):
    summary = tmp_path / "summary.json"
    env = {**os.environ, "PYTHON": sys.executable}
    done = subprocess.run(
        [
            str(REPO / "bench" / "gpu_check.sh"),
            "--dry-run",
            "--seeds",
            "3",
            "--root",
            str(tmp_path / "datasets"),
            "--out",
            str(tmp_path / "runs"),
            "--json-out",
            str(summary),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "updates/s per seed" in done.stdout and "in all" in done.stdout
    result = json.loads(summary.read_text())
    assert result["dry_run"] and result["seeds"] == 3 and result["steps"] == 20
    assert set(result["probe_updates_per_s_per_seed"]) == {"fp32", "bf16"}
    runs = sorted((tmp_path / "runs" / "hopper-m-r").iterdir())
    assert [run.name[-5:] for run in runs] == ["seed0", "seed1", "seed2"]
    assert all((run / "scores.json").is_file() for run in runs)
    assert len(result["last_scores"]) == 3
