"""Adroit (the `adroit` extra, gymnasium-robotics): the human-demonstration tasks run through
stage one and stage two from a Minari dataset in the local store, and a missing extra is a clear
error. Tests that need the extra skip cleanly without it; the missing-extra tests always run."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from builders import make_minari_dataset
from test_train_cli import TINY
from typer.testing import CliRunner

import hipode_pipeline.train as train_module
from hipode_pipeline.artifact import read_artifact
from hipode_pipeline.cli import app
from hipode_pipeline.envs import ADROIT_OBS_DIM, termination_rule
from hipode_pipeline.errors import DataFormatError, MissingExtraError, UnsafeEnvError
from hipode_pipeline.evaluate import evaluate_policies, evaluate_policy
from hipode_pipeline.simulator import check_env_id, make_env_safely
from hipode_pipeline.tasks import get_task

HAS_EXTRA = importlib.util.find_spec("gymnasium_robotics") is not None
needs_extra = pytest.mark.skipif(
    not HAS_EXTRA, reason="the adroit extra (gymnasium-robotics) is not installed"
)
ADROIT_TASKS = ("pen-h", "door-h", "hammer-h", "relocate-h")


def random_policy_episodes(env_id: str, episodes: int, steps: int, seed: int) -> list[dict]:
    """Episodes of uniform random actions in the real env, cut (truncated) after `steps`."""
    env = make_env_safely(env_id)
    rng = np.random.default_rng(seed)
    out = []
    try:
        for episode in range(episodes):
            observations = [env.reset(seed=seed * 1000 + episode)[0]]
            actions = rng.uniform(-1.0, 1.0, size=(steps, *env.action_space.shape))
            actions = actions.astype(np.float32)
            rewards, terminations = np.zeros(steps), np.zeros(steps, dtype=bool)
            for t in range(steps):
                obs, rewards[t], terminations[t], _, _ = env.step(actions[t])
                observations.append(obs)
            truncations = np.zeros(steps, dtype=bool)
            truncations[-1] = True
            out.append(
                {
                    "observations": np.asarray(observations),
                    "actions": actions,
                    "rewards": rewards,
                    "terminations": terminations,
                    "truncations": truncations,
                }
            )
    finally:
        env.close()
    return out


def write_pen_human(episodes: int = 6, steps: int = 40) -> None:
    """A tiny stand-in for Minari's D4RL/pen/human-v2 (random actions) in the local store."""
    task = get_task("pen-h")
    data = random_policy_episodes(task.env_id, episodes, steps, seed=0)
    make_minari_dataset(
        task.local_dataset_id,
        data,
        env_id=task.env_id,
        ref_min_score=task.ref_min_score,
        ref_max_score=task.ref_max_score,
    )


def test_adroit_tasks_read_minaris_d4rl_ids():
    assert [get_task(name).local_dataset_id for name in ADROIT_TASKS] == [
        "D4RL/pen/human-v2",
        "D4RL/door/human-v2",
        "D4RL/hammer/human-v2",
        "D4RL/relocate/human-v2",
    ]


@needs_extra
@pytest.mark.parametrize("name", ADROIT_TASKS)
def test_adroit_envs_match_the_registry_and_never_terminate(name):
    task = get_task(name)
    env = make_env_safely(task.env_id)
    try:
        obs, _ = env.reset(seed=0)
        assert obs.shape == (ADROIT_OBS_DIM[task.env_id.split("-v")[0]],)
        rng = np.random.default_rng(0)
        rows = [obs]
        for _ in range(30):
            obs, _, terminated, _, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
            assert not terminated
            rows.append(obs)
    finally:
        env.close()
    rule = termination_rule(task.env_id, obs.shape[0])
    # far outside anything the hand reaches: still no termination (the env has none)
    states = np.concatenate([np.asarray(rows), 1e3 * np.ones((1, obs.shape[0]))])
    assert not rule(states).any()
    with pytest.raises(DataFormatError, match=f"{obs.shape[0]} columns"):
        termination_rule(task.env_id, obs.shape[0] + 1)


@needs_extra
def test_only_gymnasium_robotics_adroit_hands_are_built():
    check_env_id("AdroitHandPen-v1")
    fetch = next(k for k in gym.envs.registry if k.startswith("FetchReach"))
    with pytest.raises(UnsafeEnvError, match="foreign entry point"):
        check_env_id(fetch)


