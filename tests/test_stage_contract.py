"""The stage contract: one artifact per set of generation settings, found by a learner's table
row, checked against the run before anything is written; caches keyed on the code."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from test_merge import write_source, write_synthetic
from typer.testing import CliRunner

from hipode_pipeline import versions
from hipode_pipeline.augment import ArtifactRequest
from hipode_pipeline.cli import app
from hipode_pipeline.contract import default_artifact_path, table_settings
from hipode_pipeline.errors import ArtifactMismatchError, SettingError
from hipode_pipeline.tasks import get_task

TINY = ["--steps", "4", "--eval-every", "4", "--eval-episodes", "1", "--batch-size", "16"]
HOPPER = get_task("hopper-m-r")


def place_artifact(root: Path, learner: str, *, seed: int = 0, eta: float | None = None) -> Path:
    """An artifact of the task's own source at the default name of `learner`'s table row."""
    settings = table_settings(HOPPER, learner)
    if eta is not None:
        settings = type(settings)(**{**settings.to_dict(), "eta": eta})
    path = default_artifact_path(HOPPER, settings, seed=seed, root=root)
    path.parent.mkdir(parents=True, exist_ok=True)
    # rows differ per stage-one seed, as real artifacts' do
    write_synthetic(
        path,
        root / "source.hdf5",
        seed=seed + 1,
        hyper_parameters=settings.to_dict(),
        seeds={"seed": seed},
    )
    return path


@pytest.fixture
def source_root(tmp_path):
    root = tmp_path / "datasets"
    root.mkdir(exist_ok=True)
    write_source(root / "source.hdf5", n_episodes=8, length=25)
    return root


def train(root: Path, out: Path, *args: str):
    return CliRunner().invoke(
        app,
        [
            "train",
            "hopper-m-r",
            "--source",
            str(root / "source.hdf5"),
            "--root",
            str(root),
            "--out",
            str(out),
            *TINY,
            "--json",
            *args,
        ],
    )


def test_iql_trains_on_the_artifact_its_table_row_built(tmp_path, source_root):
    """augment --learner iql builds IQL's Table 7 row (λ = 1.0 on hopper-m-r, no dynamics
    filter); train --learner iql finds that file, not TD3+BC's."""
    source = str(source_root / "source.hdf5")
    common = ["--source", source, "--root", str(source_root), "--profile", "quick", "--json"]
    runner = CliRunner()
    for learner in ("td3bc", "iql"):
        built = runner.invoke(app, ["augment", "hopper-m-r", "--learner", learner, *common])
        assert built.exit_code == 0, built.output
    summary = json.loads(built.stdout)
    assert summary["lam"] == 1.0 and summary["eta"] == 0.05
    assert summary["table_row"] == {"learner": "iql", "table": "Table 7", "from_paper": True}
    assert "-eta0.05-lam1-" in Path(summary["artifact"]).name

    result = train(source_root, tmp_path / "runs", "--learner", "iql")
    assert result.exit_code == 0, result.output
    config = json.loads((Path(json.loads(result.stdout)["run_dir"]) / "config.json").read_text())
    assert config["artifact_path"] == summary["artifact"]
    assert config["artifact_hyper_parameters"]["lam"] == 1.0
    assert config["eta"] == 0.05 and config["table_row"]["table"] == "Table 7"


def test_a_mismatched_artifact_is_refused_before_a_run_folder_exists(tmp_path, source_root):
    td3bc_artifact = place_artifact(source_root, "td3bc")
    out = tmp_path / "runs"
    result = train(source_root, out, "--learner", "iql")
    assert result.exit_code == ArtifactMismatchError.exit_code
    message = " ".join(result.stderr.split())
    assert "lam 0.2 (expected 1.0)" in message and "eta 0.5 (expected 0.05)" in message
    assert "hipode augment hopper-m-r --learner iql" in message
    assert not out.exists()
    # --artifact uses the given file anyway, and the run records that it was given
    given = train(
        source_root,
        out,
        "--learner",
        "iql",
        "--artifact",
        str(td3bc_artifact),
    )
    assert given.exit_code == 0, given.output
    config = json.loads((Path(json.loads(given.stdout)["run_dir"]) / "config.json").read_text())
    assert (
        config["artifact_choice"] == "given" and config["artifact_hyper_parameters"]["lam"] == 0.2
    )


def test_artifact_seed_picks_the_stage_one_seed_independently_of_the_seed(tmp_path, source_root):
    seed0, seed1 = (
        place_artifact(source_root, "td3bc"),
        place_artifact(source_root, "td3bc", seed=1),
    )
    picked = {}
    for artifact_seed in (0, 1):
        result = train(source_root, tmp_path, "--artifact-seed", str(artifact_seed), "--seed", "3")
        assert result.exit_code == 0, result.output
        config = json.loads(
            (Path(json.loads(result.stdout)["run_dir"]) / "config.json").read_text()
        )
        assert config["seed"] == 3
        picked[artifact_seed] = (config["artifact_path"], config["artifact_seed"])
    assert picked == {0: (str(seed0), 0), 1: (str(seed1), 1)}
    missing = train(source_root, tmp_path, "--artifact-seed", "2")
    assert missing.exit_code == 2 and "stage-one seed 2" in " ".join(missing.stderr.split())


