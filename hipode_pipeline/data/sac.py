"""Soft actor-critic for MuJoCo locomotion: the behaviour-policy trainer D4RL used, for the envs
where PPO does not reach D4RL's bands here (stages/collect.toml `trainer`).

SAC with twin critics, a tanh-squashed Gaussian actor and a learned temperature, over a few envs
stepped side by side; each iteration steps every env `rollout_steps` times, then makes
`updates_per_step` gradient updates per new transition. The replay buffer holds every
transition from the first step, so the medium-replay data is the buffer up to the medium policy,
as D4RL's. A checkpoint holds everything needed to continue bit-for-bit: weights, optimizers,
the buffer, RNG states and each environment's physics state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from hipode_pipeline.data.env_batch import EnvBatch
from hipode_pipeline.data.ppo import RolloutBlock
from hipode_pipeline.data.trainer_base import BehaviourTrainer, TrainerConfig

LOG_STD_BOUNDS = (-5.0, 2.0)  # keeps the policy's std in [0.007, 7.4] (as rlkit and CleanRL)
MATMUL_DTYPES = {"float32": None, "bfloat16": torch.bfloat16}


def _float32_layer(layer, h: torch.Tensor) -> torch.Tensor:
    """The output layer outside autocast: Q values and log-densities keep float32's precision."""
    with torch.autocast("cpu", enabled=False):
        return layer(h.float())


@dataclass(frozen=True)
class SACConfig(TrainerConfig):
    """SAC settings (Haarnoja et al. 2018's and D4RL's, except the env count)."""

    CHOICES: ClassVar[dict[str, Any]] = {"matmul_dtype": MATMUL_DTYPES}

    num_envs: int = 4  # environments stepped side by side
    rollout_steps: int = 50  # steps per environment between update phases
    hidden: int = 256  # width of the two hidden layers (actor and both critics)
    batch_size: int = 256  # transitions per gradient update
    learning_rate: float = 3e-4  # Adam step size of actor, critics and temperature
    gamma: float = 0.99  # discount
    tau: float = 0.005  # Polyak rate of the target critics
    updates_per_step: float = 1.0  # gradient updates per env transition
    start_steps: int = 5_000  # env steps of uniform random actions before the policy acts
    init_temperature: float = 1.0  # entropy weight at the start (learned towards -act_dim)
    buffer_size: int = 3_000_000  # transitions kept (at least the training budget: none dropped)
    # hidden layers' matmuls in "bfloat16" (autocast; weights, outputs and losses stay float32)
    matmul_dtype: str = "float32"


