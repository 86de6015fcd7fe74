"""Hostile settings and mismatched data: each is refused before any model trains, any folder is
made or anything is deleted, with one clear line and exit code 2."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import pytest
import torch
from test_merge import write_source, write_synthetic
from typer.testing import CliRunner

from hipode_pipeline.cli import app
from hipode_pipeline.errors import TrainingDivergedError
from hipode_pipeline.models import training


def snapshot(folder: Path) -> dict[str, int]:
    """Every file under `folder` with its size: what a refused command must leave unchanged."""
    return {str(p.relative_to(folder)): p.stat().st_size for p in folder.rglob("*") if p.is_file()}


def without_env_attribute(path: Path) -> Path:
    with h5py.File(path, "a") as f:
        del f.attrs["env_id"]
    return path


@pytest.fixture
def world(tmp_path):
    root = tmp_path / "datasets"
    root.mkdir(exist_ok=True)
    hopper = write_source(root / "hopper.hdf5", n_episodes=8)
    walker = write_source(root / "walker.hdf5", obs_dim=17, act_dim=6, env_id="Walker2d-v5")
    walker_bare = without_env_attribute(
        write_source(root / "walker-bare.hdf5", obs_dim=17, act_dim=6)
    )
    wrong_actions = without_env_attribute(write_source(root / "act4.hdf5", act_dim=4))
    write_synthetic(root / "art.hdf5", hopper)
    return {
        "root": root,
        "hopper": hopper,
        "walker": walker,
        "walker_bare": walker_bare,
        "act4": wrong_actions,
        "artifact": root / "art.hdf5",
    }


AUGMENT_CASES = {
    "eta inf": (["--eta", "inf"], "eta"),
    "eta 1e9": (["--eta", "1e9"], "eta"),
    "eta nan": (["--eta", "nan"], "eta"),
    "lam 0": (["--lam", "0"], "lam"),
    "lam nan": (["--lam", "nan"], "lam"),
    "n huge": (["--n", "100000"], "'n'"),
    "alpha nan": (["--alpha", "nan"], "alpha"),
    "alpha inf": (["--alpha", "inf"], "alpha"),
    "sigma inf": (["--sigma", "inf"], "sigma"),
    "seed negative": (["--seed", "-1"], "--seed"),
    "seed 2^64": (["--seed", str(2**64)], "--seed"),
    "learner unknown": (["--learner", "sac"], "learner"),
    "walker data for hopper": (["--source", "{walker}"], "env"),
    "walker-shaped data, no env": (["--source", "{walker_bare}"], "observations"),
    "4 action columns for hopper": (["--source", "{act4}"], "actions"),
}


@pytest.mark.parametrize("case", sorted(AUGMENT_CASES))
def test_augment_refuses_before_any_training(world, case):
    args, field = AUGMENT_CASES[case]
    args = [a.format(**{k: str(v) for k, v in world.items()}) for a in args]
    if "--source" not in args:
        args += ["--source", str(world["hopper"])]
    root = world["root"]
    before = snapshot(root)
    result = CliRunner().invoke(
        app, ["augment", "hopper-m-r", "--profile", "quick", "--root", str(root), *args]
    )
    assert result.exit_code == 2, (case, result.output)
    assert "Traceback" not in result.output and field in result.output, (case, result.output)
    # nothing trained, cached or written
    assert snapshot(root) == before and not (root / "cache").exists()


TRAIN_CASES = {
    "batch size 0": (["--batch-size", "0"], "--batch-size"),
    "batch size 2^40": (["--batch-size", str(2**40)], "--batch-size"),
    "eval every 0": (["--eval-every", "0"], "--eval-every"),
    "eval episodes 0": (["--eval-episodes", "0"], "--eval-episodes"),
    "steps 0": (["--steps", "0"], "--steps"),
    "seed negative": (["--seed", "-3"], "--seed"),
    "seed 2^70": (["--seed", str(2**70)], "--seed"),
    "artifact seed negative": (["--artifact-seed", "-1"], "--artifact-seed"),
    "eta above 1": (["--eta", "2"], "--eta"),
    "eta nan": (["--eta", "nan"], "--eta"),
    "mixing unknown": (["--mixing", "sometimes"], "--mixing"),
    "data unknown": (["--data", "both"], "--data"),
    "name with a slash": (["--name", "../escape"], "--name"),
    "walker data for hopper": (["--source", "{walker}", "--data", "source"], "env"),
    "walker-shaped, no env": (["--source", "{walker_bare}", "--data", "source"], "observations"),
    "4 action columns": (["--source", "{act4}", "--data", "source"], "actions"),
    "artifact of another source": (
        ["--source", "{walker}", "--artifact", "{artifact}"],
        "env",
    ),
}


@pytest.mark.parametrize("case", sorted(TRAIN_CASES))
def test_train_refuses_before_any_folder_or_deletion(world, tmp_path, case):
    args, field = TRAIN_CASES[case]
    args = [a.format(**{k: str(v) for k, v in world.items()}) for a in args]
    if "--source" not in args:
        args += ["--source", str(world["hopper"]), "--artifact", str(world["artifact"])]
    out = tmp_path / "runs"
    # an existing run that a refused `--force` must not remove
    existing = out / "hopper-m-r" / "keep-me"
    existing.mkdir(parents=True)
    (existing / "config.json").write_text(json.dumps({"task": "hopper-m-r"}))
    before = snapshot(out)
    result = CliRunner().invoke(
        app,
        ["train", "hopper-m-r", "--out", str(out), "--steps", "4", "--force", *args],
    )
    assert result.exit_code == 2, (case, result.output)
    assert "Traceback" not in result.output and field in result.output, (case, result.output)
    assert snapshot(out) == before


def test_force_replaces_a_run_only_after_every_input_checked(world, tmp_path):
    out, common = tmp_path / "runs", ["--steps", "4", "--eval-every", "4", "--eval-episodes", "1"]
    base = ["train", "hopper-m-r", "--source", str(world["hopper"]), "--data", "source"]
    first = CliRunner().invoke(app, [*base, *common, "--out", str(out), "--name", "x", "--json"])
    assert first.exit_code == 0, first.output
    run_dir = Path(json.loads(first.stdout)["run_dir"])
    before = snapshot(run_dir)
    refused = CliRunner().invoke(
        app, [*base, *common, "--out", str(out), "--name", "x", "--force", "--batch-size", "0"]
    )
    assert refused.exit_code == 2 and snapshot(run_dir) == before
    forced = CliRunner().invoke(app, [*base, *common, "--out", str(out), "--name", "x", "--force"])
    assert forced.exit_code == 0, forced.output


def test_a_diverged_generator_never_reaches_the_cache(tmp_path):
    model = torch.nn.Linear(3, 1)
    data = training.TensorData(
        {"x": torch.randn(64, 3)}, heldout_fraction=0.25, heldout_eval_rows=16, seed=0
    )

    def exploding(batch, generator):
        # a loss whose gradient is NaN: the weights become NaN after the first step
        loss = (model(batch["x"]) * torch.tensor(float("nan"))).mean()
        return loss, {}

    checkpoint = tmp_path / "m.ckpt.pt"
    with pytest.raises(TrainingDivergedError, match="finite weights"):
        training.fit(
            "value",
            model,
            exploding,
            lambda batch: model(batch["x"]).mean().reshape(1),
            data,
            steps=4,
            batch_size=8,
            lr=1e-3,
            weight_decay=0.0,
            seed=0,
            precision="fp32",
            eval_every=2,
            checkpoint_every=2,
            checkpoint_path=checkpoint,
            keep_best="none",
        )
    assert not checkpoint.exists()


def quick_augment(world, root: Path, out: Path):
    """`hipode augment hopper-m-r --profile quick` on the world's hopper source."""
    args = ["augment", "hopper-m-r", "--source", str(world["hopper"]), "--profile", "quick"]
    return CliRunner().invoke(app, [*args, "--root", str(root), "--out", str(out)])


