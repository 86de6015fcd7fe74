"""A few MuJoCo envs stepped one by one, for the behaviour-policy trainers.

No vector-env autoreset: every transition keeps its exact next observation, termination and
truncation (the time limit is applied here, so it can be checkpointed with the physics state).
"""

from __future__ import annotations

import json
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
import torch

from hipode_pipeline.simulator import make_env_safely

STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION  # physics state incl. solver warm-start


def make_env(env_id: str) -> tuple[gym.Env, int]:
    """The bare MuJoCo env and its time limit (applied by us, so it can be checkpointed)."""
    env = make_env_safely(env_id)
    return env.unwrapped, int(env.spec.max_episode_steps)


def rng_from_state(state: dict[str, Any]) -> np.random.Generator:
    rng = np.random.Generator(np.random.PCG64())
    rng.bit_generator.state = state
    return rng


class EnvBatch:
    """`num_envs` envs of `env_id`, env i first reset with seed `seed * 1000 + i`."""

    def __init__(self, env_id: str, num_envs: int, seed: int):
        made = [make_env(env_id) for _ in range(num_envs)]
        self.envs, self.time_limit = [e for e, _ in made], made[0][1]
        space = self.envs[0].action_space
        self.low, self.high = space.low, space.high
        # each env gets its own seed once; later resets draw from the env's own generator
        self.obs = np.stack([env.reset(seed=seed * 1000 + i)[0] for i, env in enumerate(self.envs)])
        self.obs_dim, self.act_dim = int(self.obs.shape[1]), int(space.shape[0])
        self.episode_steps = np.zeros(num_envs, np.int64)
        self.episode_returns = np.zeros(num_envs, np.float64)

    def __len__(self) -> int:
        return len(self.envs)

    def clip(self, raw_actions: np.ndarray) -> np.ndarray:
        return np.clip(raw_actions, self.low, self.high)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, ...]:
        """Step env i with actions[i] (already clipped); ended episodes reset.

        Returns next observations (the true ones, before any reset), rewards, terminations,
        truncations and the returns of the episodes that ended at this step.
        """
        n = len(self.envs)
        next_obs = np.empty((n, self.obs_dim))
        rewards = np.empty(n)
        terminations = np.zeros(n, bool)
        for i, env in enumerate(self.envs):
            observation, reward, terminated, _, _ = env.step(actions[i])
            next_obs[i], rewards[i], terminations[i] = observation, reward, terminated
        # a new array: callers may still hold the observations this step acted on
        self.obs = next_obs.copy()
        self.episode_steps += 1
        truncations = ~terminations & (self.episode_steps >= self.time_limit)
        self.episode_returns += rewards
        ended = terminations | truncations
        finished = self.episode_returns[ended].tolist()
        for i in np.flatnonzero(ended):
            self.obs[i] = self.envs[i].reset()[0]
        self.episode_returns[ended], self.episode_steps[ended] = 0.0, 0
        return next_obs, rewards, terminations, truncations, finished

    def state_dict(self) -> dict[str, Any]:
        size = mujoco.mj_stateSize(self.envs[0].model, STATE_SPEC)
        physics = np.empty((len(self.envs), size))
        for i, env in enumerate(self.envs):
            mujoco.mj_getState(env.model, env.data, physics[i], STATE_SPEC)
        return {
            "physics": torch.from_numpy(physics),
            "env_rngs": json.dumps([env.np_random.bit_generator.state for env in self.envs]),
            "obs": torch.from_numpy(self.obs.copy()),
            "episode_steps": torch.from_numpy(self.episode_steps.copy()),
            "episode_returns": torch.from_numpy(self.episode_returns.copy()),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for env, rng_state, physics in zip(
            self.envs, json.loads(state["env_rngs"]), state["physics"].numpy(), strict=True
        ):
            env.np_random = rng_from_state(rng_state)
            mujoco.mj_setState(env.model, env.data, physics, STATE_SPEC)
        self.obs = state["obs"].numpy().copy()
        self.episode_steps = state["episode_steps"].numpy().copy()
        self.episode_returns = state["episode_returns"].numpy().copy()
