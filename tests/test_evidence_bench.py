"""bench/evidence.py: each task's runs go to a folder named by its source's sha256, with the
campaign's budget and arms; the report pools every committed run by augmentation."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))
import evidence  # noqa: E402
import evidence_tables  # noqa: E402


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


REPO = BENCH.parent


def regenerate(text, runs=REPO / evidence.RUNS):
    return evidence_tables.regenerate(
        text, Path("doc.md"), REPO / evidence.REPORT, runs, evidence.CPU_STEPS
    )


def test_the_docs_tables_are_the_committed_reports_and_runs():
    doc = REPO / evidence.DOC
    text = doc.read_text()
    assert text.count("<!-- evidence-rows:") >= 15
    _, changed = regenerate(text)
    assert changed == [], "run `python bench/evidence.py tables`: " + "; ".join(changed)


def test_marked_rows_are_replaced_from_the_report_and_the_rest_kept():
    report = json.loads((REPO / evidence.REPORT / "report.json").read_text())
    group = next(
        g
        for g in report["groups"]
        if (g["learner"], g["task"], g["augmentation"]) == ("td3bc", "hopper-m-r", "none")
    )
    stale = "\n".join(
        [
            "before",
            "<!-- evidence-rows: groups report=pooled learner=td3bc task=hopper-m-r -->",
            "| augmentation | task | runs | last | iqm | last 3 | curve |",
            "|---|---|---|---|---|---|---|",
            "| none | hopper-m-r | 1 (1) | 0.0 [0.0, 0.0] | x | x | x |",
            "after",
        ]
    )
    text, changed = regenerate(stale)
    lines = text.split("\n")
    assert lines[:4] == stale.split("\n")[:4] and lines[-1] == "after"
    assert changed == ["doc.md:2 " + stale.split("\n")[1]]
    rows = [line for line in lines if line.startswith("| none")]
    last = group["measures"]["last"]
    assert rows[0].startswith(f"| none | hopper-m-r | {group['n_runs']} (")
    assert f"| {last['mean']:.1f} [{last['mean_ci'][0]:.1f}, {last['mean_ci'][1]:.1f}] |" in rows[0]
    assert regenerate(text)[1] == []  # regenerated rows are what the next check expects


def write_scores(run_dir, steps, curve, speed=100.0):
    run_dir.mkdir(parents=True)
    evaluations = [{"step": 5000 * (i + 1), "score_mean": s} for i, s in enumerate(curve)]
    scores = {"steps": steps, "evaluations": evaluations, "updates_per_second": speed}
    (run_dir / "scores.json").write_text(json.dumps(scores))


def test_run_rows_list_finished_runs_by_seed_number(tmp_path):
    budget = evidence.CPU_STEPS["iql"]
    arms = tmp_path / "walker2d-m-r-0123abcd" / "walker2d-m-r"
    write_scores(arms / "hipode" / "iql-seed10", budget, [1.0, 2.0, 6.0], speed=90)
    write_scores(arms / "hipode" / "iql-seed2", budget, [3.0, 3.0])
    write_scores(arms / "hipode" / "iql-seed3", budget - 5000, [9.0])  # unfinished
    write_scores(arms / "hipode" / "iql-seed02", budget, [7.0])  # not a name the sweep writes
    write_scores(arms / "eta0" / "iql-seed2", budget, [4.0])
    write_scores(arms / "eta0" / "td3bc-seed2", evidence.CPU_STEPS["td3bc"], [5.0])
    marker = "<!-- evidence-rows: runs folder=walker2d-m-r-0123abcd learner=iql -->"
    text, changed = regenerate(
        f"{marker}\n| arm | runs | updates/s |\n| --- | --- | --- |", tmp_path
    )
    assert text.split("\n")[3:] == [
        "| eta0 | 2: 4.0 / 4.0 / 4.0 | 100 |",
        "| hipode | 2: 3.0 / 3.0 / 3.0; 10: 6.0 / 3.0 / 3.0 | 100, 90 |",
    ]


@pytest.mark.parametrize(
    ("marker", "message"),
    [
        ("<!-- evidence-rows: groups report=pooled -->", "expected learner=<name>"),
        ("<!-- evidence-rows: groups report=latest learner=td3bc -->", "report: expected one of"),
        ("<!-- evidence-rows: plots report=pooled learner=td3bc -->", "expected a kind in"),
        ("<!-- evidence-rows: groups report=pooled learner=sac -->", "no rows for"),
        ("<!-- evidence-rows: runs folder=ant-m-r-00000000 learner=iql -->", "to exist"),
        ("<!-- evidence-rows: groups report = pooled -->", "malformed marker"),
    ],
)
def test_a_wrong_marker_is_named_with_its_line(marker, message):
    with pytest.raises(evidence_tables.TableError, match=message) as error:
        regenerate(f"text\n{marker}\n| a |\n|---|\n| row |")
    assert str(error.value).startswith("doc.md:2: ")
