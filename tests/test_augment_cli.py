"""`hipode augment` end to end with the real generators (quick profile) on a tiny dataset."""

import json
from pathlib import Path

import numpy as np
import pytest
from builders import make_episodes, make_minari_dataset
from typer.testing import CliRunner

from hipode_pipeline.artifact import SCHEMA_VERSION, read_artifact
from hipode_pipeline.augment import summary_path
from hipode_pipeline.cli import app
from hipode_pipeline.contract import ArtifactSettings, default_artifact_path, table_settings
from hipode_pipeline.data import collect as collect_module
from hipode_pipeline.generate import synthetic_count
from hipode_pipeline.tasks import get_task


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    """One real stage-one run (quick profile) on a fresh root whose source must be collected
    first; both tests below start from it, so the generators are trained once."""
    root = tmp_path_factory.mktemp("augment") / "datasets"
    collected = []

    def fake_collect(task, *, root=None, **kwargs):
        # stands in for policy training and rollouts: writes the task's dataset directly
        collected.append(task.name)
        make_minari_dataset(
            task.local_dataset_id, make_episodes(40, 11, 3, seed=0), env_id="Hopper-v5"
        )

    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(root))
        patch.setattr(collect_module, "collect", fake_collect)
        result = CliRunner().invoke(
            app, ["augment", "hopper-m-r", "--profile", "quick", "--root", str(root), "--json"]
        )
    return root, result, collected


def test_augment_collects_writes_reuses_and_refuses(first_run):
    root, first, collected = first_run
    assert first.exit_code == 0, first.output
    assert collected == ["hopper-m-r"]
    assert "collecting it first" in first.stderr
    summary = json.loads(first.stdout)
    quick_settings = ArtifactSettings(
        **{**table_settings(get_task("hopper-m-r"), "td3bc").to_dict(), "profile": "quick"}
    )
    path = default_artifact_path(get_task("hopper-m-r"), quick_settings, root=root)
    assert path.name == "hopper-m-r-eta0.5-lam0.2-n10-alpha1-sigma1-quick-seed0.hdf5"
    assert summary["artifact"] == str(path)
    assert summary["table_row"] == {"learner": "td3bc", "table": "Table 6", "from_paper": True}
    assert summary["kept"] == synthetic_count(0.5, summary["n_source"])  # Table 6: eta = 0.5
    assert not summary["generators_cached"]
    assert set(summary["seconds"]) == {"load", "train", "generate", "write", "total"}
    runner = CliRunner()
    quick = ["augment", "hopper-m-r", "--profile", "quick", "--root", str(root)]

    artifact = read_artifact(path)
    assert len(artifact) == summary["kept"]
    manifest = artifact.manifest
    assert manifest["schema"] == {"name": "hipode-synthetic", "version": SCHEMA_VERSION}
    assert manifest["env_id"] == "Hopper-v5"
    assert manifest["source"]["sha256"] == summary["source_sha256"]
    assert manifest["hyper_parameters"]["eta"] == 0.5 and manifest["hyper_parameters"]["lam"] == 0.2
    assert manifest["hyper_parameters"]["generator_config"]["state_transition_steps"] == 300
    assert set(manifest["generators"]["checkpoint_hashes"]) == {
        "state_transition",
        "value",
        "inverse_action",
        "inverse_reward",
        "dynamics",
    }
    assert manifest["counts"]["kept"] == len(artifact)
    assert {"torch", "numpy", "h5py", "gymnasium", "mujoco", "minari", "python"} <= set(
        manifest["versions"]
    )
    assert (
        json.loads(summary_path(path).read_text())["artifact_sha256"] == summary["artifact_sha256"]
    )

    # other settings, same output, no --force: refused, file untouched
    other = runner.invoke(app, [*quick, "--eta", "0.3", "--out", str(path)])
    assert other.exit_code != 0
    assert "--force" in other.stderr and "Traceback" not in other.output
    assert "generation.eta" in other.stderr  # says what differs
    assert read_artifact(path).manifest["checksum"] == manifest["checksum"]

    # the same request again: verified and kept, nothing trained or generated
    same = runner.invoke(app, [*quick, "--json"])
    assert same.exit_code == 0, same.output
    assert json.loads(same.stdout)["reused_artifact"] is True
    assert "train" not in json.loads(same.stdout)["seconds"]

    # --force regenerates with cached generators: identical arrays for the same seed
    forced = runner.invoke(app, [*quick, "--force", "--json"])
    assert forced.exit_code == 0, forced.output
    assert json.loads(forced.stdout)["generators_cached"] is True
    again = read_artifact(path)
    for name, array in artifact.transitions.arrays().items():
        np.testing.assert_array_equal(again.transitions.arrays()[name], array)
    for name, array in artifact.diagnostics.items():
        np.testing.assert_array_equal(again.diagnostics[name], array)
    assert again.manifest["checksum"] == manifest["checksum"] == summary["content_checksum"]


