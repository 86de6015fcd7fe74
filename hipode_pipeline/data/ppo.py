"""PPO for MuJoCo locomotion: the behaviour-policy trainer behind `hipode collect`.

Clipped-objective PPO with GAE, running observation normalization and reward scaling. The
environments are stepped one by one here (no vector-env autoreset), so every transition keeps
its exact next observation, termination and truncation; those transitions are what
medium-replay datasets are made of. A checkpoint holds everything needed to continue
bit-for-bit: weights, optimizer, normalizers, RNG states and each environment's physics state.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from hipode_pipeline.data.env_batch import EnvBatch
from hipode_pipeline.data.trainer_base import BehaviourTrainer, TrainerConfig
from hipode_pipeline.files import load_torch


@dataclass(frozen=True)
class PPOConfig(TrainerConfig):
    """PPO settings; the defaults are the plain recipe measured in DESIGN.md."""

    num_envs: int = 8  # environments stepped side by side
    rollout_steps: int = 256  # steps per environment between updates
    hidden: int = 64  # width of both hidden layers (actor and critic)
    learning_rate: float = 3e-4  # Adam step size at the start
    anneal_steps: int = (
        0  # decay the learning rate linearly to 0 over this many env steps; 0 = constant
    )
    gamma: float = 0.99  # discount
    gae_lambda: float = 0.95  # GAE's bias/variance trade-off
    epochs: int = 10  # passes over each rollout
    minibatch_size: int = 64  # transitions per gradient step
    clip_range: float = 0.2  # PPO's ratio clip
    value_coef: float = 0.5  # weight of the value loss
    entropy_coef: float = 0.0  # entropy bonus (0: the state-independent std shrinks on its own)
    max_grad_norm: float = 0.5  # gradient-norm clip
    init_log_std: float = 0.0  # initial log std of the Gaussian policy
    obs_clip: float = 10.0  # clip of normalized observations
    reward_clip: float = 10.0  # clip of scaled rewards


class RunningMeanStd:
    """Mean and variance of a stream of vectors, merged batch by batch (parallel Welford)."""

    def __init__(self, shape: tuple[int, ...]):
        self.mean = np.zeros(shape, np.float64)
        self.var = np.ones(shape, np.float64)
        self.count = 1e-4

    def update(self, batch: np.ndarray) -> None:
        batch_mean, batch_var, n = batch.mean(axis=0), batch.var(axis=0), batch.shape[0]
        delta, total = batch_mean - self.mean, self.count + n
        self.mean = self.mean + delta * n / total
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        self.var, self.count = m2 / total, total

    def state_dict(self) -> dict[str, Any]:
        return {
            "mean": torch.from_numpy(np.array(self.mean, np.float64)),
            "var": torch.from_numpy(np.array(self.var, np.float64)),
            "count": float(self.count),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.mean, self.var = state["mean"].numpy().copy(), state["var"].numpy().copy()
        self.count = float(state["count"])


def _mlp(sizes: list[int], out_gain: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        linear = nn.Linear(a, b)
        last = i == len(sizes) - 2
        # orthogonal init with a small output gain keeps early actions near zero
        nn.init.orthogonal_(linear.weight, out_gain if last else math.sqrt(2))
        nn.init.zeros_(linear.bias)
        layers += [linear] if last else [linear, nn.Tanh()]
    return nn.Sequential(*layers)


class ActorCritic(nn.Module):
    """Gaussian policy with a state-independent std, and a separate value network."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: int, init_log_std: float):
        super().__init__()
        self.actor = _mlp([obs_dim, hidden, hidden, act_dim], out_gain=0.01)
        self.critic = _mlp([obs_dim, hidden, hidden, 1], out_gain=1.0)
        self.log_std = nn.Parameter(torch.full((act_dim,), float(init_log_std)))

    def log_prob_value(self, obs: torch.Tensor, raw_actions: torch.Tensor):
        mean = self.actor(obs)
        dist = torch.distributions.Normal(mean, self.log_std.exp())
        return (
            dist.log_prob(raw_actions).sum(-1),
            dist.entropy().sum(-1),
            self.critic(obs).squeeze(-1),
        )


