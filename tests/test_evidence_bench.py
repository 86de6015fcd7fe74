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
    # IQL's budget on hopper-m-r is its own; TD3+BC's there is the learner's
    for argv, steps in ((["--learner", "iql"], "500000"), ([], "200000")):
        hopper = evidence.sweep(evidence.main_parser().parse_args(["sweep", "hopper-m-r", *argv]))
        assert hopper[hopper.index("--steps") + 1] == steps
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


def test_report_versus_rollouts_compares_each_arm_with_the_rollouts():
    for argv, out in (
        ([], "bench/evidence/report/versus-rollouts"),
        (["--by-source"], "bench/evidence/report/versus-rollouts/by-source"),
        (["--by-stage-one-seed"], "bench/evidence/report/versus-rollouts/by-stage-one-seed"),
    ):
        args = evidence.main_parser().parse_args(["report", "--versus-rollouts", *argv])
        command = evidence.report(args)
        assert command[command.index("--compare") + 1] == "augmentation=model-rollouts"
        assert command[command.index("--out") + 1] == str(Path(out))


def test_report_design_takes_the_design_runs_alone(monkeypatch):
    monkeypatch.chdir(REPO)
    folders = ["bench/evidence/runs/a/run-1", "bench/evidence/runs/b/run-2"]
    monkeypatch.setattr(evidence, "design_folders", lambda: folders)
    for argv, out in (
        ([], "bench/evidence/report/design"),
        (["--versus-rollouts"], "bench/evidence/report/versus-rollouts/design"),
    ):
        command = evidence.report(evidence.main_parser().parse_args(["report", "--design", *argv]))
        assert command[1 : command.index("--by")] == folders
        assert command[command.index("--out") + 1] == str(Path(out))
    with pytest.raises(SystemExit):  # one grouping at a time
        evidence.main_parser().parse_args(["report", "--design", "--by-source"])


def design_run(source, augmentation, stage_one, seed, learner="iql", steps=200_000):
    from hipode_pipeline.report import Run

    keys = {
        "source_sha256": source,
        "learner": learner,
        "task": "walker2d-m-r",
        "steps": steps,
        "augmentation": augmentation,
        "artifact_seed": stage_one,
        "seed": seed,
    }
    return Run(Path(f"{source}/{augmentation}-{stage_one}/{learner}-seed{seed}"), keys, [], [])


def test_the_design_takes_full_grids_and_leaves_sources_stopped_early():
    import evidence_design

    full = [design_run("full", "none", None, seed) for seed in range(5)]
    full += [design_run("full", "hipode", a, seed) for a in (0, 1, 2) for seed in range(5)]
    # the rollouts hold one full stage-one seed: below the design's two
    rollouts = [design_run("full", "model-rollouts", 0, seed) for seed in range(5)]
    rollouts += [design_run("full", "model-rollouts", 1, seed) for seed in range(4)]
    # another learner and budget on the same source are cells of their own
    other = [design_run("full", "none", None, seed, learner="td3bc") for seed in range(5)]
    diagnostic = [design_run("full", "hipode", 3, seed, steps=500_000) for seed in range(5)]
    early = [design_run("early", "none", None, seed) for seed in range(4)]
    early += [design_run("early", "hipode", a, seed) for a in (0, 1) for seed in range(5)]
    runs = full + rollouts + other + diagnostic + early
    chosen = evidence_design.design_runs(runs, evidence.budget)
    # the whole grid of the full arms, η = 0 of both learners, nothing else, in the order given
    assert chosen == full + other
    full_rollouts = rollouts + [design_run("full", "model-rollouts", 1, 4)]
    assert evidence_design.design_runs(full + full_rollouts, evidence.budget) == (
        full + full_rollouts
    )


REPO = BENCH.parent


def regenerate(text, reports=evidence.REPORT, runs=evidence.RUNS):
    """evidence_tables.regenerate as `bench/evidence.py tables` calls it: paths as the reports
    name them, relative to the working directory."""
    return evidence_tables.regenerate(text, Path("doc.md"), reports, runs, evidence.budget)


