"""The simulator as ground truth: safe env construction, state restoration, stepping."""

import sys

import gymnasium as gym
import numpy as np
import pytest

from hipode_pipeline.errors import DataFormatError, HipodeError
from hipode_pipeline.simulator import (
    check_env_id,
    clipped_velocity_rows,
    make_env_safely,
    policy_returns,
    set_state_from_observation,
    step_from_observations,
)


def real_rollout(env_id: str, steps: int, seed: int, action_scale: float = 1.0):
    """Transitions of a real gymnasium rollout with seeded random actions, resetting on
    termination or truncation: (observations, actions, rewards, next_observations, terminated)."""
    env = gym.make(env_id)
    rng = np.random.default_rng(seed)
    observation, _ = env.reset(seed=seed)
    rows = []
    for t in range(steps):
        action = (action_scale * rng.uniform(-1, 1, env.action_space.shape)).astype(np.float32)
        next_observation, reward, terminated, truncated, _ = env.step(action)
        rows.append((observation, action, reward, next_observation, terminated))
        observation = next_observation
        if terminated or truncated:
            observation, _ = env.reset(seed=seed + t + 1)
    env.close()
    return tuple(np.array(column) for column in zip(*rows, strict=True))


@pytest.mark.parametrize("env_id", ["Hopper-v5", "Walker2d-v5", "HalfCheetah-v5"])
def test_replaying_real_transitions_reproduces_them(env_id):
    observations, actions, rewards, next_observations, terminated = real_rollout(
        env_id, 150, seed=3, action_scale=0.5
    )
    assert terminated.any() or env_id == "HalfCheetah-v5"
    sim_next, sim_rewards, sim_terminated = step_from_observations(env_id, observations, actions)
    # velocities the env clipped in its observation cannot be restored exactly
    exact = ~clipped_velocity_rows(env_id, observations)
    assert exact.sum() >= 50
    np.testing.assert_allclose(sim_next[exact], next_observations[exact], atol=1e-8, rtol=0)
    np.testing.assert_allclose(sim_rewards[exact], rewards[exact], atol=1e-8, rtol=0)
    np.testing.assert_array_equal(sim_terminated[exact], terminated[exact])
    # stored as float32 (as datasets are), the answer moves by rounding only
    sim32, _, _ = step_from_observations(env_id, observations.astype(np.float32), actions)
    assert np.abs(sim32[exact] - next_observations[exact]).max() < 1e-2


def test_row_order_does_not_matter():
    observations, actions, *_ = real_rollout("Hopper-v5", 40, seed=5)
    forward, _, _ = step_from_observations("Hopper-v5", observations, actions)
    backward, _, _ = step_from_observations("Hopper-v5", observations[::-1], actions[::-1])
    np.testing.assert_array_equal(forward, backward[::-1])


def test_x_position_is_restored_as_zero_and_state_from_observation():
    env = make_env_safely("Hopper-v5")
    env.reset(seed=0)
    observation = np.linspace(-0.5, 0.5, 11)
    observation[0] = 1.25
    set_state_from_observation(env, observation)
    data = env.unwrapped.data
    assert data.qpos[0] == 0.0
    np.testing.assert_array_equal(data.qpos[1:], observation[:5])
    np.testing.assert_array_equal(data.qvel, observation[5:])
    np.testing.assert_allclose(env.unwrapped._get_obs(), observation)
    with pytest.raises(DataFormatError, match="shape"):
        set_state_from_observation(env, observation[:10])
    env.close()


def test_wrong_layout_and_unsupported_envs_are_refused():
    observations, actions, *_ = real_rollout("Hopper-v5", 5, seed=0)
    with pytest.raises(DataFormatError, match="observations"):
        step_from_observations("Walker2d-v5", observations, np.zeros((5, 6)))
    with pytest.raises(DataFormatError, match="actions"):
        step_from_observations("Hopper-v5", observations, actions[:, :2])
    # safe (gymnasium's own) but its state is not restorable from an observation
    with pytest.raises(DataFormatError, match="env_id"):
        step_from_observations("CartPole-v1", observations, actions)


@pytest.fixture
def foreign_module(tmp_path, monkeypatch):
    """An importable module outside gymnasium whose import would be visible in sys.modules."""
    name = "hipode_foreign_env_probe"
    (tmp_path / f"{name}.py").write_text(
        "import gymnasium\nclass ProbeEnv(gymnasium.Env):\n    pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop(name, None)
    gym.register(id="ForeignProbe-v0", entry_point=f"{name}:ProbeEnv")
    yield name
    gym.envs.registry.pop("ForeignProbe-v0", None)
    sys.modules.pop(name, None)


def test_unsafe_env_ids_are_refused_without_import(foreign_module):
    for env_id in ("ForeignProbe-v0", f"{foreign_module}:ForeignProbe-v0", "NoSuchEnv-v9", ""):
        with pytest.raises(HipodeError, match="refused"):
            make_env_safely(env_id)
        with pytest.raises(DataFormatError) as caught:
            make_env_safely(env_id, origin="some/artifact.hdf5")
        assert caught.value.path == "some/artifact.hdf5" and caught.value.field == "env_id"
        assert foreign_module not in sys.modules
    with pytest.raises(DataFormatError, match="foreign entry point"):
        check_env_id("ForeignProbe-v0", origin="x.hdf5")
    with pytest.raises(DataFormatError, match="module path"):
        check_env_id(f"{foreign_module}:ProbeEnv", origin="x.hdf5")
    with pytest.raises(DataFormatError, match="non-empty string"):
        check_env_id(None, origin="x.hdf5")
    assert foreign_module not in sys.modules
    # the same module is importable, so the refusal above is what kept it out
    env = make_env_safely("Hopper-v5")
    assert env.spec.id == "Hopper-v5"
    env.close()


def test_policy_returns_replay_a_real_episode_from_its_states():
    env_id, horizon, discount = "Hopper-v5", 12, 0.9
    weights = np.random.default_rng(7).normal(0, 0.6, (11, 3))

    def policy(observations):  # deterministic: the same action at the same state
        return np.tanh(np.asarray(observations, np.float64) @ weights)

    env = gym.make(env_id)
    observation, _ = env.reset(seed=4)
    observations, rewards, ends = [], [], []
    for _ in range(200):
        observations.append(observation)
        observation, reward, terminated, truncated, _ = env.step(policy(observation[None])[0])
        rewards.append(reward)
        ends.append(terminated)
        if terminated or truncated:
            break
    env.close()
    assert ends[-1]  # the episode falls, so some starts' returns end at the fall
    observations = np.array(observations)
    starts = [
        t
        for t in range(len(observations))
        if not clipped_velocity_rows(env_id, observations[t : t + 1])[0]
    ]
    returns, steps = policy_returns(
        env_id, observations[starts], policy, horizon=horizon, discount=discount
    )
    for i, t in enumerate(starts):
        span = rewards[t : t + horizon]
        assert steps[i] == len(span)
        expected = sum(discount**k * r for k, r in enumerate(span))
        assert returns[i] == pytest.approx(expected, rel=1e-6, abs=1e-6)
    assert steps.min() < horizon == steps.max()  # starts near the fall stop there
    with pytest.raises(HipodeError, match="horizon"):
        policy_returns(env_id, observations[:1], policy, horizon=0, discount=0.9)
    none, no_steps = policy_returns(env_id, observations[:0], policy, horizon=5, discount=0.9)
    assert none.shape == no_steps.shape == (0,)