def test_batch_eta_follows_the_artifact_and_refuses_overuse(tmp_path, source_root):
    """An artifact of η = 0.1 trains at batch η 0.1 by default; η up to 2× its rate is warned
    about, beyond that refused before any folder is made."""
    artifact = str(place_artifact(source_root, "td3bc", eta=0.1))
    default = train(source_root, tmp_path / "a", "--artifact", artifact)
    assert default.exit_code == 0, default.output
    assert json.loads(default.stdout)["eta"] == 0.1
    warned = train(source_root, tmp_path / "b", "--artifact", artifact, "--eta", "0.15")
    assert warned.exit_code == 0, warned.output
    assert "1.5× as often" in warned.stderr
    refused = train(source_root, tmp_path / "c", "--artifact", artifact, "--eta", "0.5")
    assert refused.exit_code == SettingError.exit_code
    assert "5.0× as often" in refused.stderr and "--eta ≤ 0.2" in refused.stderr
    assert not (tmp_path / "c").exists()


def test_a_sweep_over_eta_writes_distinct_run_folders(tmp_path, source_root):
    artifact = str(place_artifact(source_root, "td3bc"))
    folders = set()
    for eta in ("0.1", "0.2", "0.5"):
        result = train(source_root, tmp_path, "--artifact", artifact, "--eta", eta)
        assert result.exit_code == 0, result.output
        folders.add(json.loads(result.stdout)["run_dir"])
    baseline = train(source_root, tmp_path, "--data", "source")
    assert baseline.exit_code == 0, baseline.output
    folders.add(json.loads(baseline.stdout)["run_dir"])
    names = sorted(Path(f).name for f in folders)
    assert len(names) == 4 and [n.split("-")[2] for n in names[:3]] == [
        "eta0.1",
        "eta0.2",
        "eta0.5",
    ]


def test_bad_run_settings_are_refused_before_any_folder(tmp_path, source_root):
    artifact = str(place_artifact(source_root, "td3bc"))
    for args in (["--batch-size", "0"], ["--eval-every", "0"], ["--seed", "-1"]):
        result = CliRunner().invoke(
            app,
            [
                "train",
                "hopper-m-r",
                "--source",
                str(source_root / "source.hdf5"),
                "--artifact",
                artifact,
                "--out",
                str(tmp_path / "runs"),
                "--steps",
                "4",
                *args,
            ],
        )
        assert result.exit_code == 2, (args, result.output)
        assert "Traceback" not in result.output
    assert not (tmp_path / "runs").exists()


def test_code_digest_follows_model_code_and_ignores_the_rest(tmp_path, monkeypatch):
    copy = tmp_path / "package"
    shutil.copytree(
        versions.PACKAGE_DIR, copy, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
    )
    monkeypatch.setattr(versions, "PACKAGE_DIR", copy)
    before = versions.code_digest(versions.GENERATOR_CODE)
    with open(copy / "commands" / "tasks.py", "a") as f:
        f.write("\n# an edit outside stage one\n")
    versions._code_digest.cache_clear()
    assert versions.code_digest(versions.GENERATOR_CODE) == before
    with open(copy / "models" / "cvae.py", "a") as f:
        f.write("\n# an edit of a model\n")
    versions._code_digest.cache_clear()
    assert versions.code_digest(versions.GENERATOR_CODE) != before
    versions._code_digest.cache_clear()


def test_changed_code_retrains_generators_and_rebuilds_the_artifact(tmp_path, monkeypatch):
    import numpy as np
    from test_generators import tiny_config

    from hipode_pipeline.data.transitions import Transitions
    from hipode_pipeline.models import generators

    rng = np.random.default_rng(0)
    s = rng.normal(size=(400, 5)).astype(np.float32)
    a = rng.uniform(-1, 1, size=(400, 2)).astype(np.float32)
    transitions = Transitions(
        s, a, s[:, 0].copy(), s + 0.1, np.zeros(400, bool), np.zeros(400, bool)
    )
    config = tiny_config()
    args = dict(cache_root=tmp_path, seed=0, show_progress=False)
    first = generators.train_generators(transitions, "a" * 64, config, **args)
    same = generators.train_generators(transitions, "a" * 64, config, **args)
    assert all(r["cached"] for r in same.training_report.values())
    monkeypatch.setattr(generators, "code_digest", lambda parts: "f" * 64)
    edited = generators.train_generators(transitions, "a" * 64, config, **args)
    assert edited.cache_dir != first.cache_dir
    assert not any(r.get("cached") for r in edited.training_report.values())

    # the artifact's request carries the stage-one code: an edit makes an old file stale
    request = ArtifactRequest("hopper-m-r", "a" * 64, {}, {}, 0)
    stored = {**request.__dict__, "code_digest": "0" * 64}
    assert any(name.startswith("code") for name in request.differences(stored))
    assert request.differences(dict(request.__dict__)) == []