def test_augment_with_overrides_reuses_generators_and_prints_a_table(first_run, tmp_path):
    root, first, _ = first_run
    assert first.exit_code == 0, first.output
    out = tmp_path / "out" / "ablation.hdf5"
    result = CliRunner().invoke(
        app,
        [
            "augment",
            "hopper-m-r",
            "--source",
            "local/hopper/medium-replay-v0",
            "--root",
            str(root),
            "--profile",
            "quick",
            "--eta",
            "0.25",
            "--lam",
            "0.5",
            "--n",
            "4",
            "--selection",
            "global",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert (
        "kept" in result.stdout and "artifact sha256" in result.stdout and "cached" in result.stdout
    )
    artifact = read_artifact(out)
    n_source = json.loads(first.stdout)["n_source"]
    assert len(artifact) == synthetic_count(0.25, n_source)
    assert artifact.manifest["hyper_parameters"]["selection"] == "global"
    assert artifact.manifest["hyper_parameters"]["n"] == 4
    assert artifact.manifest["env_id"] == "Hopper-v5"


def test_missing_source_that_cannot_be_collected_fails_cleanly(tmp_path):
    result = CliRunner().invoke(
        app, ["augment", "hopper-m-r", "--source", str(tmp_path / "absent.hdf5")]
    )
    assert result.exit_code != 0
    assert "absent.hdf5" in result.stderr and "Traceback" not in result.output


def test_model_rollout_baseline_on_the_same_generators(first_run, tmp_path):
    root, first, _ = first_run
    assert first.exit_code == 0, first.output
    quick = ["augment", "hopper-m-r", "--profile", "quick", "--root", str(root)]
    runner = CliRunner()
    refused = runner.invoke(app, [*quick, "--method", "model-rollouts", "--lam", "0.5"])
    assert refused.exit_code != 0 and "--lam" in refused.stderr
    assert "Traceback" not in refused.output
    result = runner.invoke(app, [*quick, "--method", "model-rollouts", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    path = Path(summary["artifact"])
    assert path.name == "hopper-m-r-eta0.5-lam1-n1-alpha1-sigma1-model-rollouts-quick-seed0.hdf5"
    assert summary["kept"] == json.loads(first.stdout)["kept"]  # the same η·N as HIPODE's
    artifact = read_artifact(path)
    manifest = artifact.manifest
    assert manifest["hyper_parameters"]["method"] == "model-rollouts"
    assert manifest["generators"]["behaviour_cvae"]["steps"] == 300
    hipode = read_artifact(Path(json.loads(first.stdout)["artifact"])).manifest
    # the five generators are HIPODE's own, read from its cache
    assert manifest["generators"]["checkpoint_hashes"] == hipode["generators"]["checkpoint_hashes"]
    assert manifest["request"]["code_digest"] != hipode["request"]["code_digest"]
    assert not summary["generators_cached"]  # the behaviour model was trained here
    valid = runner.invoke(app, ["validate", str(path)])
    assert valid.exit_code == 0, valid.output
    again = runner.invoke(app, [*quick, "--method", "model-rollouts", "--force", "--json"])
    assert again.exit_code == 0, again.output
    assert json.loads(again.stdout)["generators_cached"] is True
    assert read_artifact(path).manifest["checksum"] == manifest["checksum"]
