"""The sweep engine (`hipode sweep`, and bench/quality.py, its thin caller) on tiny data: both
arms on the same seed and budget, the artifact built when missing, the report files,
resume/skip, several learners, and clear user errors (units of seeds: test_sweep_units.py)."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest
from test_merge import write_source, write_synthetic
from typer.testing import CliRunner

from hipode_pipeline.artifact import read_artifact, read_manifest
from hipode_pipeline.cli import app
from hipode_pipeline.contract import ArtifactSettings, default_artifact_path, table_settings
from hipode_pipeline.data.load import load_source
from hipode_pipeline.errors import DataFormatError, HipodeError
from hipode_pipeline.sweep import driver, engines, plan, report
from hipode_pipeline.sweep.worker import RunSpec
from hipode_pipeline.tasks import get_task

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))
import quality  # noqa: E402

TINY = ["--tasks", "hopper-m-r", "--seeds", "0", "--eval-every", "10", "--eval-episodes", "2"]


def sweep_args(tmp_path, source, *extra):
    args = [*TINY, "--source", str(source), "--profile", "quick", "--engine", "local"]
    args += ["--out", str(tmp_path / "out"), "--results", str(tmp_path / "results"), "--json"]
    return [*args, *extra]


def invoke(tmp_path, source, *extra):
    """`hipode sweep` through the package's command line."""
    return CliRunner().invoke(app, ["sweep", *sweep_args(tmp_path, source, *extra)])


