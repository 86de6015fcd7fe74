"""Evaluation in a real MuJoCo env: fixed seeds, batched episodes, D4RL-normalized scores."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from hipode_pipeline.errors import HipodeError
from hipode_pipeline.evaluate import evaluate_policy, evaluation_seeds, normalized_score
from hipode_pipeline.tasks import get_task


def fixed_policy(observations: np.ndarray) -> np.ndarray:
    """A deterministic function of the observation, so returns depend only on the start states."""
    return np.tanh(observations[:, :3] * 3.0)


def test_hopper_rollouts_are_reproducible_and_match_sequential_episodes():
    task = get_task("hopper-m-r")
    result = evaluate_policy(
        fixed_policy,
        "Hopper-v5",
        episodes=3,
        seed=2,
        ref_min_score=task.ref_min_score,
        ref_max_score=task.ref_max_score,
        max_episode_steps=60,
    )
    again = evaluate_policy(fixed_policy, "Hopper-v5", episodes=3, seed=2, max_episode_steps=60)
    assert result.returns == again.returns and again.score_mean is None
    assert result.seeds == evaluation_seeds(2, 3) == [2000, 2001, 2002]
    # stepping the episodes together gives what one-at-a-time episodes give
    for seed, expected in zip(result.seeds, result.returns, strict=True):
        env = gym.make("Hopper-v5")
        obs, _ = env.reset(seed=seed)
        total, steps, done = 0.0, 0, False
        while not done and steps < 60:
            obs, reward, terminated, truncated, _ = env.step(
                fixed_policy(obs[None].astype(np.float32))[0]
            )
            total, steps, done = total + reward, steps + 1, terminated or truncated
        assert total == pytest.approx(expected)
    scores = [task.normalized_score(r) for r in result.returns]
    assert result.score_mean == pytest.approx(np.mean(scores))
    assert result.score_std == pytest.approx(np.std(scores))
    assert result.return_mean == pytest.approx(np.mean(result.returns))


def test_different_seeds_meet_different_starts():
    a = evaluate_policy(fixed_policy, "Hopper-v5", episodes=2, seed=0, max_episode_steps=30)
    b = evaluate_policy(fixed_policy, "Hopper-v5", episodes=2, seed=1, max_episode_steps=30)
    assert a.returns != b.returns


def test_normalized_score_endpoints():
    assert normalized_score(-20.0, -20.0, 80.0) == 0.0
    assert normalized_score(80.0, -20.0, 80.0) == 100.0


def test_module_paths_as_env_ids_are_refused():
    with pytest.raises(HipodeError, match="module path"):
        evaluate_policy(fixed_policy, "os:system", episodes=1)


def test_a_sampling_policy_is_asked_only_for_running_episodes():
    """A policy that draws random numbers sees exactly the episodes still running, so its draws
    (and a behaviour policy's measured return) do not depend on finished ones."""
    sizes = []
    rng = np.random.default_rng(0)

    def noisy(observations):
        sizes.append(len(observations))
        return rng.uniform(-1, 1, (len(observations), 3))

    result = evaluate_policy(noisy, "Hopper-v5", episodes=4, seed=0)
    lengths = sorted(result.lengths)
    # with 4 episodes of lengths l1 <= ... <= l4, the batch shrinks by one at each ending
    expected = [sum(1 for length in lengths if length > t) for t in range(lengths[-1])]
    assert sizes == expected and len(set(lengths)) > 1
