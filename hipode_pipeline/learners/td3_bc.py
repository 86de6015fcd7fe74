"""TD3+BC: "A Minimalist Approach to Offline Reinforcement Learning", Fujimoto & Gu, NeurIPS 2021.

TD3 plus a behaviour-cloning term on the actor, with the Q-term scaled by alpha / mean|Q|.
Settings follow the paper and CORL (alpha 2.5, policy noise 0.2 clipped at 0.5, actor every 2nd
step). Speed: all seeds' actors and both critics of every seed run as one batched matmul per layer,
the actor step reads the critic through detached weights (no weight gradients it would throw
away), Adam is fused and the target update is one batched lerp.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from hipode_pipeline.learners.base import (
    Batch,
    Learner,
    LearnerConfig,
    adam,
    as_seed_batch,
    polyak_,
)
from hipode_pipeline.learners.stacked import StackedMLP, StackedTwinCritic


@dataclass
class TD3BCConfig(LearnerConfig):
    """TD3+BC's settings (paper / CORL defaults)."""

    alpha: float = 2.5  # weight of the Q-term against behaviour cloning (0.001 on Adroit)
    actor_lr: float = 3e-4  # actor learning rate
    critic_lr: float = 3e-4  # critic learning rate
    policy_noise: float = 0.2  # std of the target-policy smoothing noise (times max_action)
    noise_clip: float = 0.5  # clip of that noise (times max_action)
    policy_freq: int = 2  # actor and target updates every this many critic updates
    compile: bool = False  # torch.compile the update (first call compiles for tens of seconds)


class TD3BC(Learner):
    """TD3+BC with deterministic tanh actors and twin critics, K seeds at once."""

    name = "td3bc"
    config_class = TD3BCConfig

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        config: TD3BCConfig | None = None,
        *,
        device=None,
        seed: int | Sequence[int] = 0,
    ):
        super().__init__(obs_dim, act_dim, config, device=device, seed=seed)
        c, gens = self.config, self.init_generators
        self.actor = StackedMLP([obs_dim, c.hidden_dim, c.hidden_dim, act_dim], gens, nn.Tanh())
        self.critic = StackedTwinCritic(obs_dim, act_dim, gens, c.hidden_dim)
        self.actor, self.critic = self.actor.to(self.device), self.critic.to(self.device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.modules = {
            "actor": self.actor,
            "critic": self.critic,
            "actor_target": self.actor_target,
            "critic_target": self.critic_target,
        }
        self.apply_precision()
        self.optimizers = {
            "actor": adam(self.actor.parameters(), c.actor_lr, self.device),
            "critic": adam(self.critic.parameters(), c.critic_lr, self.device),
        }
        self._critic_step = self._compiled(self._critic_step_eager)
        self._actor_step = self._compiled(self._actor_step_eager)

    def _compiled(self, fn):
        return torch.compile(fn) if self.config.compile else fn

    def _policy_actions(self, observations: torch.Tensor) -> torch.Tensor:
        return self.config.max_action * self.actor(observations)

    def _critic_step_eager(self, obs, actions, rewards, next_obs, dones, noise):
        c = self.config
        with torch.no_grad():
            next_actions = (c.max_action * self.actor_target(next_obs) + noise).clamp(
                -c.max_action, c.max_action
            )
            target_q = self.critic_target(next_obs, next_actions).amin(1)  # (K, B)
            target = rewards + (1.0 - dones) * c.discount * target_q
        q = self.critic(obs, actions)  # (K, 2, B)
        # per seed, the sum over its two critics of each one's MSE, as two losses would give
        critic_losses = (q - target.unsqueeze(1)).square().mean(2).sum(1)
        self.optimizers["critic"].zero_grad(set_to_none=True)
        critic_losses.sum().backward()
        self.optimizers["critic"].step()
        return critic_losses.detach(), q.detach().mean((1, 2))

    def _actor_step_eager(self, obs, actions):
        c = self.config
        policy_actions = c.max_action * self.actor(obs)
        q = self.critic.first(obs, policy_actions, frozen=True)  # (K, B)
        lmbda = c.alpha / q.abs().mean(1).detach()
        actor_losses = -lmbda * q.mean(1) + (policy_actions - actions).square().mean((1, 2))
        self.optimizers["actor"].zero_grad(set_to_none=True)
        actor_losses.sum().backward()
        self.optimizers["actor"].step()
        polyak_(self.critic_target, self.critic, c.tau)
        polyak_(self.actor_target, self.actor, c.tau)
        return actor_losses.detach()

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        c = self.config
        batch = as_seed_batch(batch, self.n_seeds)
        obs, next_obs = self.normalize(batch.observations), self.normalize(batch.next_observations)
        noise = self.randn(*batch.actions.shape[1:])
        noise = (noise * c.policy_noise).clamp(-c.noise_clip, c.noise_clip) * c.max_action
        self.step += 1
        critic_loss, q_mean = self._critic_step(
            obs, batch.actions, batch.rewards, next_obs, batch.dones, noise
        )
        metrics = {"critic_loss": critic_loss, "q_mean": q_mean}
        if self.step % c.policy_freq == 0:
            metrics["actor_loss"] = self._actor_step(obs, batch.actions)
        return metrics