def test_sweep_runs_both_arms_reports_and_resumes(tmp_path, dataset_root):
    source = write_source(tmp_path / "source.hdf5", n_episodes=8)
    ablations = ["--lam", "1", "--union", "--artifact-seeds", "3"]
    first = invoke(tmp_path, source, "--steps", "20", *ablations)
    assert first.exit_code == 0, first.output
    result = json.loads(first.stdout)
    runs = {r["arm"]: r for r in result["runs"]}
    assert set(runs) == {"eta0", "hipode", "lam1", "artifact-seed3", "mixing-union"}
    assert all(r["status"] == "trained" and r["learner"] == "td3bc" for r in runs.values())
    # every run in its own folder, named by the sweep
    out = tmp_path / "out" / "hopper-m-r"
    for arm, run in runs.items():
        assert Path(run["run_dir"]) == out / arm / "td3bc-seed0"
        assert (out / arm / "td3bc-seed0" / "scores.json").is_file()
    # the ablation arm got its own artifact, built with its λ
    ablation = read_manifest(out / "lam1" / "artifact.hdf5")
    assert ablation["hyper_parameters"]["lam"] == 1.0 and ablation["seeds"]["seed"] == 0
    # the control arm: the table's settings, another stage-one seed
    control = read_manifest(out / "artifact-seed3" / "artifact.hdf5")
    assert control["seeds"]["seed"] == 3 and control["hyper_parameters"]["lam"] == 0.2
    # each arm's synthetic data is described against the real rewards at the same states
    described = {a["name"]: a for a in result["arms"]["hopper-m-r"]}
    lam1 = read_artifact(out / "lam1" / "artifact.hdf5")
    real, info = load_source(str(source))
    stats = described["lam1"]["synthetic"]
    assert described["eta0"]["synthetic"] is None
    assert stats["rows"] == len(lam1.transitions.rewards)
    assert stats["reward_mean"] == pytest.approx(float(lam1.transitions.rewards.mean()))
    same_states = real.rewards[lam1.diagnostics["source_index"]].mean()
    assert stats["source_reward_mean_same_states"] == pytest.approx(float(same_states))
    assert described["eta0"]["stage_one_seed"] is None and described["lam1"]["stage_one_seed"] == 0
    assert described["artifact-seed3"]["stage_one_seed"] == 3
    # and the source itself beside them, for the authenticity tables
    assert result["sources"]["hopper-m-r"] == {
        "sha256": info.sha256,
        "rows": len(real.rewards),
        "reward_mean": pytest.approx(float(real.rewards.mean())),
        "terminal_fraction": pytest.approx(float(real.terminals.mean())),
    }
    quality_md = (tmp_path / "results" / "quality.md").read_text()
    # the terminal share written as the docs write percentages
    assert f"| hopper-m-r | source | {len(real.rewards):,} |" in quality_md
    assert f"| {100 * float(real.terminals.mean()):.2f} % |" in quality_md
    union_config = json.loads((Path(runs["mixing-union"]["run_dir"]) / "config.json").read_text())
    assert union_config["mixing"] == "union" and union_config["eta"] == 0.5
    assert (
        [p[0] for p in runs["eta0"]["curve"]] == [p[0] for p in runs["hipode"]["curve"]] == [10, 20]
    )
    assert runs["eta0"]["eta"] == 0.0 and runs["hipode"]["eta"] == 0.5  # Table 6
    # the missing artifact was built through stage one under the dataset root, named by the
    # stage contract (the quick profile, this foreign source's tag)
    task = get_task("hopper-m-r")
    settings = ArtifactSettings(**{**table_settings(task, "td3bc").to_dict(), "profile": "quick"})
    built = default_artifact_path(
        task, settings, seed=0, root=dataset_root.resolve(), source_tag=info.sha256[:8]
    )
    assert built.is_file() and Path(described["hipode"]["artifact"]) == built
    assert described["hipode"]["label"].startswith("TD3+BC: HIPODE")
    difference = result["summary"]["hopper-m-r"]["hipode"]["difference"]["eta0"]
    assert difference["per_seed"] == [runs["hipode"]["final_score"] - runs["eta0"]["final_score"]]
    results = tmp_path / "results"
    assert (results / "quality.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((results / "quality.json").read_text())["runs"] == result["runs"]
    assert result["command"].startswith("hipode sweep --tasks hopper-m-r --seeds 0")
    markdown = (results / "quality.md").read_text()
    assert "| hopper-m-r | hipode |" in markdown
    assert f"| hopper-m-r | lam1 | {stats['rows']:,} | {stats['reward_mean']:.3f} |" in markdown

    fewer_arms = invoke(tmp_path, source, "--steps", "20")
    again = json.loads(fewer_arms.stdout)
    assert [r["status"] for r in again["runs"]] == ["finished earlier"] * 2
    # the arms it did not plan are named where a person reads, not silently dropped
    unplanned = ["hopper-m-r td3bc " + arm for arm in ("artifact-seed3", "lam1", "mixing-union")]
    assert again["unplanned_arms"] == unplanned
    assert ", ".join(unplanned) in " ".join(fewer_arms.stderr.split())
    named = "Not in this report: the runs in this folder of arms this sweep did not plan ("
    assert named + ", ".join(unplanned) + ")" in (results / "quality.md").read_text()
    assert [r["final_score"] for r in again["runs"]] == [
        runs[a]["final_score"] for a in ("eta0", "hipode")
    ]

    longer = json.loads(invoke(tmp_path, source, "--steps", "30").stdout)
    assert [r["status"] for r in longer["runs"]] == ["resumed from step 20"] * 2
    assert [p[0] for p in longer["runs"][0]["curve"]] == [10, 20, 30]
    hipode = next(r for r in longer["runs"] if r["arm"] == "hipode")
    window = longer["summary"]["hopper-m-r"]["hipode"]["window_scores"]
    assert window == [pytest.approx(sum(p[1] for p in hipode["curve"]) / 3)]  # last 3 evals
    hipode_summary = longer["summary"]["hopper-m-r"]["hipode"]
    assert hipode_summary["curve_means"] == window  # three evaluations: all of them are the last 3
    # a sweep over fewer arms keeps the rows of the arms it left out, by artifact checksum
    seen = json.loads((results / "quality.json").read_text())["synthetic_seen"]["hopper-m-r"]
    for arm in ("hipode", "lam1", "artifact-seed3"):
        assert seen[described[arm]["synthetic"]["checksum"]] == described[arm]["synthetic"]
    seed3 = out / "artifact-seed3" / "artifact.hdf5"
    seed3.unlink()
    left_out = invoke(tmp_path, source, "--steps", "20", "--artifact-seeds", "3", "--report-only")
    assert left_out.exit_code == 0, left_out.output
    kept = {a["name"]: a for a in json.loads(left_out.stdout)["arms"]["hopper-m-r"]}
    assert kept["artifact-seed3"]["synthetic"] == described["artifact-seed3"]["synthetic"]
    assert not seed3.exists()

    # bench/quality.py runs the same engine: --report-only trains nothing, reads the runs back
    args = sweep_args(tmp_path, source, "--steps", "30", "--report-only")
    args[args.index("--results") + 1] = str(tmp_path / "bench-results")
    read = CliRunner().invoke(quality.app, args)
    assert read.exit_code == 0, read.output
    read = json.loads(read.stdout)
    assert [r["final_score"] for r in read["runs"]] == [r["final_score"] for r in longer["runs"]]
    assert [r["status"] for r in read["runs"]] == ["finished earlier"] * 2
    assert read["budget"]["report_only"] is True
    assert read["command"].startswith("python bench/quality.py --tasks hopper-m-r")
    assert (tmp_path / "bench-results" / "quality.md").is_file()
    unreached = invoke(tmp_path, source, "--steps", "40", "--report-only")
    assert unreached.exit_code == 2 and "no finished runs" in unreached.output

    # a finished run with other settings is refused, not reported as if it matched
    other = invoke(tmp_path, source, "--steps", "20", "--eval-episodes", "3")
    assert other.exit_code == 2 and "other settings" in other.output

    # --report-only on a machine without the artifact reads the runs back and builds nothing
    built.unlink()
    bare = invoke(tmp_path, source, "--steps", "30", "--report-only")
    assert bare.exit_code == 0, bare.output
    assert [r["final_score"] for r in json.loads(bare.stdout)["runs"]] == [
        r["final_score"] for r in longer["runs"]
    ]
    assert "not built for --report-only" in " ".join(bare.stderr.split())
    assert not built.exists()
    # its synthetic-data row comes from the previous report, which describes the same artifact
    hipode_rows = described["hipode"]["synthetic"]["rows"]
    assert f"| hopper-m-r | hipode | {hipode_rows:,} |" in markdown
    assert f"| hopper-m-r | hipode | {hipode_rows:,} |" in (results / "quality.md").read_text()
    kept = {a["name"]: a for a in json.loads(bare.stdout)["arms"]["hopper-m-r"]}
    assert kept["hipode"]["synthetic"] == described["hipode"]["synthetic"]
    # a previous report of another artifact (another checksum) is not taken for this one
    previous = json.loads((results / "quality.json").read_text())
    for arm in previous["arms"]["hopper-m-r"]:
        if arm["synthetic"]:
            arm["synthetic"]["checksum"] = "sha256:" + "0" * 64
    previous["synthetic_seen"] = {}
    (results / "quality.json").write_text(json.dumps(previous))
    other_artifact = invoke(tmp_path, source, "--steps", "30", "--report-only")
    assert other_artifact.exit_code == 0, other_artifact.output
    dropped = {a["name"]: a for a in json.loads(other_artifact.stdout)["arms"]["hopper-m-r"]}
    assert dropped["hipode"]["synthetic"] is None
    assert f"| hopper-m-r | hipode | {hipode_rows:,} |" not in (results / "quality.md").read_text()


def test_synthetic_rows_seen_keep_other_tasks_and_take_this_sweeps_on_top():
    old = {"checksum": "sha256:a", "rows": 1}
    other_task = {"checksum": "sha256:b", "rows": 2}
    new = {"checksum": "sha256:a", "rows": 3}
    previous = {"hopper-m-r": {"sha256:a": old}, "walker2d-m-r": {"sha256:b": other_task}}
    arms = {"hopper-m-r": [{"synthetic": None}, {"synthetic": new}]}
    seen = plan.synthetic_seen(previous, arms)
    # a sweep over fewer tasks keeps the others' rows; this sweep's row replaces the old one
    assert seen == {"hopper-m-r": {"sha256:a": new}, "walker2d-m-r": {"sha256:b": other_task}}
    assert previous["hopper-m-r"]["sha256:a"] is old  # the previous report is not edited


def test_sweep_over_learners_pairs_each_with_its_own_baseline(tmp_path, dataset_root):
    source = write_source(tmp_path / "source.hdf5", n_episodes=8)
    done = invoke(
        tmp_path, source, "--learners", "td3bc,iql", "--steps", "10", "--eval-episodes", "1"
    )
    assert done.exit_code == 0, done.output
    result = json.loads(done.stdout)
    runs = {(r["learner"], r["arm"]): r for r in result["runs"]}
    assert set(runs) == {
        (learner, arm) for learner in ("td3bc", "iql") for arm in ("eta0", "hipode")
    }
    # each learner's hipode arm trains on its own table row's artifact at its own η (Table 7)
    iql = json.loads((Path(runs["iql", "hipode"]["run_dir"]) / "config.json").read_text())
    td3bc = json.loads((Path(runs["td3bc", "hipode"]["run_dir"]) / "config.json").read_text())
    assert iql["learner"] == "iql" and iql["eta"] == 0.05 and td3bc["eta"] == 0.5
    assert iql["artifact_hyper_parameters"]["lam"] == 1.0
    assert td3bc["artifact_hyper_parameters"]["lam"] == 0.2
    summary = result["summary"]["hopper-m-r"]
    assert set(summary) == {"td3bc/eta0", "td3bc/hipode", "iql/eta0", "iql/hipode"}
    for learner in ("td3bc", "iql"):  # paired with the same learner's eta0, seed by seed
        per_seed = summary[f"{learner}/hipode"]["difference"]["eta0"]["per_seed"]
        mine = runs[learner, "hipode"]["final_score"] - runs[learner, "eta0"]["final_score"]
        assert per_seed == [pytest.approx(mine)]
    assert "| hopper-m-r | iql/hipode |" in (tmp_path / "results" / "quality.md").read_text()


def test_bench_quality_is_the_package_command_with_the_repository_defaults():
    shown = CliRunner().invoke(quality.app, ["--help"], env={"COLUMNS": "200"})
    assert shown.exit_code == 0, shown.output
    assert "bench/results" in shown.output and "bench/out/quality" in shown.output
    assert "--learners" in shown.output and "--engine" in shown.output
    assert "--seeds-per-process" in shown.output and "0-4" in shown.output
    # the engine lives in the package: the script holds no sweep code of its own
    text = (BENCH / "quality.py").read_text()
    assert "def run_" not in text and "hipode_pipeline.commands.sweep" in text
    package = CliRunner().invoke(app, ["sweep", "--help"], env={"COLUMNS": "200"})
    assert "runs/sweep" in package.output and "OUT/report" in package.output
    assert "bench/results" not in package.output


def test_ablation_arms_and_budget_checks():
    config = plan.SweepConfig(
        alphas=[-1, 8],
        uniform=True,
        lams=[0.2, 1.0],
        penalties=["l2"],
        union=True,
        artifact_seeds=[1],
    )
    arms = plan.arms_for(config)
    assert [a.name for a in arms] == [
        "eta0",
        "hipode",
        "alpha-1",
        "alpha8",
        "uniform",
        "lam0.2",
        "lam1",
        "penalty-l2",
        "artifact-seed1",
        "mixing-union",
    ]
    assert arms[-3].augment == {"penalty": "l2"} and arms[-2].augment == {"seed": 1}
    assert arms[-1].mixing == "union"
    assert arms[4].augment == {"candidates": "uniform"} and arms[0].data == "source"
    with pytest.raises(HipodeError, match="artifact-seeds"):
        plan.arms_for(plan.SweepConfig(artifact_seeds=[0]))  # the hipode arm itself
    with pytest.raises(HipodeError, match="other than 1"):
        plan.arms_for(plan.SweepConfig(artifact_seed=1, artifact_seeds=[0, 1]))
    command = driver.command_line(plan.SweepConfig(artifact_seed=1, artifact_seeds=[2]))
    assert "--artifact-seed 1 --artifact-seeds 2" in command
    with pytest.raises(HipodeError, match="no repeats"):
        plan.arms_for(plan.SweepConfig(alphas=[1, 1]))
    with pytest.raises(HipodeError, match="divisor"):
        plan.resolve_budget(plan.SweepConfig(steps=100, eval_every=30))
    with pytest.raises(HipodeError, match="--learners: expected distinct learners"):
        plan.check_learners(["td3bc", "d3rlpy:CQL"])
    from hipode_pipeline.commands.sweep import parse_list

    with pytest.raises(HipodeError, match="--seeds"):
        parse_list("0,x", int, "--seeds")


def test_paired_difference_pairs_seeds():
    runs = [
        {"arm": "eta0", "seed": 0, "final_score": 10.0},
        {"arm": "eta0", "seed": 1, "final_score": 20.0},
        {"arm": "eta0", "seed": 2, "final_score": 30.0},
        {"arm": "hipode", "seed": 0, "final_score": 12.0},
        {"arm": "hipode", "seed": 1, "final_score": 24.0},
    ]
    diff = report.paired_difference(runs, "hipode", "eta0")
    assert diff["seeds"] == [0, 1] and diff["per_seed"] == [2.0, 4.0]  # seed 2 has no pair
    assert diff["mean"] == pytest.approx(3.0) and diff["sem"] == pytest.approx(1.0)


def test_ray_engine_without_ray_names_the_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    spec = RunSpec("hopper-m-r", "eta0", "source", 0.0, 0, 10, 10, 1, "out", "root")
    with pytest.raises(HipodeError, match=r"pip install 'hipode-pipeline\[ray\]'"):
        next(engines.run_ray([[spec]], None, 1))


def test_ray_engine_runs_a_tiny_sweep(tmp_path):
    pytest.importorskip(
        "ray", reason="ray is not installed here (the optional extra hipode-pipeline[ray])"
    )
    source = write_source(tmp_path / "source.hdf5", n_episodes=8)
    write_synthetic(tmp_path / "art.hdf5", source)
    done = invoke(
        tmp_path,
        source,
        "--artifact",
        str(tmp_path / "art.hdf5"),
        "--steps",
        "10",
        "--eval-episodes",
        "1",
        "--engine",
        "ray",
        "--workers",
        "1",
        "--seeds",
        "0,1",
    )
    assert done.exit_code == 0, done.output
    result = json.loads(done.stdout)
    assert {r["arm"] for r in result["runs"]} == {"eta0", "hipode"}
    assert all(r["status"] == "trained" for r in result["runs"])
    # one Ray task per arm trains both seeds together
    assert all(r["seeds_trained_together"] == [0, 1] for r in result["runs"])
    for arm in ("eta0", "hipode"):
        assert len({r["worker_pid"] for r in result["runs"] if r["arm"] == arm}) == 1
    assert result["machine"]["engine"] == "ray"


def test_a_missing_artifact_is_known_by_the_checksum_its_runs_record(tmp_path):
    config = plan.SweepConfig(seeds=[0, 1, 2], out=tmp_path)
    arm = tmp_path / "hopper-m-r" / "hipode"
    missing = tmp_path / "gone.hdf5"
    assert plan.recorded_checksum(config, "hopper-m-r", "td3bc", "hipode", missing) is None
    for seed, checksum in [(0, "sha256:aa"), (2, "sha256:aa")]:
        (arm / f"td3bc-seed{seed}").mkdir(parents=True)
        record = {"artifact_checksum": checksum, "seed": seed}
        (arm / f"td3bc-seed{seed}" / "config.json").write_text(json.dumps(record))
    assert plan.recorded_checksum(config, "hopper-m-r", "td3bc", "hipode", missing) == "sha256:aa"
    (arm / "td3bc-seed1").mkdir()
    (arm / "td3bc-seed1" / "config.json").write_text(json.dumps({"artifact_checksum": "sha256:bb"}))
    with pytest.raises(HipodeError, match="artifact_checksum.*gone.hdf5"):
        plan.recorded_checksum(config, "hopper-m-r", "td3bc", "hipode", missing)


def test_synthetic_stats_refuse_an_artifact_of_another_source(tmp_path):
    source = write_source(tmp_path / "source.hdf5")
    other = write_source(tmp_path / "other.hdf5", seed=1)
    write_synthetic(tmp_path / "art.hdf5", source)
    stats = plan.synthetic_stats(tmp_path / "art.hdf5", load_source(str(source)))
    assert stats["rows"] == 20
    with pytest.raises(DataFormatError, match="sha256"):
        plan.synthetic_stats(tmp_path / "art.hdf5", load_source(str(other)))


def test_model_rollout_arms_follow_the_stage_one_seeds():
    config = plan.SweepConfig(model_rollouts=True, artifact_seeds=[1, 2])
    arms = {a.name: a for a in plan.arms_for(config)}
    assert arms["model-rollouts"].augment == {"method": "model-rollouts"}
    assert arms["model-rollouts-seed2"].augment == {"method": "model-rollouts", "seed": 2}
    assert arms["model-rollouts-seed1"].data == "merged"
    assert {"hipode", "artifact-seed1", "artifact-seed2"} <= set(arms)
    assert "--model-rollouts" in driver.command_line(config)
    assert "model-rollouts" not in {a.name for a in plan.arms_for(plan.SweepConfig())}


def test_a_sweep_of_new_seeds_reports_every_finished_run_of_its_folder(tmp_path, dataset_root):
    source = write_source(tmp_path / "source.hdf5", n_episodes=8)
    tiny = ("--steps", "10", "--eval-episodes", "1")
    assert invoke(tmp_path, source, *tiny).exit_code == 0  # seed 0
    arms = tmp_path / "out" / "hopper-m-r"
    # folders the report must not take for finished runs of the arms: an unfinished run, a run
    # of other settings (its config names seed 0), a name run_folder never writes
    (arms / "eta0" / "td3bc-seed5").mkdir()
    (arms / "eta0" / "td3bc-seed5" / "config.json").write_text("{}")
    shutil.copytree(arms / "hipode" / "td3bc-seed0", arms / "hipode" / "td3bc-seed7")
    shutil.copytree(arms / "hipode" / "td3bc-seed0", arms / "hipode" / "td3bc-seed01")

    later = invoke(tmp_path, source, *tiny, "--seeds", "1")
    assert later.exit_code == 0, later.output
    result = json.loads(later.stdout)
    runs = {(r["arm"], r["seed"]): r["status"] for r in result["runs"]}
    assert runs == {
        ("eta0", 0): "finished earlier",
        ("hipode", 0): "finished earlier",
        ("eta0", 1): "trained",
        ("hipode", 1): "trained",
    }
    assert result["budget"]["seeds"] == [1] and result["budget"]["earlier_seeds"] == [0]
    difference = result["summary"]["hopper-m-r"]["hipode"]["difference"]["eta0"]
    assert difference["seeds"] == [0, 1]
    left_out = " ".join(later.stderr.split())
    assert "td3bc-seed5 (not finished at 10 updates)" in left_out
    assert "td3bc-seed7 (other settings: seed differ)" in left_out
    assert "seed01" not in left_out
    markdown = (tmp_path / "results" / "quality.md").read_text()
    assert "seeds [1] asked in every arm, and seeds [0] that earlier invocations finished" in (
        " ".join(markdown.split())
    )
    # read back alone, the folder reports the same runs
    again = json.loads(invoke(tmp_path, source, *tiny, "--seeds", "0", "--report-only").stdout)
    assert again["budget"]["earlier_seeds"] == [1]
    assert sorted((r["arm"], r["seed"]) for r in again["runs"]) == sorted(runs)