@needs_extra
def test_pen_evaluation_stops_at_d4rls_horizon():
    task = get_task("pen-h")
    assert task.max_episode_steps == 100 and gym.spec(task.env_id).max_episode_steps == 200
    result = evaluate_policy(
        lambda obs: np.zeros(24, dtype=np.float32),
        task.env_id,
        episodes=2,
        max_episode_steps=task.max_episode_steps,
    )
    assert result.lengths == [100, 100]


@needs_extra
def test_pen_human_runs_through_quick_augment_and_training(tmp_path, dataset_root, monkeypatch):
    write_pen_human()
    lengths = []

    def evaluate_recording(*args, **kwargs):
        results = evaluate_policies(*args, **kwargs)
        lengths.extend(length for result in results for length in result.lengths)
        return results

    monkeypatch.setattr(train_module, "evaluate_policies", evaluate_recording)
    runner = CliRunner()
    augmented = runner.invoke(
        app, ["augment", "pen-h", "--profile", "quick", "--set", "dynamics_members=3", "--json"]
    )
    assert augmented.exit_code == 0, augmented.output
    # what it is about to do, before it trains: data, settings, what differs from the profile
    assert "stage one on pen-h: D4RL/pen/human-v2 (240 rows, AdroitHandPen-v1)" in augmented.stderr
    assert "eta 0.8" in augmented.stderr and "with dynamics_members=3" in augmented.stderr
    summary = json.loads(augmented.stdout)
    assert summary["source_id"] == "D4RL/pen/human-v2" and summary["kept"] > 0
    artifact = read_artifact(Path(summary["artifact"]))
    assert len(artifact) == summary["kept"]
    # the hand never terminates, so neither does any synthetic transition
    assert summary["terminals"] == 0 and not artifact.transitions.terminals.any()
    trained = runner.invoke(
        app,
        [
            "train",
            "pen-h",
            *TINY,
            "--out",
            str(tmp_path / "runs"),
            "--json",
        ],
    )
    assert trained.exit_code == 0, trained.output
    scores = json.loads(trained.stdout)
    assert [e["step"] for e in scores["evaluations"]] == [10, 20]
    assert all(np.isfinite(e["score_mean"]) for e in scores["evaluations"])
    config = json.loads((Path(scores["run_dir"]) / "config.json").read_text())
    # Table 6's TD3+BC alpha for Adroit, D4RL's pen horizon
    assert config["learner_config"]["alpha"] == 0.001
    assert config["eval_max_episode_steps"] == 100 and config["n_synthetic"] > 0
    assert lengths == [100] * 4  # 2 evaluations of 2 episodes


@pytest.fixture
def without_extra(monkeypatch):
    """As if gymnasium-robotics were not installed: no Adroit ids, and its import fails."""
    for env_id in [k for k in gym.envs.registry if k.startswith("AdroitHand")]:
        monkeypatch.delitem(gym.envs.registry, env_id)
    monkeypatch.setitem(sys.modules, "gymnasium_robotics", None)


def test_missing_extra_is_named(without_extra):
    with pytest.raises(MissingExtraError, match=r"pip install -e '\.\[adroit\]'"):
        check_env_id("AdroitHandDoor-v1")


def test_augment_without_extra_fails_before_training(without_extra, dataset_root):
    task = get_task("pen-h")
    make_minari_dataset(
        task.local_dataset_id,
        [
            {
                "observations": np.zeros((11, 45)),
                "actions": np.zeros((10, 24), dtype=np.float32),
                "rewards": np.zeros(10),
                "terminations": np.zeros(10, dtype=bool),
                "truncations": np.eye(10, dtype=bool)[-1],
            }
        ]
        * 3,
        env_id=task.env_id,
    )
    result = CliRunner().invoke(app, ["augment", "pen-h", "--profile", "quick"])
    assert result.exit_code == 2
    assert "adroit" in result.output and "gymnasium-robotics" in result.output
    assert not (dataset_root / "artifacts").exists()


def test_missing_pen_dataset_says_where_to_get_it(dataset_root):
    result = CliRunner().invoke(app, ["augment", "pen-h", "--profile", "quick"])
    assert result.exit_code == 2
    assert "D4RL/pen/human-v2" in result.output and "minari download" in result.output