def test_the_machine_refusing_a_path_is_one_line_not_a_traceback(world, tmp_path):
    root = tmp_path / "rootc"
    root.mkdir()
    (root / "cache").touch()  # a file where stage one needs its cache folder
    result = quick_augment(world, root, tmp_path / "a.hdf5")
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "Not a directory" in result.stderr and str(root / "cache") in result.stderr


def test_a_lock_that_cannot_be_made_is_refused_not_waited_for(world, tmp_path):
    folder = tmp_path / "lk"
    folder.mkdir()
    (folder / ".y.hdf5.lock").symlink_to(tmp_path / "nowhere" / "file")
    result = quick_augment(world, world["root"], folder / "y.hdf5")
    assert result.exit_code == 2 and "lock" in result.stderr


@pytest.mark.parametrize("flag", ["--steps", "--eval-every", "--eval-episodes"])
def test_sweep_refuses_zero_instead_of_taking_the_default(world, tmp_path, flag):
    result = CliRunner().invoke(
        app,
        [
            "sweep",
            "--tasks",
            "hopper-m-r",
            "--source",
            str(world["hopper"]),
            "--seeds",
            "0",
            "--profile",
            "quick",
            "--root",
            str(world["root"]),
            "--out",
            str(tmp_path / "s"),
            "--steps",
            "20",
            "--eval-every",
            "10",
            "--eval-episodes",
            "1",
            flag,
            "0",
        ],
    )
    assert result.exit_code == 2, result.output
    assert "expected positive integers" in result.stderr
    assert not (tmp_path / "s").exists() or not any((tmp_path / "s").rglob("config.json"))