def test_iql_runs_with_corls_per_task_settings(tmp_path, source_root):
    """stages/train.toml's [iql.tasks.*]: CORL's deterministic actor, tau 0.001 and reward
    normalization on hopper-m-r; IQLConfig's defaults (CORL's for most tasks) on walker2d-m-r."""
    hopper = train(source_root, tmp_path, "--learner", "iql", "--data", "source")
    assert hopper.exit_code == 0, hopper.output
    walker_source = write_source(
        source_root / "walker.hdf5", obs_dim=17, act_dim=6, env_id="Walker2d-v5"
    )
    walker = CliRunner().invoke(
        app,
        [
            "train",
            "walker2d-m-r",
            "--learner",
            "iql",
            "--data",
            "source",
            "--source",
            str(walker_source),
            "--out",
            str(tmp_path),
            *TINY,
            "--json",
        ],
    )
    assert walker.exit_code == 0, walker.output
    configs = {
        name: json.loads((Path(json.loads(r.stdout)["run_dir"]) / "config.json").read_text())
        for name, r in (("hopper", hopper), ("walker", walker))
    }
    settings = {
        name: {
            k: c["learner_config"][k] for k in ("deterministic_policy", "tau", "normalize_reward")
        }
        for name, c in configs.items()
    }
    assert settings == {
        "hopper": {"deterministic_policy": True, "tau": 0.001, "normalize_reward": True},
        "walker": {"deterministic_policy": False, "tau": 0.005, "normalize_reward": False},
    }


def test_an_ablation_artifact_is_never_taken_for_the_table_row(tmp_path, source_root):
    settings = table_settings(HOPPER, "td3bc")
    uniform = type(settings)(**{**settings.to_dict(), "candidates": "uniform"})
    path = default_artifact_path(HOPPER, uniform, root=source_root)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_synthetic(
        path, source_root / "source.hdf5", hyper_parameters=uniform.to_dict(), seeds={"seed": 0}
    )
    result = train(source_root, tmp_path / "runs")
    assert result.exit_code == ArtifactMismatchError.exit_code, result.output
    message = " ".join(result.stderr.split())
    assert "candidates 'uniform' (expected 'model')" in message
    # the command it suggests builds from the same source into the same root
    assert f"--source {source_root / 'source.hdf5'}" in message
    assert f"--root {source_root}" in message
    assert not (tmp_path / "runs").exists()


def test_a_manifest_rate_that_is_no_rate_falls_back_to_the_table(tmp_path, source_root):
    path = source_root / "zero.hdf5"
    write_synthetic(path, source_root / "source.hdf5", hyper_parameters={"eta": 0.0})
    given = train(source_root, tmp_path, "--artifact", str(path), "--eta", "0.1")
    assert given.exit_code == 0, given.output
    default = train(source_root, tmp_path, "--artifact", str(path))
    assert default.exit_code == 0, default.output
    assert (
        json.loads(default.stdout)["eta"] == 0.5 and "records no synthetic rate" in default.stderr
    )


def test_a_run_keeps_its_evaluation_schedule(tmp_path, source_root):
    first = train(source_root, tmp_path, "--data", "source", "--name", "r")
    assert first.exit_code == 0, first.output
    other = CliRunner().invoke(
        app,
        [
            "train",
            "hopper-m-r",
            "--source",
            str(source_root / "source.hdf5"),
            "--data",
            "source",
            "--out",
            str(tmp_path),
            "--name",
            "r",
            "--steps",
            "8",
            "--eval-every",
            "2",
            "--eval-episodes",
            "1",
            "--batch-size",
            "16",
        ],
    )
    assert other.exit_code == 2 and "eval_every" in other.stderr


def test_the_code_digest_ignores_line_endings(tmp_path, monkeypatch):
    copy = tmp_path / "package"
    shutil.copytree(
        versions.PACKAGE_DIR, copy, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
    )
    monkeypatch.setattr(versions, "PACKAGE_DIR", copy)
    before = versions.code_digest(versions.ARTIFACT_CODE)
    cvae = copy / "models" / "cvae.py"
    cvae.write_bytes(cvae.read_bytes().replace(b"\n", b"\r\n"))
    versions._code_digest.cache_clear()
    assert versions.code_digest(versions.ARTIFACT_CODE) == before
    versions._code_digest.cache_clear()


def test_an_artifact_under_any_name_is_found_by_its_manifest(tmp_path, source_root):
    """`hipode import` keeps the sender's file name: train reads manifests, not names."""
    canonical = place_artifact(source_root, "td3bc")
    shared = canonical.with_name("shared.hdf5")
    canonical.rename(shared)
    result = train(source_root, tmp_path)
    assert result.exit_code == 0, result.output
    config = json.loads((Path(json.loads(result.stdout)["run_dir"]) / "config.json").read_text())
    assert config["artifact_path"] == str(shared) and config["artifact_choice"] == "table"
    baseline = train(source_root, tmp_path, "--data", "source")
    assert baseline.exit_code == 0 and "not used" not in baseline.stderr
