"""bench/evidence.py: each task's runs go to a folder named by its source's sha256, with the
campaign's budget and arms; the report pools every committed run by augmentation."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))
import evidence  # noqa: E402


def test_sweep_runs_go_to_the_sources_folder(monkeypatch):
    info = SimpleNamespace(sha256="0123abcd" + "f" * 56)
    monkeypatch.setattr(
        "hipode_pipeline.sweep.plan.ensure_source", lambda *args, **kwargs: (None, info)
    )
    args = evidence.main_parser().parse_args(["sweep", "walker2d-m-r", "--learner", "iql"])
    command = evidence.sweep(args)
    out = command[command.index("--out") + 1]
    assert out == str(Path("bench/evidence/runs/walker2d-m-r-0123abcd"))
    assert command[command.index("--steps") + 1] == "200000"
    assert command[command.index("--learners") + 1] == "iql"
    assert "--model-rollouts" in command and "--report-only" not in command
    assert command[command.index("--seeds-per-process") + 1] == "1"
    again = evidence.main_parser().parse_args(["sweep", "walker2d-m-r", "--report-only"])
    assert evidence.sweep(again)[-1] == "--report-only"
    fewer = evidence.main_parser().parse_args(
        ["sweep", "walker2d-m-r", "--artifact-seeds", "", "--no-model-rollouts"]
    )
    command = evidence.sweep(fewer)
    assert "--model-rollouts" not in command
    assert command[command.index("--artifact-seeds") + 1] == ""


def test_report_pools_by_augmentation():
    command = evidence.report(evidence.main_parser().parse_args(["report"]))
    assert command[:2] == ["report", str(Path("bench/evidence/runs"))]
    assert command[command.index("--by") + 1] == "task,learner,augmentation"
    assert command[command.index("--compare") + 1] == "augmentation=none"
    assert command[command.index("--out") + 1] == str(Path("bench/evidence/report"))


def test_report_by_source_keeps_sources_apart():
    args = evidence.main_parser().parse_args(["report", "--by-source"])
    command = evidence.report(args)
    assert command[command.index("--by") + 1] == "task,learner,augmentation,source_sha256"
    assert command[command.index("--out") + 1] == str(Path("bench/evidence/report/by-source"))


def test_report_by_stage_one_seed_splits_each_source_by_artifact():
    args = evidence.main_parser().parse_args(["report", "--by-stage-one-seed"])
    command = evidence.report(args)
    expected = "task,learner,augmentation,source_sha256,artifact_seed"
    assert command[command.index("--by") + 1] == expected
    out = command[command.index("--out") + 1]
    assert out == str(Path("bench/evidence/report/by-stage-one-seed"))
