"""Synthetic terminal flags follow gymnasium's own termination rules on sampled MuJoCo states."""

import gymnasium as gym
import numpy as np
import pytest

from hipode_pipeline.envs import terminal_flags
from hipode_pipeline.errors import DataFormatError


def _sampled_states(env, rng: np.random.Generator, count: int):
    """Poses around the env's start with heights and angles spread across the healthy borders."""
    qpos = np.tile(env.init_qpos, (count, 1))
    qpos[:, 1] = rng.uniform(0.4, 2.3, count)  # torso height: below, inside and above the ranges
    # torso angle: half near Hopper's narrow border (0.2), half across Walker's (1.0)
    qpos[:, 2] = rng.uniform(-1.0, 1.0, count) * np.where(np.arange(count) % 2 == 0, 0.3, 1.5)
    qpos[:, 3:] = rng.uniform(-1.0, 1.0, (count, env.model.nq - 3))
    qvel = rng.uniform(-8.0, 8.0, (count, env.model.nv))
    return qpos, qvel


@pytest.mark.parametrize("env_id", ["Hopper-v5", "Walker2d-v5", "HalfCheetah-v5"])
def test_rule_matches_env_is_healthy(env_id):
    env = gym.make(env_id).unwrapped
    qpos, qvel = _sampled_states(env, np.random.default_rng(0), 400)
    observations, expected = [], []
    for p, v in zip(qpos, qvel, strict=True):
        env.set_state(p, v)
        observations.append(env._get_obs())
        # HalfCheetah has no health check: it never terminates
        expected.append(not env.is_healthy if hasattr(env, "is_healthy") else False)
    expected = np.array(expected)
    got = terminal_flags(env_id, np.array(observations, dtype=np.float32))
    assert got.dtype == np.bool_
    np.testing.assert_array_equal(got, expected)
    if env_id != "HalfCheetah-v5":
        # the sample must exercise both outcomes, or agreement proves nothing
        assert 0.1 < expected.mean() < 0.9


@pytest.mark.parametrize("env_id", ["Hopper-v5", "Walker2d-v5", "HalfCheetah-v5"])
def test_rule_matches_terminated_after_a_step(env_id):
    env = gym.make(env_id)
    rng = np.random.default_rng(1)
    inner = env.unwrapped
    qpos, qvel = _sampled_states(inner, rng, 150)
    env.reset(seed=1)
    next_observations, terminated = [], []
    for p, v in zip(qpos, qvel, strict=True):
        inner.set_state(p, v)
        obs, _, term, _, _ = inner.step(rng.uniform(-1, 1, env.action_space.shape))
        next_observations.append(obs)
        terminated.append(term)
    np.testing.assert_array_equal(terminal_flags(env_id, np.array(next_observations)), terminated)


def test_unknown_env_and_wrong_layout_are_rejected():
    with pytest.raises(DataFormatError, match="env_id"):
        terminal_flags("Ant-v5", np.zeros((3, 27)), origin="demo.hdf5")
    with pytest.raises(DataFormatError, match="11 columns"):
        # x position included: the rule would read the wrong columns
        terminal_flags("Hopper-v5", np.zeros((3, 12)), origin="demo.hdf5")
