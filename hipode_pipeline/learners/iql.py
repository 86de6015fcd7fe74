"""IQL: "Offline Reinforcement Learning with Implicit Q-Learning", Kostrikov, Nair & Levine,
ICLR 2022.

Expectile regression of V towards the target twin-Q minimum, TD(0) of Q towards r + γV(s'),
and advantage-weighted regression of a Gaussian policy. Settings are CORL's defaults
(β = 3, expectile 0.7, exp-advantage capped at 100, cosine-decayed actor learning rate, and
for locomotion rewards scaled by 1000 / (max − min episode return) of the real data).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn
from torch.optim.lr_scheduler import CosineAnnealingLR

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.learners.base import (
    Batch,
    Learner,
    LearnerConfig,
    adam,
    as_seed_batch,
    polyak_,
)
from hipode_pipeline.learners.stacked import StackedMLP, StackedTwinCritic

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


@dataclass
class IQLConfig(LearnerConfig):
    """IQL's settings: CORL's defaults here; CORL's per-task values (deterministic actor, tau,
    reward normalization on some Hopper tasks) come from stages/train.toml."""

    beta: float = 3.0  # inverse temperature of the advantage weights
    expectile: float = 0.7  # tau of the expectile regression of V
    exp_adv_max: float = 100.0  # cap of exp(beta * advantage)
    actor_lr: float = 3e-4  # actor learning rate (cosine-decayed to 0 over max_steps)
    critic_lr: float = 3e-4  # Q learning rate
    value_lr: float = 3e-4  # V learning rate
    max_steps: int = 1_000_000  # length of the actor's cosine schedule (the run sets it)
    deterministic_policy: bool = False  # regress a deterministic actor instead of a Gaussian
    normalize_reward: bool = False  # scale rewards by 1000 / (max - min real episode return)


def expectile_loss(diff: torch.Tensor, expectile: float) -> torch.Tensor:
    """Asymmetric L2 (weight `expectile` above zero, 1 - expectile below), mean over the last
    axis: one loss per seed."""
    weight = torch.where(diff < 0, 1.0 - expectile, expectile)
    return (weight * diff.square()).mean(-1)


class IQL(Learner):
    """IQL with twin Q, V and a tanh-mean Gaussian (or deterministic) actor, K seeds at once."""

    name = "iql"
    config_class = IQLConfig

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        config: IQLConfig | None = None,
        *,
        device=None,
        seed: int | Sequence[int] = 0,
    ):
        super().__init__(obs_dim, act_dim, config, device=device, seed=seed)
        c, gens = self.config, self.init_generators
        hidden = [c.hidden_dim, c.hidden_dim]
        self.actor = StackedMLP([obs_dim, *hidden, act_dim], gens, nn.Tanh()).to(self.device)
        self.log_std = nn.Parameter(torch.zeros(self.n_seeds, act_dim, device=self.device))
        self.critic = StackedTwinCritic(obs_dim, act_dim, gens, c.hidden_dim).to(self.device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.value = StackedMLP([obs_dim, *hidden, 1], gens).to(self.device)
        self.actor_params = nn.ParameterDict({"log_std": self.log_std})
        self.modules = {
            "actor": self.actor,
            "actor_log_std": self.actor_params,
            "critic": self.critic,
            "critic_target": self.critic_target,
            "value": self.value,
        }
        self.apply_precision()
        actor_params = list(self.actor.parameters()) + (
            [] if c.deterministic_policy else [self.log_std]
        )
        self.optimizers = {
            "actor": adam(actor_params, c.actor_lr, self.device),
            "critic": adam(self.critic.parameters(), c.critic_lr, self.device),
            "value": adam(self.value.parameters(), c.value_lr, self.device),
        }
        self.schedulers = {
            "actor": CosineAnnealingLR(self.optimizers["actor"], max(1, c.max_steps))
        }
        self.reward_scale = 1.0

    def fit_statistics(self, real: Transitions) -> None:
        super().fit_statistics(real)
        if self.config.normalize_reward:
            totals = real.episode_returns()
            low, high = float(totals.min()), float(totals.max())
            self.reward_scale = 1000.0 / max(high - low, 1e-6)

    def _extra_state(self):
        return {"reward_scale": self.reward_scale}

    def _load_extra_state(self, state):
        self.reward_scale = float(state["reward_scale"])

    def _policy_actions(self, observations: torch.Tensor) -> torch.Tensor:
        return self.config.max_action * self.actor(observations)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        c = self.config
        batch = as_seed_batch(batch, self.n_seeds)
        obs, next_obs = self.normalize(batch.observations), self.normalize(batch.next_observations)
        rewards = batch.rewards * self.reward_scale
        self.step += 1
        # V: expectile of the target twin-Q minimum; V(s') for Q's target is taken before V moves
        with torch.no_grad():
            target_q = self.critic_target(obs, batch.actions).amin(1)  # (K, B)
            next_v = self.value(next_obs).squeeze(-1)
        v = self.value(obs).squeeze(-1)
        advantage = target_q - v
        value_losses = expectile_loss(advantage, c.expectile)
        self.optimizers["value"].zero_grad(set_to_none=True)
        value_losses.sum().backward()
        self.optimizers["value"].step()
        # Q: TD(0) towards r + γ V(s'), both critics of every seed in one batched pass
        target = rewards + (1.0 - batch.dones) * c.discount * next_v
        q = self.critic(obs, batch.actions)  # (K, 2, B)
        critic_losses = (q - target.unsqueeze(1)).square().mean(2).sum(1)
        self.optimizers["critic"].zero_grad(set_to_none=True)
        critic_losses.sum().backward()
        self.optimizers["critic"].step()
        polyak_(self.critic_target, self.critic, c.tau)
        # actor: advantage-weighted regression
        weights = torch.exp(c.beta * advantage.detach()).clamp(max=c.exp_adv_max)
        mean = c.max_action * self.actor(obs)
        if c.deterministic_policy:
            bc_losses = (mean - batch.actions).square().sum(-1)
        else:
            log_std = self.log_std.clamp(LOG_STD_MIN, LOG_STD_MAX).unsqueeze(1)
            log_prob = (
                torch.distributions.Normal(mean, log_std.exp()).log_prob(batch.actions).sum(-1)
            )
            bc_losses = -log_prob
        actor_losses = (weights * bc_losses).mean(1)
        self.optimizers["actor"].zero_grad(set_to_none=True)
        actor_losses.sum().backward()
        self.optimizers["actor"].step()
        self.schedulers["actor"].step()
        return {
            "value_loss": value_losses.detach(),
            "critic_loss": critic_losses.detach(),
            "actor_loss": actor_losses.detach(),
            "q_mean": q.detach().mean((1, 2)),
        }
