"""The sweep's artifacts before any training: each stage-one seed's artifacts built in one
process, in order (they share its cached generators), the seeds side by side with --workers,
their progress as labelled plain lines, and a second call finding every artifact up to date."""

from __future__ import annotations

import pickle

from test_merge import write_source

from hipode_pipeline import console
from hipode_pipeline.artifact import read_manifest
from hipode_pipeline.data.load import load_source
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.sweep import plan
from hipode_pipeline.tasks import get_task


def test_stage_one_seeds_build_side_by_side_and_share_their_generators(
    tmp_path, dataset_root, capfd
):
    source = write_source(tmp_path / "source.hdf5", n_episodes=8)
    config = plan.SweepConfig(
        tasks=["hopper-m-r"],
        source=str(source),
        profile="quick",
        artifact_seeds=[1],
        model_rollouts=True,
        workers=2,
        out=tmp_path / "out",
        root=dataset_root,
        show_progress=True,
    )
    task, arms = get_task("hopper-m-r"), plan.arms_for(config)
    info = load_source(str(source))[1]
    paths = plan.prepare_artifacts(task, arms, config, dataset_root, info)
    assert set(paths) == {("td3bc", arm.name) for arm in arms}
    assert paths["td3bc", "eta0"] is None
    manifests = {arm: read_manifest(path) for (_, arm), path in paths.items() if path}
    seeds = {arm: m["seeds"]["seed"] for arm, m in manifests.items()}
    assert seeds == {
        "hipode": 0,
        "artifact-seed1": 1,
        "model-rollouts": 0,
        "model-rollouts-seed1": 1,
    }
    assert manifests["model-rollouts-seed1"]["hyper_parameters"]["method"] == "model-rollouts"
    assert (
        paths["td3bc", "artifact-seed1"]
        == tmp_path / "out" / "hopper-m-r" / "artifact-seed1" / "artifact.hdf5"
    )
    # each rollout artifact read its own seed's generators, trained once by the hipode build
    hashes = {arm: m["generators"]["checkpoint_hashes"] for arm, m in manifests.items()}
    assert hashes["model-rollouts"] == hashes["hipode"] != hashes["artifact-seed1"]
    assert hashes["model-rollouts-seed1"] == hashes["artifact-seed1"]
    err = capfd.readouterr().err
    assert "stage-one seeds [0, 1] in 2 processes" in err
    assert "hopper-m-r stage-one seed 1: " in err and "hopper-m-r stage-one seed 0: " in err

    # in one process, later: every artifact is found up to date, none is written again
    written = {path: path.stat().st_mtime_ns for path in paths.values() if path}
    again = plan.prepare_artifacts(
        task, arms, plan.SweepConfig(**{**vars(config), "workers": 1}), dataset_root, info
    )
    assert again == paths
    assert {path: path.stat().st_mtime_ns for path in written} == written
    assert "processes" not in capfd.readouterr().err


def test_a_labelled_process_prints_plain_progress_lines(monkeypatch, capsys):
    monkeypatch.setenv(console.LABEL_ENV, "walker2d-m-r stage-one seed 1")
    monkeypatch.setenv(console.LINE_EVERY_ENV, "0")
    with console.progress() as progress:
        bar = progress.add_task("value", total=2, rate="", info="")
        progress.advance(bar)
    assert isinstance(progress, console.LineProgress)
    assert "walker2d-m-r stage-one seed 1: value: 1/2 (50%)" in capsys.readouterr().err


def test_a_worker_process_data_error_reaches_the_parent_whole():
    error = DataFormatError("a.hdf5", "rewards", "finite floats", "NaN")
    again = pickle.loads(pickle.dumps(error))
    assert type(again) is DataFormatError and str(again) == str(error)
    assert (again.path, again.field, again.expected, again.found) == (
        "a.hdf5",
        "rewards",
        "finite floats",
        "NaN",
    )