class GaussianPolicy:
    """A frozen snapshot of the actor with its observation normalizer, run in numpy.

    Numpy inference of a 64-wide MLP is about twice as fast as torch at these batch sizes.
    """

    def __init__(
        self,
        layers: list[tuple[np.ndarray, np.ndarray]],
        log_std: np.ndarray,
        obs_mean: np.ndarray,
        obs_var: np.ndarray,
        obs_clip: float,
    ):
        self.layers, self.std = layers, np.exp(log_std)
        self.obs_mean, self.obs_scale, self.obs_clip = (
            obs_mean,
            1.0 / np.sqrt(obs_var + 1e-8),
            obs_clip,
        )

    @classmethod
    def from_model(
        cls, model: ActorCritic, obs_rms: RunningMeanStd, obs_clip: float
    ) -> GaussianPolicy:
        linears = [m for m in model.actor if isinstance(m, nn.Linear)]
        layers = [
            (
                m.weight.detach().numpy().T.astype(np.float64),
                m.bias.detach().numpy().astype(np.float64),
            )
            for m in linears
        ]
        return cls(
            layers,
            model.log_std.detach().numpy().astype(np.float64),
            obs_rms.mean.copy(),
            obs_rms.var.copy(),
            obs_clip,
        )

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        return np.clip((obs - self.obs_mean) * self.obs_scale, -self.obs_clip, self.obs_clip)

    def mean_action(self, obs: np.ndarray) -> np.ndarray:
        x = self.normalize(obs)
        for i, (w, b) in enumerate(self.layers):
            x = x @ w + b
            if i < len(self.layers) - 1:
                x = np.tanh(x)
        return x

    def sample(
        self, obs: np.ndarray, rng: np.random.Generator, deterministic: bool = False
    ) -> np.ndarray:
        """Unclipped Gaussian actions for a batch of raw observations."""
        mean = self.mean_action(obs)
        return mean if deterministic else mean + self.std * rng.standard_normal(mean.shape)

    def state_dict(self) -> dict[str, Any]:
        return {
            "class": "gaussian",
            "weights": [torch.from_numpy(w.copy()) for w, _ in self.layers],
            "biases": [torch.from_numpy(b.copy()) for _, b in self.layers],
            "log_std": torch.from_numpy(np.log(self.std)),
            "obs_mean": torch.from_numpy(self.obs_mean.copy()),
            "obs_var": torch.from_numpy(self.obs_var.copy()),
            "obs_clip": float(self.obs_clip),
        }

    @property
    def obs_var(self) -> np.ndarray:
        return 1.0 / self.obs_scale**2 - 1e-8

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> GaussianPolicy:
        layers = [
            (w.numpy(), b.numpy()) for w, b in zip(state["weights"], state["biases"], strict=True)
        ]
        return cls(
            layers,
            state["log_std"].numpy(),
            state["obs_mean"].numpy(),
            state["obs_var"].numpy(),
            state["obs_clip"],
        )


# ---- checkpoint files ------------------------------------------------------------------------


def load_checkpoint(path: Path) -> dict[str, Any]:
    return load_torch(path, "a checkpoint written by hipode collect")


@dataclass
class RolloutBlock:
    """Raw transitions of one rollout, laid out (step, env); observations as the env gives them."""

    observations: np.ndarray  # (T, N, obs_dim) float64
    actions: np.ndarray  # (T, N, act_dim) float32, clipped to the action space as executed
    rewards: np.ndarray  # (T, N) float64, raw env rewards
    next_observations: np.ndarray  # (T, N, obs_dim) float64
    terminations: np.ndarray  # (T, N) bool
    truncations: np.ndarray  # (T, N) bool

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def empty(cls, steps: int, num_envs: int, obs_dim: int, act_dim: int) -> RolloutBlock:
        return cls(
            observations=np.empty((steps, num_envs, obs_dim)),
            actions=np.empty((steps, num_envs, act_dim), np.float32),
            rewards=np.empty((steps, num_envs)),
            next_observations=np.empty((steps, num_envs, obs_dim)),
            terminations=np.zeros((steps, num_envs), bool),
            truncations=np.zeros((steps, num_envs), bool),
        )

    def record(self, t: int, observations, actions, step: tuple[np.ndarray, ...]) -> list[float]:
        """Store step t (EnvBatch.step's result); returns the returns of the ended episodes."""
        next_obs, rewards, terminations, truncations, finished = step
        self.observations[t], self.actions[t] = observations, actions
        self.next_observations[t], self.rewards[t] = next_obs, rewards
        self.terminations[t], self.truncations[t] = terminations, truncations
        return finished


