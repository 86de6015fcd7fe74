"""The sweep trains the seeds of an arm together: one `train_seeds` call per unit (the runs that
differ only in their seed), finished seeds read back and never retrained, --seeds-per-process
splitting units, and the sweep's own folders and per-run records kept as they were."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import pytest
from test_merge import write_source, write_synthetic
from typer.testing import CliRunner

import hipode_pipeline.train as train
from hipode_pipeline.cli import app
from hipode_pipeline.errors import HipodeError
from hipode_pipeline.sweep import plan, worker
from hipode_pipeline.sweep.worker import RunSpec

ARMS = ("eta0", "hipode")


@pytest.fixture
def calls(monkeypatch):
    """The seeds of every `train_seeds` call the sweep makes (the real one still trains)."""
    seen: list[tuple[str, list[int]]] = []
    real = train.train_seeds

    def recording(task, learner, *args, seeds, **kwargs):
        seen.append((kwargs["data"], list(seeds)))
        return real(task, learner, *args, seeds=seeds, **kwargs)

    monkeypatch.setattr(train, "train_seeds", recording)
    return seen


@pytest.fixture
def tiny(tmp_path):
    """A tiny source and a synthetic artifact of it: no stage one in these tests."""
    source = write_source(tmp_path / "source.hdf5", n_episodes=8)
    write_synthetic(tmp_path / "art.hdf5", source)
    return source, tmp_path / "art.hdf5"


def invoke(tmp_path, tiny, seeds, *extra):
    source, artifact = tiny
    args = ["sweep", "--tasks", "hopper-m-r", "--seeds", seeds, "--steps", "10"]
    args += ["--eval-every", "10", "--eval-episodes", "1", "--source", str(source)]
    args += ["--artifact", str(artifact), "--out", str(tmp_path / "out"), "--json", *extra]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    return result


def sweep(tmp_path, tiny, seeds, *extra):
    return json.loads(invoke(tmp_path, tiny, seeds, *extra).stdout)


def runs_by(result):
    return {(r["arm"], r["seed"]): r for r in result["runs"]}


def test_one_unit_trains_every_seed_of_an_arm_and_keeps_the_sweep_folders(tmp_path, tiny, calls):
    result = sweep(tmp_path, tiny, "0-2")
    assert sorted(calls) == [("merged", [0, 1, 2]), ("source", [0, 1, 2])]
    runs = runs_by(result)
    assert set(runs) == {(arm, seed) for arm in ARMS for seed in (0, 1, 2)}
    for (arm, seed), run in runs.items():
        folder = tmp_path / "out" / "hopper-m-r" / arm / f"td3bc-seed{seed}"
        assert Path(run["run_dir"]) == folder and (folder / "scores.json").is_file()
        config = json.loads((folder / "config.json").read_text())
        assert config["seed"] == seed and config["seeds_trained_together"] == [0, 1, 2]
        assert run["status"] == "trained" and run["seeds_trained_together"] == [0, 1, 2]
    # paired seeds still pair: one difference per seed
    difference = result["summary"]["hopper-m-r"]["hipode"]["difference"]["eta0"]
    assert difference["seeds"] == [0, 1, 2]
    assert result["machine"]["seeds_per_process"] is None
    assert result["command"].startswith("hipode sweep --tasks hopper-m-r --seeds 0,1,2 ")


def test_finished_seeds_are_read_back_and_the_others_train_together(tmp_path, tiny, calls):
    sweep(tmp_path, tiny, "1")
    assert sorted(calls) == [("merged", [1]), ("source", [1])]
    calls.clear()
    result = sweep(tmp_path, tiny, "0-2")
    assert sorted(calls) == [("merged", [0, 2]), ("source", [0, 2])]
    runs = runs_by(result)
    for arm in ARMS:
        assert runs[arm, 1]["status"] == "finished earlier"
        assert runs[arm, 1]["seeds_trained_together"] == [1]  # how it was trained, back then
        assert [runs[arm, s]["status"] for s in (0, 2)] == ["trained"] * 2
        assert runs[arm, 0]["seeds_trained_together"] == [0, 2]
    calls.clear()
    again = sweep(tmp_path, tiny, "0-2")
    assert calls == []  # every seed finished: no unit calls train_seeds, no model is built
    assert {r["status"] for r in again["runs"]} == {"finished earlier"}
    assert [r["final_score"] for r in again["runs"]] == [r["final_score"] for r in result["runs"]]


def test_seeds_per_process_one_trains_each_seed_alone(tmp_path, tiny, calls):
    result = sweep(tmp_path, tiny, "0,1,2", "--seeds-per-process", "1")
    # the old order: the seeds interleaved, every arm of seed 0 before seed 1
    assert [seeds for _, seeds in calls] == [[0], [0], [1], [1], [2], [2]]
    assert {tuple(r["seeds_trained_together"]) for r in result["runs"]} == {(0,), (1,), (2,)}
    assert result["command"].endswith("--seeds-per-process 1")


def spec(arm, seed):
    return RunSpec("hopper-m-r", arm, "source", 0.0, seed, 10, 10, 1, "out", "root")


def test_units_split_by_seeds_per_process_in_the_plans_order():
    specs = [spec(arm, seed) for seed in range(5) for arm in ("eta0", "hipode")]
    units = plan.run_units(specs)
    assert [[s.seed for s in unit] for unit in units] == [[0, 1, 2, 3, 4]] * 2
    assert [unit[0].arm for unit in units] == ["eta0", "hipode"]
    units = plan.run_units(specs, 2)
    assert [(unit[0].arm, [s.seed for s in unit]) for unit in units] == [
        ("eta0", [0, 1]),
        ("hipode", [0, 1]),
        ("eta0", [2, 3]),
        ("hipode", [2, 3]),
        ("eta0", [4]),
        ("hipode", [4]),
    ]
    # runs that differ in anything but the seed never share a unit
    other = [replace(spec("eta0", seed), steps=20) for seed in range(2)]
    assert len(plan.run_units([*specs[:2], *other])) == 3
    for bad in (0, -1, 10**6, True):
        with pytest.raises(HipodeError, match=r"--seeds-per-process: expected an integer"):
            plan.run_units(specs, bad)
    with pytest.raises(HipodeError, match="differ only in their seed"):
        worker.run_unit([spec("eta0", 0).to_dict(), spec("hipode", 1).to_dict()])


@pytest.mark.parametrize(
    ("flag", "value", "message"),
    [
        ("--seeds-per-process", "0", "--seeds-per-process: expected an integer in [1, "),
        ("--seeds", "2-0", "--seeds: expected ranges low-high"),
        ("--seeds", "0,x", "--seeds: expected seeds like 0-4 or 0,2,5"),
        ("--seeds", "0,0-1", "--seeds: expected each seed once"),
    ],
)
def test_seed_flags_are_checked_before_anything_trains(tmp_path, tiny, flag, value, message):
    source, artifact = tiny
    args = ["sweep", "--tasks", "hopper-m-r", "--source", str(source), "--artifact", str(artifact)]
    args += ["--steps", "10", "--eval-every", "10", "--out", str(tmp_path / "out"), flag, value]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    assert message in result.stderr
    assert not any((tmp_path / "out").rglob("config.json"))


def test_local_worker_processes_each_train_a_unit(tmp_path, tiny):
    done = invoke(tmp_path, tiny, "0,1", "--workers", "3")
    assert "2 unit(s) of seeds for --workers 3" in done.stderr  # the idle worker is said
    result = json.loads(done.stdout)
    assert {(r["arm"], r["status"]) for r in result["runs"]} == {
        ("eta0", "trained"),
        ("hipode", "trained"),
    }
    assert all(r["seeds_trained_together"] == [0, 1] for r in result["runs"])
    # one spawned process per unit: both seeds of an arm in the same one, not in this process
    pids = [{r["worker_pid"] for r in result["runs"] if r["arm"] == arm} for arm in ARMS]
    assert [len(p) for p in pids] == [1, 1] and os.getpid() not in pids[0] | pids[1]


def finished_run(arm, seed, final):
    """A finished IQL hopper-m-r run record whose curve climbs to `final` in three evaluations."""
    curve = [[100, final - 2.0], [200, final - 1.0], [300, final]]
    return {
        "task": "hopper-m-r",
        "learner": "iql",
        "arm": arm,
        "seed": seed,
        "final_score": final,
        "curve": curve,
    }


def test_a_quality_row_of_one_run_shows_no_spread():
    from hipode_pipeline.sweep import report

    runs = [
        finished_run("eta0", 1, 40.0),
        finished_run("eta0", 2, 50.0),
        finished_run("model-rollouts", 1, 43.0),
    ]
    arms = {"hopper-m-r": [{"name": name, "learner": "iql"} for name in ("eta0", "model-rollouts")]}
    summary = report.summarize(runs, arms)
    quality = report.QualityReport("", {}, {}, arms, {}, runs, summary, "", 0.0)
    rows = {row[1]: row for row in report.table_rows(quality)}
    assert rows["eta0"][3] == "45.0 ± 7.1"
    rollouts = rows["model-rollouts"]
    assert rollouts[3] == "43.0 (one run)" and rollouts[4] == "+3.0 (one pair)"
    assert rollouts[8] == "42.0 (one run)" and rollouts[9] == "+3.0 (one pair)"
    assert summary["hopper-m-r"]["model-rollouts"]["difference"]["eta0"]["sem"] is None


def test_a_rollout_arm_meets_the_hipode_artifact_of_its_own_stage_one_seed():
    from hipode_pipeline.sweep import report

    finals = {
        "eta0": (40.0, 50.0),
        "hipode": (44.0, 54.0),
        "artifact-seed1": (30.0, 36.0),
        "model-rollouts": (45.0, 56.0),
        "model-rollouts-seed1": (33.0, 40.0),
    }
    runs = [finished_run(a, seed, f) for a, pair in finals.items() for seed, f in enumerate(pair)]
    stage_one = {"eta0": None, "hipode": 0, "artifact-seed1": 1, "model-rollouts": 0,
                 "model-rollouts-seed1": 1}  # fmt: skip
    arms = {
        "hopper-m-r": [
            {"name": name, "learner": "iql", "stage_one_seed": seed}
            for name, seed in stage_one.items()
        ]
    }
    full = report.summarize(runs, arms)
    summary = full["hopper-m-r"]
    seed1 = summary["model-rollouts-seed1"]["difference"]["hipode"]
    assert seed1["vs"] == "artifact-seed1" and seed1["per_seed"] == [3.0, 4.0]
    assert summary["model-rollouts"]["difference"]["hipode"]["per_seed"] == [1.0, 2.0]
    # a HIPODE arm of another stage-one seed meets the hipode arm: the stage-one seeds' spread
    assert summary["artifact-seed1"]["difference"]["hipode"]["per_seed"] == [-14.0, -18.0]
    assert "hipode" not in summary["hipode"]["difference"]
    quality = report.QualityReport("", {}, {}, arms, {}, runs, full, "", 0.0)
    rows = {row[1]: row for row in report.table_rows(quality)}
    assert rows["model-rollouts-seed1"][5].endswith("vs artifact-seed1")
    assert rows["model-rollouts"][5] == "+1.5 ± 0.7 (sem 0.5, n=2)"