class TanhGaussianPolicy:
    """A frozen snapshot of SAC's actor, run in numpy: tanh(N(mean(s), std(s))) in action units."""

    def __init__(
        self, layers: list[tuple[np.ndarray, np.ndarray]], low: np.ndarray, high: np.ndarray
    ):
        self.layers = layers
        self.low, self.high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        self.scale, self.center = (self.high - self.low) / 2, (self.high + self.low) / 2

    def mean_log_std(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = obs
        for i, (w, b) in enumerate(self.layers):
            x = x @ w + b
            if i < len(self.layers) - 1:
                x = np.maximum(x, 0.0)
        mean, log_std = np.split(x, 2, axis=-1)
        return mean, np.clip(log_std, *LOG_STD_BOUNDS)

    def sample(
        self, obs: np.ndarray, rng: np.random.Generator, deterministic: bool = False
    ) -> np.ndarray:
        """Actions for a batch of raw observations (the mode's tanh when `deterministic`)."""
        mean, log_std = self.mean_log_std(obs)
        u = mean if deterministic else mean + np.exp(log_std) * rng.standard_normal(mean.shape)
        return np.tanh(u) * self.scale + self.center

    def state_dict(self) -> dict[str, Any]:
        return {
            "class": "tanh_gaussian",
            "weights": [torch.from_numpy(w.copy()) for w, _ in self.layers],
            "biases": [torch.from_numpy(b.copy()) for _, b in self.layers],
            "low": torch.from_numpy(self.low.copy()),
            "high": torch.from_numpy(self.high.copy()),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> TanhGaussianPolicy:
        layers = [
            (w.numpy(), b.numpy()) for w, b in zip(state["weights"], state["biases"], strict=True)
        ]
        return cls(layers, state["low"].numpy(), state["high"].numpy())


class SquashedActor(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden: int, low: np.ndarray, high: np.ndarray):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, 2 * act_dim),
        )
        self.register_buffer("scale", torch.as_tensor((high - low) / 2, dtype=torch.float32))
        self.register_buffer("center", torch.as_tensor((high + low) / 2, dtype=torch.float32))

    def forward(self, obs: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterized actions and their log-densities (in action units) for given noise."""
        out = _float32_layer(self.net[-1], self.net[:-1](obs))
        mean, log_std = out.chunk(2, dim=-1)
        log_std = log_std.clamp(*LOG_STD_BOUNDS)
        u = mean + log_std.exp() * noise
        # log N(u) - log|d tanh(u)/du| - log scale, the tanh term in its stable softplus form
        log_prob = (-0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1) - (
            2 * (math.log(2) - u - nn.functional.softplus(-2 * u))
        ).sum(-1)
        log_prob = log_prob - self.scale.log().sum()
        return torch.tanh(u) * self.scale + self.center, log_prob

    def snapshot(self, low: np.ndarray, high: np.ndarray) -> TanhGaussianPolicy:
        linears = [m for m in self.net if isinstance(m, nn.Linear)]
        layers = [
            (
                m.weight.detach().numpy().T.astype(np.float64),
                m.bias.detach().numpy().astype(np.float64),
            )
            for m in linears
        ]
        return TanhGaussianPolicy(layers, low, high)


class TwinCritic(nn.Module):
    """Two Q networks as one set of batched matmuls: parameters (2, in, out)."""

    def __init__(self, in_dim: int, hidden: int):
        super().__init__()
        sizes = [in_dim, hidden, hidden, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
            bound = 1.0 / math.sqrt(fan_in)  # nn.Linear's default init, per critic
            self.weights.append(
                nn.Parameter(torch.empty(2, fan_in, fan_out).uniform_(-bound, bound))
            )
            self.biases.append(nn.Parameter(torch.empty(2, 1, fan_out).uniform_(-bound, bound)))

    def forward(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """(B, obs) and (B, act) -> (2, B) Q values."""
        h = torch.cat([obs, actions], -1).expand(2, -1, -1)
        *hidden, (w_out, b_out) = zip(self.weights, self.biases, strict=True)
        for w, b in hidden:
            h = torch.relu(torch.baddbmm(b, h, w))
        return _float32_layer(lambda x: torch.baddbmm(b_out, x, w_out), h).squeeze(-1)


class ReplayBuffer:
    """Every transition in arrival order (float32 tensors), sampled uniformly."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int):
        self.capacity, self.size = capacity, 0
        self.obs = torch.empty(capacity, obs_dim)
        self.actions = torch.empty(capacity, act_dim)
        self.rewards = torch.empty(capacity)
        self.next_obs = torch.empty(capacity, obs_dim)
        self.terminal = torch.empty(capacity)

    def add(self, block: RolloutBlock) -> None:
        # (step, env) order flattened step-major, as the block is laid out
        n = block.rewards.size
        if self.size + n > self.capacity:
            raise ValueError(f"replay buffer full ({self.capacity} transitions): raise buffer_size")
        rows = slice(self.size, self.size + n)
        self.obs[rows] = torch.from_numpy(block.observations.reshape(n, -1))
        self.actions[rows] = torch.from_numpy(block.actions.reshape(n, -1))
        self.rewards[rows] = torch.from_numpy(block.rewards.reshape(n))
        self.next_obs[rows] = torch.from_numpy(block.next_observations.reshape(n, -1))
        self.terminal[rows] = torch.from_numpy(block.terminations.reshape(n).astype(np.float32))
        self.size += n

    def arrays(self) -> dict[str, torch.Tensor]:
        keys = ("obs", "actions", "rewards", "next_obs", "terminal")
        return {k: getattr(self, k)[: self.size].clone() for k in keys}

    def load(self, arrays: dict[str, torch.Tensor]) -> None:
        self.size = int(arrays["rewards"].shape[0])
        for key, value in arrays.items():
            getattr(self, key)[: self.size] = value


class SACTrainer(BehaviourTrainer):
    """SAC over a batch of envs; `train_iteration()` is one rollout phase plus its updates."""

    name = "SAC"

    def __init__(self, env_id: str, config: SACConfig, seed: int, recent_episodes: int = 20):
        super().__init__(env_id, config, seed, recent_episodes)
        torch.manual_seed(seed)
        self.generator = torch.Generator().manual_seed(seed)
        self.envs = EnvBatch(env_id, config.num_envs, seed)
        obs_dim, act_dim = self.envs.obs_dim, self.envs.act_dim
        self.actor = SquashedActor(obs_dim, act_dim, config.hidden, self.envs.low, self.envs.high)
        self.critic = TwinCritic(obs_dim + act_dim, config.hidden)
        self.target = TwinCritic(obs_dim + act_dim, config.hidden)
        self.target.load_state_dict(self.critic.state_dict())
        self.target.requires_grad_(False)
        self.log_temperature = nn.Parameter(torch.tensor(math.log(config.init_temperature)))
        self.target_entropy = -float(act_dim)
        lr = config.learning_rate
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=lr)
        self.temperature_opt = torch.optim.Adam([self.log_temperature], lr=lr)
        self.buffer = ReplayBuffer(config.buffer_size, obs_dim, act_dim)
        self.updates = 0
        self.owed_updates = 0.0  # fractional updates carried to the next iteration

    # -- acting --------------------------------------------------------------------------------

    def policy(self) -> TanhGaussianPolicy:
        return self.actor.snapshot(self.envs.low, self.envs.high)

    def _collect(self) -> RolloutBlock:
        c, n, envs = self.config, self.config.num_envs, self.envs
        t_len = c.rollout_steps
        block = RolloutBlock.empty(t_len, n, envs.obs_dim, envs.act_dim)
        policy = self.policy()
        for t in range(t_len):
            if self.steps + t * n < c.start_steps:
                actions = self.rng.uniform(envs.low, envs.high, size=(n, envs.act_dim))
            else:
                actions = envs.clip(policy.sample(envs.obs, self.rng))
            finished = block.record(t, envs.obs, actions, envs.step(actions))
            self.recent_returns.extend(finished)
            self.episodes_done += len(finished)
        self.steps += t_len * n
        return block

    # -- learning ------------------------------------------------------------------------------

    def _update(self) -> dict[str, torch.Tensor]:
        dtype = MATMUL_DTYPES[self.config.matmul_dtype]
        with torch.autocast("cpu", dtype=dtype or torch.bfloat16, enabled=dtype is not None):
            return self._update_step()

    def _update_step(self) -> dict[str, torch.Tensor]:
        c, buf = self.config, self.buffer
        idx = torch.randint(buf.size, (c.batch_size,), generator=self.generator)
        obs, actions, rewards = buf.obs[idx], buf.actions[idx], buf.rewards[idx]
        next_obs, terminal = buf.next_obs[idx], buf.terminal[idx]
        noise = torch.randn(2, c.batch_size, self.envs.act_dim, generator=self.generator)
        temperature = self.log_temperature.detach().exp()
        with torch.no_grad():
            next_actions, next_log_prob = self.actor(next_obs, noise[0])
            next_q = self.target(next_obs, next_actions).min(0).values
            target = rewards + c.gamma * (1 - terminal) * (next_q - temperature * next_log_prob)
        critic_loss = (self.critic(obs, actions) - target).pow(2).mean(1).sum()
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()

        self.critic.requires_grad_(False)
        new_actions, log_prob = self.actor(obs, noise[1])
        actor_loss = (temperature * log_prob - self.critic(obs, new_actions).min(0).values).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        self.critic.requires_grad_(True)

        temperature_loss = -(
            self.log_temperature * (log_prob.detach() + self.target_entropy)
        ).mean()
        self.temperature_opt.zero_grad(set_to_none=True)
        temperature_loss.backward()
        self.temperature_opt.step()
        with torch.no_grad():
            torch._foreach_lerp_(
                list(self.target.parameters()), list(self.critic.parameters()), c.tau
            )
        return {"critic_loss": critic_loss.detach(), "actor_loss": actor_loss.detach()}

    def train_iteration(self) -> tuple[RolloutBlock, dict[str, float]]:
        """One rollout phase, then its share of gradient updates once start_steps are taken."""
        block = self._collect()
        self.buffer.add(block)
        self.iteration += 1
        # updates are owed for the transitions past start_steps
        fresh = self.steps - max(self.steps - block.rewards.size, self.config.start_steps)
        if fresh <= 0:
            return block, {}
        self.owed_updates += fresh * self.config.updates_per_step
        count = int(self.owed_updates)
        self.owed_updates -= count
        sums: dict[str, torch.Tensor] = {}
        for _ in range(count):
            for key, value in self._update().items():
                sums[key] = sums.get(key, 0) + value
        self.updates += count
        stats = {k: float(v) / count for k, v in sums.items()}  # one host read per iteration
        stats["temperature"] = float(self.log_temperature.detach().exp())
        return block, stats

    # -- checkpoints ---------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            **self.progress_state(),
            "trainer": "sac",
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "target": self.target.state_dict(),
            "log_temperature": self.log_temperature.detach().clone(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "temperature_opt": self.temperature_opt.state_dict(),
            "buffer": self.buffer.arrays(),
            "updates": self.updates,
            "owed_updates": self.owed_updates,
            "generator": self.generator.get_state(),
            "envs": self.envs.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any], origin: object = "checkpoint") -> None:
        self.load_progress(state, origin)
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.target.load_state_dict(state["target"])
        with torch.no_grad():
            self.log_temperature.copy_(state["log_temperature"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.temperature_opt.load_state_dict(state["temperature_opt"])
        self.buffer.load(state["buffer"])
        self.updates, self.owed_updates = int(state["updates"]), float(state["owed_updates"])
        self.generator.set_state(state["generator"])
        self.envs.load_state_dict(state["envs"])