def test_the_docs_tables_are_the_reports_and_runs_of_the_checkout(monkeypatch):
    monkeypatch.chdir(REPO)
    text = evidence.DOC.read_text()
    assert text.count("<!-- evidence-rows:") >= 15
    _, changed = regenerate(text)
    assert changed == [], "run `python bench/evidence.py tables`: " + "; ".join(
        where for where, _, _ in changed
    )


def test_marked_rows_are_replaced_from_the_report_and_the_rest_kept(monkeypatch):
    monkeypatch.chdir(REPO)
    report = json.loads((evidence.REPORT / "report.json").read_text())
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
    assert [where for where, _, _ in changed] == ["doc.md:2 " + stale.split("\n")[1]]
    assert changed[0][1] == [stale.split("\n")[4]]
    rows = [line for line in lines if line.startswith("| none")]
    last = group["measures"]["last"]
    assert rows[0].startswith(f"| none | hopper-m-r | {group['n_runs']} (")
    assert f"| {last['mean']:.1f} [{last['mean_ci'][0]:.1f}, {last['mean_ci'][1]:.1f}] |" in rows[0]
    assert regenerate(text)[1] == []  # regenerated rows are what the next check expects


def test_an_augmentation_keeps_one_arms_rows(monkeypatch):
    monkeypatch.chdir(REPO)
    header = "| a | b | c | d | e | f | g |\n|---|---|---|---|---|---|---|\n| row |"
    rows = {}
    for arm in ("", " augmentation=hipode"):
        marker = f"<!-- evidence-rows: comparisons report=pooled learner=td3bc{arm} -->"
        text, _ = regenerate(f"{marker}\n{header}")
        rows[arm] = [line for line in text.split("\n")[3:] if line.startswith("|")]
    assert {line.split(" | ")[0] for line in rows[""]} == {"| hipode", "| model-rollouts"}
    assert rows[" augmentation=hipode"] == [r for r in rows[""] if r.startswith("| hipode")]


def test_a_report_of_other_runs_than_the_pooled_one_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    pooled = json.loads((evidence.REPORT / "report.json").read_text())
    (tmp_path / "report.json").write_text(json.dumps(pooled))
    stale = json.loads(json.dumps(pooled))
    stale["groups"][0]["runs"] = stale["groups"][0]["runs"][:-1]  # written before a run finished
    (tmp_path / "versus-rollouts").mkdir()
    (tmp_path / "versus-rollouts" / "report.json").write_text(json.dumps(stale))
    marker = "<!-- evidence-rows: across report=versus-rollouts learner=td3bc -->"
    table = f"{marker}\n| a | b | c | d | e | f |\n|---|---|---|---|---|---|\n| row |"
    with pytest.raises(evidence_tables.TableError, match="other runs than the pooled") as error:
        regenerate(table, reports=tmp_path)
    assert "python bench/evidence.py report --versus-rollouts` again" in str(error.value)
    (tmp_path / "versus-rollouts" / "report.json").write_text(json.dumps(pooled))
    assert regenerate(table, reports=tmp_path)[1]  # the same runs: its rows replace the stale one
    # a design report holds the design's share of the pooled runs: every pooled run is too many
    (tmp_path / "design").mkdir()
    (tmp_path / "design" / "report.json").write_text(json.dumps(pooled))
    design = table.replace("report=versus-rollouts", "report=design")
    with pytest.raises(evidence_tables.TableError, match="design picks from") as error:
        regenerate(design, reports=tmp_path)
    assert "python bench/evidence.py report --design` again" in str(error.value)
    committed = evidence.REPORT / "design" / "report.json"
    (tmp_path / "design" / "report.json").write_text(committed.read_text())
    assert regenerate(design, reports=tmp_path)[1]


def write_scores(run_dir, steps, curve, speed=100.0):
    run_dir.mkdir(parents=True)
    evaluations = [{"step": 5000 * (i + 1), "score_mean": s} for i, s in enumerate(curve)]
    scores = {"steps": steps, "evaluations": evaluations, "updates_per_second": speed}
    (run_dir / "scores.json").write_text(json.dumps(scores))
    return run_dir.as_posix()


