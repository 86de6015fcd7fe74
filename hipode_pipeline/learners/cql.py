"""CQL: "Conservative Q-Learning for Offline Reinforcement Learning", Kumar et al., NeurIPS 2020.

SAC with a conservative term: logsumexp of Q over sampled actions (uniform, policy at s, policy
at s', importance-weighted) minus Q on the data, weighted by cql_alpha (10, as in the paper's
runs). Settings follow CORL's CQL (3-layer critics with orthogonal init, automatic entropy,
10 sampled actions). All sampled actions of a batch, of every seed, go through the twin
critics as one batched pass, which is what keeps CQL usable on a CPU.
"""

from __future__ import annotations

import copy
import math
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
from hipode_pipeline.learners.stacked import (
    StackedMLP,
    StackedTwinCritic,
    orthogonal_,
    xavier_uniform_,
)

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


@dataclass
class CQLConfig(LearnerConfig):
    """CQL's settings (CORL defaults; cql_alpha from the paper's runs)."""

    cql_alpha: float = 10.0  # weight of the conservative term
    cql_n_actions: int = 10  # actions sampled per state for each of the three proposals
    cql_temp: float = 1.0  # temperature of the logsumexp
    policy_lr: float = 3e-5  # actor (and entropy temperature) learning rate
    critic_lr: float = 3e-4  # critic learning rate
    critic_hidden_layers: int = 3  # hidden layers of each Q-network
    actor_hidden_layers: int = 3  # hidden layers of the policy
    target_entropy: float | None = None  # None: -act_dim
    auto_entropy: bool = True  # learn the SAC temperature
    backup_entropy: bool = False  # subtract alpha * log pi in the TD target
    orthogonal_init: bool = True  # orthogonal init of the critics (CORL)


