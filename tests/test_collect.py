"""`hipode collect` at the quick profile: real PPO, MuJoCo and Minari datasets, tiny budgets."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from hipode_pipeline.cli import app
from hipode_pipeline.data import collect as collect_module
from hipode_pipeline.data.collect import (
    CollectionBusyError,
    CollectionInterrupted,
    NotCollectableError,
    collect,
    load_recipe,
    work_dir,
)
from hipode_pipeline.data.minari_write import split_episodes
from hipode_pipeline.data.ppo import RolloutBlock
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.tasks import get_task


def _episodes(dataset_id: str) -> tuple[list, dict]:
    import minari

    dataset = minari.load_dataset(dataset_id)
    return list(dataset.iterate_episodes()), dataset.storage.metadata


def _flat(episodes: list) -> dict[str, np.ndarray]:
    return {
        "observations": np.concatenate([e.observations for e in episodes]),
        "actions": np.concatenate([e.actions for e in episodes]),
        "rewards": np.concatenate([e.rewards for e in episodes]),
        "terminations": np.concatenate([e.terminations for e in episodes]),
        "truncations": np.concatenate([e.truncations for e in episodes]),
    }


def _steps(path) -> int:
    return int(torch.load(path, weights_only=True)["steps"])


def test_cli_collects_a_medium_replay_minari_dataset(dataset_root):
    result = CliRunner().invoke(app, ["collect", "hopper-m-r", "--profile", "quick", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["dataset_ids"] == ["local/hopper/medium-replay-v0"]
    recipe = load_recipe("hopper", "quick")

    episodes, metadata = _episodes("local/hopper/medium-replay-v0")
    # medium-replay is every PPO transition up to the medium checkpoint (the step budget here)
    assert sum(len(e.rewards) for e in episodes) == recipe.medium_max_steps == report["transitions"]
    assert len(episodes) == report["episodes"]
    for e in episodes:
        t = len(e.rewards)
        assert e.observations.shape == (t + 1, 11) and e.actions.shape == (t, 3)
        # exactly one end flag, on the last step only
        assert not (e.terminations[:-1] | e.truncations[:-1]).any()
        assert e.terminations[-1] != e.truncations[-1]
        assert np.all(np.abs(e.actions) <= 1.0)
    assert any(e.terminations[-1] for e in episodes), "an early Hopper policy falls over"

    # the loader of the pipeline reads it as flat transitions with the same end flags
    from hipode_pipeline.data.load import load_source

    transitions, info = load_source("hopper-m-r")
    assert len(transitions) == report["transitions"]
    assert int(transitions.terminals.sum()) == sum(bool(e.terminations[-1]) for e in episodes)
    assert int(transitions.timeouts.sum()) == sum(bool(e.truncations[-1]) for e in episodes)
    assert info.metadata["hipode"]["kind"] == "medium-replay"

    task = get_task("hopper-m-r")
    assert metadata["ref_min_score"] == task.ref_min_score
    assert metadata["ref_max_score"] == task.ref_max_score
    extra = metadata["hipode"]
    assert {"recipe", "seeds", "behaviour_policy", "versions", "training"} <= set(extra)
    assert extra["recipe"]["profile"] == "quick" and extra["seeds"]["seed"] == 0
    medium = extra["behaviour_policy"]["medium"]
    assert medium["episodes"] == recipe.eval_episodes
    assert medium["normalized"] == pytest.approx(task.normalized_score(medium["mean"]))
    assert report["policy_returns"]["medium"] == pytest.approx(medium["mean"])
    assert {"torch", "gymnasium", "mujoco", "minari", "numpy", "hipode_pipeline"} <= set(
        extra["versions"]
    )


def test_policies_are_trained_once_and_reused(dataset_root):
    first = collect(get_task("hopper-m-r"), profile="quick", show_progress=False)
    work = work_dir(dataset_root, "hopper", 0)
    checkpoint, medium_policy = work / "ppo.pt", work / "policy-medium.pt"
    stamps = (checkpoint.stat().st_mtime_ns, medium_policy.stat().st_mtime_ns)

    medium = collect(get_task("hopper-m"), profile="quick", show_progress=False)
    assert (checkpoint.stat().st_mtime_ns, medium_policy.stat().st_mtime_ns) == stamps, "retrained"
    assert "train" not in medium.steps_per_second
    assert medium.policy_returns == first.policy_returns  # the same cached measurement
    assert medium.transitions == load_recipe("hopper", "quick").medium_size

    # expert training continues the same PPO run past the medium checkpoint
    expert = collect(get_task("hopper-e"), profile="quick", show_progress=False)
    assert medium_policy.stat().st_mtime_ns == stamps[1]
    assert _steps(checkpoint) >= load_recipe("hopper", "quick").expert_steps
    assert set(expert.policy_returns) == {"expert"}
    # every expert check is kept, in order, as the search's learning curve
    meta_path = dataset_root / "local/hopper/expert-v0/data/metadata.json"
    checks = json.loads(meta_path.read_text())["hipode"]["training"]["expert_checks"]
    steps = [c["steps"] for c in checks]
    assert steps == sorted(steps) and steps[-1] == _steps(checkpoint)
    assert all(np.isfinite(c["normalized"]) for c in checks)

    # an existing dataset is left alone; force rebuilds it with the same content
    again = collect(get_task("hopper-m"), profile="quick", show_progress=False)
    assert again.reused and again.transitions == medium.transitions
    before = _flat(_episodes("local/hopper/medium-v0")[0])
    rebuilt = collect(get_task("hopper-m"), profile="quick", force=True, show_progress=False)
    assert not rebuilt.reused
    after = _flat(_episodes("local/hopper/medium-v0")[0])
    assert all(np.array_equal(before[k], after[k]) for k in before)

    # the work folder belongs to the quick recipe: the full one must not reuse its policies
    with pytest.raises(DataFormatError, match="another recipe"):
        collect(get_task("hopper-m-e"), profile="full", show_progress=False)


def test_interrupted_collection_resumes_to_the_same_dataset(dataset_root, tmp_path, monkeypatch):
    task = get_task("hopper-m-r")
    monkeypatch.setattr(collect_module, "STOP_AFTER_STEPS", 512)
    with pytest.raises(CollectionInterrupted):
        collect(task, profile="quick", show_progress=False)
    assert _steps(work_dir(dataset_root, "hopper", 0) / "ppo.pt") == 512
    monkeypatch.setattr(collect_module, "STOP_AFTER_STEPS", None)
    resumed = collect(task, profile="quick", show_progress=False)
    resumed_arrays = _flat(_episodes(task.local_dataset_id)[0])

    other_root = tmp_path / "uninterrupted"
    straight = collect(task, root=other_root, profile="quick", show_progress=False)
    straight_arrays = _flat(_episodes(task.local_dataset_id)[0])
    assert resumed.transitions == straight.transitions
    for name in resumed_arrays:
        assert np.array_equal(resumed_arrays[name], straight_arrays[name]), name
    assert resumed.policy_returns == straight.policy_returns

    # a different seed is a different run
    collect(task, root=tmp_path / "seed1", seed=1, profile="quick", show_progress=False)
    seed1 = _flat(_episodes(task.local_dataset_id)[0])
    assert not np.array_equal(seed1["observations"][:100], straight_arrays["observations"][:100])


def test_random_dataset_uses_uniform_actions(dataset_root):
    work = work_dir(dataset_root, "walker2d", 0)
    work.mkdir(parents=True)
    (work / ".lock").write_text(str(os.getpid()))  # a live owner: refuse
    with pytest.raises(CollectionBusyError, match="another collection"):
        collect(get_task("walker2d-r"), profile="quick", show_progress=False)
    finished = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    (work / ".lock").write_text(finished.stdout.strip())  # a dead owner: take the lock over

    result = collect(get_task("walker2d-r"), profile="quick", show_progress=False)
    episodes, metadata = _episodes("local/walker2d/random-v0")
    actions = _flat(episodes)["actions"]
    assert result.transitions == len(actions) == load_recipe("walker2d", "quick").random_size
    assert result.policy_returns == {}
    assert metadata["algorithm_name"] == "uniform-random"
    # uniform on [-1, 1]: spread over the whole box, mean near 0
    assert actions.min() < -0.9 and actions.max() > 0.9 and abs(actions.mean()) < 0.1
    assert not (work / "ppo.pt").exists() and not (work / ".lock").exists()


def test_adroit_task_is_refused_clearly():
    with pytest.raises(NotCollectableError, match="pen-h"):
        collect(get_task("pen-h"), profile="quick", show_progress=False)
    result = CliRunner().invoke(app, ["collect", "door-h", "--profile", "quick"])
    assert result.exit_code == 2
    assert "cannot be collected" in result.output


def test_unknown_profile_names_the_recipe_file():
    with pytest.raises(DataFormatError, match="collect.toml.*profiles"):
        load_recipe("hopper", "tiny")


def test_split_episodes_marks_the_cut_as_truncated():
    t, n = 5, 2
    block = RolloutBlock(
        observations=np.arange(t * n * 1, dtype=np.float64).reshape(t, n, 1),
        actions=np.zeros((t, n, 1), np.float32),
        rewards=np.ones((t, n)),
        next_observations=np.arange(t * n * 1, dtype=np.float64).reshape(t, n, 1) + 100,
        terminations=np.zeros((t, n), bool),
        truncations=np.zeros((t, n), bool),
    )
    block.terminations[1, 0] = True  # env 0: episodes of 2 and 3 steps; env 1: one cut episode
    episodes = split_episodes(block)
    assert [len(e["rewards"]) for e in episodes] == [2, 3, 5]
    assert [bool(e["terminations"][-1]) for e in episodes] == [True, False, False]
    assert [bool(e["truncations"][-1]) for e in episodes] == [False, True, True]
    # the last observation of an episode is the next observation of its last step
    assert episodes[0]["observations"][-1, 0] == block.next_observations[1, 0, 0]
    assert episodes[2]["observations"].shape == (6, 1)