def test_run_rows_list_the_reported_finished_runs_by_seed_number(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    budget = evidence.CPU_STEPS["iql"]
    arms = Path("runs") / "walker2d-m-r-0123abcd" / "walker2d-m-r"
    reported = [
        write_scores(arms / "hipode" / "iql-seed10", budget, [1.0, 2.0, 6.0], speed=90),
        write_scores(arms / "hipode" / "iql-seed2", budget, [3.0, 3.0]),
        write_scores(arms / "eta0" / "iql-seed2", budget, [4.0]),
    ]
    write_scores(arms / "hipode" / "iql-seed3", budget - 5000, [9.0])  # unfinished
    write_scores(arms / "hipode" / "iql-seed02", budget, [7.0])  # not a name the sweep writes
    write_scores(arms / "eta0" / "td3bc-seed2", evidence.CPU_STEPS["td3bc"], [5.0])
    Path("report").mkdir()
    pooled = {"groups": [{"runs": reported[:2]}, {"runs": reported[2:]}]}
    (Path("report") / "report.json").write_text(json.dumps(pooled))
    marker = "<!-- evidence-rows: runs folder=walker2d-m-r-0123abcd learner=iql -->"
    table = f"{marker}\n| arm | runs | updates/s |\n| --- | --- | --- |"
    text, _ = regenerate(table, Path("report"), Path("runs"))
    assert text.split("\n")[3:] == [
        "| eta0 | 2: 4.0 / 4.0 / 4.0 | 100 |",
        "| hipode | 2: 3.0 / 3.0 / 3.0; 10: 6.0 / 3.0 / 3.0 | 100, 90 |",
    ]
    # a run that finished after the report was written: the tables wait for the report
    write_scores(arms / "eta0" / "iql-seed4", budget, [8.0])
    with pytest.raises(evidence_tables.TableError, match="finished after .*report.json"):
        regenerate(table, Path("report"), Path("runs"))


SHA = "0123abcd" + "0" * 56


def write_verify(folder, arm, error, within, novelty, artifact=None, source=SHA):
    checked = {
        "next_state_error_median_exact_rows": error,
        "next_state_error_median": error + 1.0,  # rows without exact ground truth: not shown
        "within_tolerance": within,
        "novelty_median": novelty,
    }
    report = {"artifact": artifact or f"runs/{arm}/artifact.hdf5", "source_sha256": source}
    (folder / arm).mkdir(parents=True, exist_ok=True)
    (folder / arm / "artifact.hdf5.verify.json").write_text(
        json.dumps(report | {"hipode": checked})
    )


def test_authenticity_rows_put_the_source_beside_each_artifact_and_its_check(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    results = Path("runs") / "hopper-m-r-0123abcd" / "report" / "td3bc"
    results.mkdir(parents=True)

    def arm(name, seed, reward, same, terminal, augment=None):
        synthetic = {
            "reward_mean": reward,
            "source_reward_mean_same_states": same,
            "terminal_fraction": terminal,
        }
        return {
            "name": name,
            "learner": "td3bc",
            "data": "merged",
            "augment": augment,
            "artifact": f"runs/{name}/artifact.hdf5",
            "stage_one_seed": seed,
            "synthetic": synthetic,
        }

    source_only = {"name": "eta0", "data": "source", "artifact": None, "synthetic": None}
    arms = [
        arm("model-rollouts-seed1", 1, 2.9, 2.8, 0.0061, {"method": "model-rollouts", "seed": 1}),
        {**source_only, "learner": "td3bc", "stage_one_seed": None},
        arm("hipode", 2, 3.2, 3.1, 0.0006),
        arm("artifact-seed1", 1, 3.0, 3.0, 0, {"seed": 1}),
        {**source_only, "learner": "iql"},
    ]
    trained = ["hipode", "artifact-seed1", "model-rollouts-seed1"]
    quality = {
        "command": "hipode sweep --tasks hopper-m-r --artifact-seed 2 --artifact-seeds 1",
        "arms": {"hopper-m-r": arms},
        "runs": [{"task": "hopper-m-r", "learner": "td3bc", "arm": name} for name in trained],
        "sources": {
            "hopper-m-r": {"sha256": SHA, "reward_mean": 2.881234, "terminal_fraction": 0.0061}
        },
    }

    def write_quality():
        (results / "quality.json").write_text(json.dumps(quality))

    write_quality()
    write_verify(results / "verify", "hipode", 0.00934, 0.9995, 0.2444)
    write_verify(results / "verify", "artifact-seed1", 0.0100, 1.0, 0.241)
    write_verify(results / "verify", "model-rollouts-seed1", 0.0069, 0.982, 0.262)
    marker = "<!-- evidence-rows: authenticity folder=hopper-m-r-0123abcd learner=td3bc -->"
    table = f"{marker}\n| arm | seed | reward | terminal | error | within | novelty |\n|---|"
    text, _ = regenerate(table, Path("report"), Path("runs"))
    assert text.split("\n")[3:] == [
        "| source |  | 2.881 | 0.61 % |  |  |  |",
        "| hipode | 2 | 3.200 (3.100) | 0.06 % | 0.0093 | 99.95 % | 0.244 |",
        "| hipode | 1 | 3.000 (3.000) | 0.00 % | 0.0100 | 100.00 % | 0.241 |",
        "| model-rollouts | 1 | 2.900 (2.800) | 0.61 % | 0.0069 | 98.20 % | 0.262 |",
    ]

    def refused(match):
        with pytest.raises(evidence_tables.TableError, match=match):
            regenerate(table, Path("report"), Path("runs"))

    # a verify report of another artifact or source is never quoted as the arm's
    write_verify(results / "verify", "hipode", 0.01, 1.0, 0.2, artifact="datasets/other.hdf5")
    refused("field artifact: expected 'runs/hipode/artifact.hdf5'")
    write_verify(results / "verify", "hipode", 0.01, 1.0, 0.2, source="ff" * 32)
    refused("field source_sha256")
    (results / "verify" / "hipode" / "artifact.hdf5.verify.json").unlink()
    refused("expected one .*hipode verify runs/hipode/artifact.hdf5")
    write_verify(results / "verify", "hipode", 0.01, 1.0, 0.2)
    # an arm a wider sweep planned but never built nor trained has nothing to describe
    before = regenerate(table, Path("report"), Path("runs"))[0]
    arms.append({**arm("model-rollouts-seed2", 2, 0, 0, 0), "synthetic": None})
    write_quality()
    assert regenerate(table, Path("report"), Path("runs"))[0] == before
    # an artifact arm with runs whose synthetic row is missing is refused, not left out
    arms[2]["synthetic"] = None
    write_quality()
    refused("arm hipode has no synthetic; .*--report-only`")
    quality["runs"].append(
        {"task": "hopper-m-r", "learner": "td3bc", "arm": "model-rollouts-seed2"}
    )
    arms[2]["synthetic"] = arms[0]["synthetic"]
    write_quality()
    refused("arm model-rollouts-seed2 has no synthetic")
    # and so are a report of another source and one from before sources were recorded
    quality["sources"]["hopper-m-r"]["sha256"] = "ffff" + "0" * 60
    write_quality()
    refused("sha256: expected 0123abcd…, found ffff0000…")
    del quality["sources"]
    write_quality()
    refused("no field sources.hopper-m-r; rewrite it on a machine that holds source 0123abcd")


@pytest.mark.parametrize(
    ("marker", "message"),
    [
        ("<!-- evidence-rows: groups report=pooled -->", "expected keys"),
        ("<!-- evidence-rows: groups report=pooled learner=td3bc tsak=x -->", "expected keys"),
        ("<!-- evidence-rows: groups report=latest learner=td3bc -->", "report: expected one of"),
        ("<!-- evidence-rows: plots report=pooled learner=td3bc -->", "expected a kind in"),
        ("<!-- evidence-rows: groups report=pooled learner=sac -->", "no rows for"),
        ("<!-- evidence-rows: runs folder=ant-m-r-00000000 learner=iql -->", "to exist"),
        ("<!-- evidence-rows: runs folder=hopper-m-r learner=iql -->", "<task>-<first 8"),
        ("<!-- evidence-rows: runs folder=hopper-m-r-7c80ddd9 learner=iql -->", "no rows for"),
        ("<!-- evidence-rows: runs folder=hopper-m-r-7c80ddd9 learner=sac -->", "a budget for"),
        ("<!-- evidence-rows: groups report = pooled -->", "malformed marker"),
    ],
)
def test_a_wrong_marker_is_named_with_its_line(marker, message, monkeypatch):
    monkeypatch.chdir(REPO)
    with pytest.raises(evidence_tables.TableError, match=message) as error:
        regenerate(f"text\n{marker}\n| a |\n|---|\n| row |")
    assert str(error.value).startswith("doc.md:2: ")


@pytest.mark.parametrize("below", ["\n| a |", "\n\n| a |\n|---|\n| row |", "\n| a |\n| b |"])
def test_a_marker_without_its_table_right_below_is_refused(below, monkeypatch):
    monkeypatch.chdir(REPO)
    marker = "<!-- evidence-rows: groups report=pooled learner=td3bc -->"
    with pytest.raises(evidence_tables.TableError, match="separator on the two lines"):
        regenerate(f"text\n{marker}{below}")


def test_sources_say_which_folders_this_cpu_can_extend(tmp_path):
    import evidence_sources

    this_cpu = "AMD EPYC (family 25, model 17, stepping 1)"

    def run(folder: str, arm: str, learner: str, steps: int, cpu: str | None):
        path = tmp_path / folder / "walker2d-m-r" / arm / f"{learner}-seed0"
        path.mkdir(parents=True)
        record = {
            "task": "walker2d-m-r",
            "learner": learner,
            "steps": steps,
            "data_identity": {"source_sha256": folder.split("-")[-1] + "0" * 56},
            **({} if cpu is None else {"cpu": cpu}),
        }
        (path / "scores.json").write_text(json.dumps(record))

    run("walker2d-m-r-aaaaaaaa", "eta0", "iql", 200_000, this_cpu)
    run("walker2d-m-r-aaaaaaaa", "hipode", "iql", 100_000, this_cpu)  # not at the budget
    run("walker2d-m-r-bbbbbbbb", "eta0", "td3bc", 200_000, "AMD EPYC")
    run("walker2d-m-r-cccccccc", "eta0", "td3bc", 200_000, "Intel(R) Xeon(R) Processor")
    run("walker2d-m-r-cccccccc", "hipode", "td3bc", 200_000, None)
    (tmp_path / "walker2d-m-r-dddddddd").mkdir()  # nothing finished: says nothing
    entries = evidence_sources.read_sources(tmp_path, evidence.budget, this_cpu)
    by_folder = {e["folder"]: e for e in entries}
    assert list(by_folder) == [
        "walker2d-m-r-aaaaaaaa",
        "walker2d-m-r-bbbbbbbb",
        "walker2d-m-r-cccccccc",
    ]
    same, brand, other = by_folder.values()
    assert same["match"] == evidence_sources.SAME and same["runs_at_budget"] == {"iql": 1}
    assert same["cpus"] == {this_cpu: 2} and same["source_sha256"].startswith("aaaaaaaa")
    assert brand["match"] == evidence_sources.BRAND_ONLY
    assert other["match"] == evidence_sources.OTHER
    assert other["cpus"] == {"Intel(R) Xeon(R) Processor": 1, "not recorded": 1}
    assert "walker2d-m-r-aaaaaaaa" in evidence_sources.extendable(entries, "walker2d-m-r")
    without_mine = [same_or_not for same_or_not in entries if same_or_not is not same]
    assert "may or may not" in evidence_sources.extendable(without_mine, "walker2d-m-r")
    assert "starts a folder" in evidence_sources.extendable([other], "walker2d-m-r")
    table = evidence_sources.markdown(entries, this_cpu)
    assert f"This machine: {this_cpu}" in table
    assert "| walker2d-m-r-bbbbbbbb | walker2d-m-r | AMD EPYC (1) | td3bc 1 |" in table
    # another generation of the same brand is another CPU
    assert evidence_sources.cpu_match("AMD EPYC (family 25, model 1, stepping 1)", this_cpu) == (
        evidence_sources.OTHER
    )