class PPOTrainer(BehaviourTrainer):
    """PPO over a list of environments; `train_iteration()` is one rollout plus one update."""

    name = "PPO"

    def __init__(self, env_id: str, config: PPOConfig, seed: int, recent_episodes: int = 20):
        super().__init__(env_id, config, seed, recent_episodes)
        torch.manual_seed(seed)
        self.envs = EnvBatch(env_id, config.num_envs, seed)
        self.obs_dim, self.act_dim = self.envs.obs_dim, self.envs.act_dim
        self.model = ActorCritic(self.obs_dim, self.act_dim, config.hidden, config.init_log_std)
        self.optimizer = torch.optim.Adam(
            self.model.parameters(), lr=config.learning_rate, eps=1e-5
        )
        self.obs_rms = RunningMeanStd((self.obs_dim,))
        self.ret_rms = RunningMeanStd(())
        self.discounted_returns = np.zeros(config.num_envs, np.float64)
        self.obs_rms.update(self.envs.obs)

    # -- acting --------------------------------------------------------------------------------

    def policy(self) -> GaussianPolicy:
        return GaussianPolicy.from_model(self.model, self.obs_rms, self.config.obs_clip)

    def _collect(self) -> tuple[RolloutBlock, np.ndarray]:
        """Step every env `rollout_steps` times; returns raw transitions and unclipped actions."""
        c, n, envs = self.config, self.config.num_envs, self.envs
        block = RolloutBlock.empty(c.rollout_steps, n, self.obs_dim, self.act_dim)
        raw_actions = np.empty((c.rollout_steps, n, self.act_dim))
        policy = self.policy()
        for t in range(c.rollout_steps):
            raw = policy.sample(envs.obs, self.rng)
            clipped = envs.clip(raw)
            raw_actions[t] = raw
            finished = block.record(t, envs.obs, clipped, envs.step(clipped))
            self.recent_returns.extend(finished)
            self.episodes_done += len(finished)
            self.obs_rms.update(block.next_observations[t])
        self.steps += c.rollout_steps * n
        return block, raw_actions

    def _scaled_rewards(self, block: RolloutBlock) -> np.ndarray:
        """Rewards divided by the running std of the discounted return (per env stream)."""
        scaled = np.empty_like(block.rewards)
        for t in range(block.rewards.shape[0]):
            self.discounted_returns = self.discounted_returns * self.config.gamma + block.rewards[t]
            self.ret_rms.update(self.discounted_returns)
            ended = block.terminations[t] | block.truncations[t]
            self.discounted_returns[ended] = 0.0
        scale = np.sqrt(self.ret_rms.var + 1e-8)
        scaled[:] = np.clip(
            block.rewards / scale, -self.config.reward_clip, self.config.reward_clip
        )
        return scaled

    # -- learning ------------------------------------------------------------------------------

    def _learning_rate(self) -> float:
        c = self.config
        if c.anneal_steps <= 0:
            return c.learning_rate
        return c.learning_rate * max(0.0, 1.0 - self.steps / c.anneal_steps)

    def _update(
        self, block: RolloutBlock, raw_actions: np.ndarray, rewards: np.ndarray
    ) -> dict[str, float]:
        c = self.config
        t_len, n = rewards.shape
        policy = self.policy()  # normalizer as of the end of this rollout, for every forward pass
        obs = torch.as_tensor(
            policy.normalize(block.observations.reshape(t_len * n, -1)), dtype=torch.float32
        )
        next_obs = torch.as_tensor(
            policy.normalize(block.next_observations.reshape(t_len * n, -1)), dtype=torch.float32
        )
        actions = torch.as_tensor(raw_actions.reshape(t_len * n, -1), dtype=torch.float32)
        with torch.no_grad():
            old_log_prob, _, values = self.model.log_prob_value(obs, actions)
            next_values = self.model.critic(next_obs).squeeze(-1)
        values_np = values.numpy().reshape(t_len, n)
        next_values_np = next_values.numpy().reshape(t_len, n)
        # truncated steps bootstrap from their true next state; terminated ones do not
        deltas = rewards + c.gamma * next_values_np * ~block.terminations - values_np
        ended = block.terminations | block.truncations
        advantages = np.zeros_like(deltas)
        running = np.zeros(n)
        for t in reversed(range(t_len)):
            running = deltas[t] + c.gamma * c.gae_lambda * ~ended[t] * running
            advantages[t] = running
        returns = torch.as_tensor((advantages + values_np).reshape(-1), dtype=torch.float32)
        adv = torch.as_tensor(advantages.reshape(-1), dtype=torch.float32)
        for group in self.optimizer.param_groups:
            group["lr"] = self._learning_rate()
        total, stats = t_len * n, {"policy_loss": 0.0, "value_loss": 0.0, "approx_kl": 0.0}
        updates = 0
        for _ in range(c.epochs):
            order = torch.as_tensor(self.rng.permutation(total))
            for start in range(0, total, c.minibatch_size):
                idx = order[start : start + c.minibatch_size]
                log_prob, entropy, value = self.model.log_prob_value(obs[idx], actions[idx])
                mb_adv = adv[idx]
                mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
                log_ratio = log_prob - old_log_prob[idx]
                ratio = log_ratio.exp()
                policy_loss = -torch.min(
                    ratio * mb_adv, ratio.clamp(1 - c.clip_range, 1 + c.clip_range) * mb_adv
                ).mean()
                value_loss = 0.5 * (value - returns[idx]).pow(2).mean()
                loss = policy_loss + c.value_coef * value_loss - c.entropy_coef * entropy.mean()
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                nn.utils.clip_grad_norm_(self.model.parameters(), c.max_grad_norm)
                self.optimizer.step()
                with torch.no_grad():
                    stats["policy_loss"] += float(policy_loss)
                    stats["value_loss"] += float(value_loss)
                    stats["approx_kl"] += float(((ratio - 1) - log_ratio).mean())
                updates += 1
        return {k: v / max(updates, 1) for k, v in stats.items()}

    def train_iteration(self) -> tuple[RolloutBlock, dict[str, float]]:
        """One rollout and one PPO update; returns the raw transitions of the rollout."""
        block, raw_actions = self._collect()
        stats = self._update(block, raw_actions, self._scaled_rewards(block))
        self.iteration += 1
        return block, stats

    # -- checkpoints ---------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            **self.progress_state(),
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "obs_rms": self.obs_rms.state_dict(),
            "ret_rms": self.ret_rms.state_dict(),
            "torch_rng": torch.get_rng_state(),
            **self.envs.state_dict(),  # the envs' keys at the top level, as before EnvBatch
            "discounted_returns": torch.from_numpy(self.discounted_returns.copy()),
        }

    def load_state_dict(self, state: dict[str, Any], origin: str | Path = "checkpoint") -> None:
        self.load_progress(state, origin)
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.obs_rms.load_state_dict(state["obs_rms"])
        self.ret_rms.load_state_dict(state["ret_rms"])
        torch.set_rng_state(state["torch_rng"])
        self.envs.load_state_dict(state)
        self.discounted_returns = state["discounted_returns"].numpy().copy()


# ---- rollouts of a fixed policy ----------------------------------------------------------------

ActionFn = Callable[[np.ndarray, np.random.Generator], np.ndarray]


def run_policy(
    env_id: str,
    act: ActionFn,
    steps_per_env: int,
    num_envs: int,
    seed: int,
    on_step: Callable[[int, list[float]], None] | None = None,
) -> RolloutBlock:
    """Step `num_envs` envs `steps_per_env` times with `act(raw_obs, rng) -> actions`.

    Episodes reset as they end; the last step of each env's stream is left as is (the caller
    marks the cut). `on_step(steps_done, finished_returns)` feeds progress displays.
    """
    rng = np.random.default_rng(seed)
    envs = EnvBatch(env_id, num_envs, seed)
    block = RolloutBlock.empty(steps_per_env, num_envs, envs.obs_dim, envs.act_dim)
    for t in range(steps_per_env):
        actions = envs.clip(act(envs.obs, rng))
        finished = block.record(t, envs.obs, actions, envs.step(actions))
        if on_step is not None:
            on_step(t + 1, finished)
    return block