class TanhGaussianActor(nn.Module):
    """K stacked MLPs -> (mean, log_std) -> tanh-squashed Gaussians; log-probs with the tanh
    correction. The caller draws the noise (one stream per seed)."""

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        hidden_dim: int,
        hidden_layers: int,
        max_action: float,
        generators: Sequence[torch.Generator],
    ):
        super().__init__()
        self.net = StackedMLP([obs_dim, *([hidden_dim] * hidden_layers), 2 * act_dim], generators)
        # a near-zero last layer starts the policy centred, as CORL does
        xavier_uniform_(self.net.weights[-1], 1e-2, generators)
        nn.init.zeros_(self.net.biases[-1])
        k = len(generators)
        # learnable affine map of the raw log-std, starting at std e^-1 (as CORL's policy does)
        self.log_std_scale = nn.Parameter(torch.ones(k))
        self.log_std_offset = nn.Parameter(torch.full((k,), -1.0))
        self.max_action = max_action

    def forward(self, obs: torch.Tensor, eps: torch.Tensor | None = None):
        """(K, ..., ds) -> actions (K, ..., da) and log-probs (K, ...); deterministic (tanh of
        the mean, no log-prob) without `eps`, the standard normals of the sample."""
        mean, log_std = self.net(obs).chunk(2, dim=-1)
        per_seed = (-1, *([1] * (log_std.dim() - 1)))
        log_std = (
            self.log_std_scale.view(per_seed) * log_std + self.log_std_offset.view(per_seed)
        ).clamp(LOG_STD_MIN, LOG_STD_MAX)
        if eps is None:
            return self.max_action * torch.tanh(mean), None
        pre_tanh = mean + log_std.exp() * eps
        log_prob = (-0.5 * eps.square() - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
        # log|d tanh(u)/du| = 2 (log 2 - u - softplus(-2u)), the numerically stable form
        log_prob = log_prob - (
            2 * (math.log(2) - pre_tanh - nn.functional.softplus(-2 * pre_tanh))
        ).sum(-1)
        return self.max_action * torch.tanh(pre_tanh), log_prob


class CQL(Learner):
    """CQL(H) with twin critics, a tanh-Gaussian actor and automatic entropy tuning, K seeds at
    once."""

    name = "cql"
    config_class = CQLConfig

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        config: CQLConfig | None = None,
        *,
        device=None,
        seed: int | Sequence[int] = 0,
    ):
        super().__init__(obs_dim, act_dim, config, device=device, seed=seed)
        c, gens = self.config, self.init_generators
        self.actor = TanhGaussianActor(
            obs_dim, act_dim, c.hidden_dim, c.actor_hidden_layers, c.max_action, gens
        ).to(self.device)
        self.critic = StackedTwinCritic(
            obs_dim, act_dim, gens, c.hidden_dim, n_hidden=c.critic_hidden_layers
        )
        if c.orthogonal_init:
            last = len(self.critic.weights) - 1
            for i, (w, b) in enumerate(zip(self.critic.weights, self.critic.biases, strict=True)):
                orthogonal_(w.data, 1e-2 if i == last else math.sqrt(2), gens)
                nn.init.zeros_(b.data)
        self.critic = self.critic.to(self.device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.zeros(self.n_seeds, device=self.device))
        self.entropy = nn.ParameterDict({"log_alpha": self.log_alpha})
        self.target_entropy = -float(act_dim) if c.target_entropy is None else c.target_entropy
        self.modules = {
            "actor": self.actor,
            "critic": self.critic,
            "critic_target": self.critic_target,
            "entropy": self.entropy,
        }
        self.apply_precision()
        self.optimizers = {
            "actor": adam(self.actor.parameters(), c.policy_lr, self.device),
            "critic": adam(self.critic.parameters(), c.critic_lr, self.device),
            "entropy": adam([self.log_alpha], c.policy_lr, self.device),
        }

    def _policy_actions(self, observations: torch.Tensor) -> torch.Tensor:
        return self.actor(observations)[0]

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        c = self.config
        batch = as_seed_batch(batch, self.n_seeds)
        obs, next_obs, actions = (
            self.normalize(batch.observations),
            self.normalize(batch.next_observations),
            batch.actions,
        )
        k, b, da, n = self.n_seeds, actions.shape[1], self.act_dim, c.cql_n_actions
        self.step += 1

        # actor and temperature (SAC), against the current critics
        new_actions, log_pi = self.actor(obs, self.randn(b, da))
        if c.auto_entropy:
            alpha_losses = -(self.log_alpha.unsqueeze(1) * (log_pi.detach() + self.target_entropy))
            alpha_losses = alpha_losses.mean(1)
            alpha = self.log_alpha.detach().exp()
        else:
            alpha_losses = torch.zeros(k, device=self.device)
            alpha = torch.ones(k, device=self.device)
        q_new = self.critic(obs, new_actions).amin(1)  # (K, B)
        actor_losses = (alpha.unsqueeze(1) * log_pi - q_new).mean(1)

        # TD target
        with torch.no_grad():
            next_actions, next_log_pi = self.actor(next_obs, self.randn(b, da))
            target_q = self.critic_target(next_obs, next_actions).amin(1)
            if c.backup_entropy:
                target_q = target_q - alpha.unsqueeze(1) * next_log_pi
            target = batch.rewards + (1.0 - batch.dones) * c.discount * target_q

        # conservative term: uniform, pi(.|s) and pi(.|s') proposals, all scored at s in one pass
        with torch.no_grad():
            random_actions = self.uniform(-c.max_action, c.max_action, b, n, da)
            both = torch.cat([obs, next_obs], dim=1).unsqueeze(2).expand(-1, -1, n, -1)
            sampled, sampled_log_pi = self.actor(both, self.randn(2 * b, n, da))
            current_actions, next_proposals = sampled.split(b, dim=1)
            current_log_pi, next_log_pi_s = sampled_log_pi.split(b, dim=1)
        proposals = torch.cat(
            [actions.unsqueeze(2), random_actions, next_proposals, current_actions], dim=2
        )
        # (K, 2, B, 1 + 3n)
        q_all = self.critic(obs.unsqueeze(2).expand(-1, -1, 1 + 3 * n, -1), proposals)
        q_data = q_all[..., 0]
        # every proposal's log density in action units: the policy's is of tanh(u), scaled
        random_density = da * math.log(0.5 / c.max_action)
        to_action_units = da * math.log(c.max_action)
        log_density = torch.cat(
            [
                torch.full((k, b, n), random_density, device=self.device),
                next_log_pi_s - to_action_units,
                current_log_pi - to_action_units,
            ],
            dim=2,
        ).unsqueeze(1)
        ood = torch.logsumexp((q_all[..., 1:] - log_density) / c.cql_temp, dim=-1) * c.cql_temp
        cql_gap = (ood - q_data).mean(2)  # (K, 2): per seed, per critic
        td_loss = (q_data - target.unsqueeze(1)).square().mean(2)
        critic_losses = (td_loss + c.cql_alpha * cql_gap).sum(1)

        if c.auto_entropy:
            self.optimizers["entropy"].zero_grad(set_to_none=True)
            alpha_losses.sum().backward()
            self.optimizers["entropy"].step()
        self.optimizers["actor"].zero_grad(set_to_none=True)
        actor_losses.sum().backward(inputs=list(self.actor.parameters()))
        self.optimizers["actor"].step()
        self.optimizers["critic"].zero_grad(set_to_none=True)
        critic_losses.sum().backward()
        self.optimizers["critic"].step()
        polyak_(self.critic_target, self.critic, c.tau)
        return {
            "critic_loss": critic_losses.detach(),
            "td_loss": td_loss.detach().sum(1),
            "cql_gap": cql_gap.detach().mean(1),
            "actor_loss": actor_losses.detach(),
            "alpha": alpha.detach(),
            "q_mean": q_data.detach().mean((1, 2)),
        }
