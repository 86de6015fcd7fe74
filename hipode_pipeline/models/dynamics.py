"""Forward dynamics p_w(s', r | s, a): a probabilistic ensemble in the manner of d3rlpy 1.x's
ProbabilisticEnsembleDynamics (members of 256-256 ReLU MLPs predicting a Gaussian over
(delta s, r), learnable soft log-std bounds, each member trained on its own random half of
every minibatch), with all members computed together. d3rlpy's spectral norm on the hidden and
mean layers is an option, off by default: it caps each member at Lipschitz 1 in z-scored
units, and measured here it left a linear system's reward error at 44% of its variance (0.07%
without) and tripled the state error on Hopper data (bench/results/models_precision.md)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

LOSS_FORMS = ("gaussian_nll", "d3rlpy")


class EnsembleLinear(nn.Module):
    """E independent linear layers as one (E, in, out) weight: x (E, B, in) -> (E, B, out).

    With `spectral_norm`, each member's weight is divided by its largest singular value,
    estimated by one power iteration per training forward (as torch's spectral_norm does).
    """

    def __init__(
        self, members: int, in_features: int, out_features: int, spectral_norm: bool = False
    ):
        super().__init__()
        bound = 1.0 / math.sqrt(in_features)
        # nn.Linear's default init, drawn independently per member
        self.weight = nn.Parameter(
            torch.empty(members, in_features, out_features).uniform_(-bound, bound)
        )
        self.bias = nn.Parameter(torch.empty(members, 1, out_features).uniform_(-bound, bound))
        self.spectral_norm = spectral_norm
        if spectral_norm:
            self.register_buffer("sn_u", F.normalize(torch.randn(members, out_features), dim=-1))
            self.register_buffer("sn_v", F.normalize(torch.randn(members, in_features), dim=-1))
            # settle the singular-vector estimates before the first forward, as torch's
            # parametrized spectral_norm does at registration
            with torch.no_grad():
                for _ in range(15):
                    self._power_iteration()

    @torch.no_grad()
    def _power_iteration(self) -> None:
        w = self.weight.float()
        self.sn_v.copy_(F.normalize(torch.einsum("eio,eo->ei", w, self.sn_u), dim=-1, eps=1e-12))
        self.sn_u.copy_(F.normalize(torch.einsum("eio,ei->eo", w, self.sn_v), dim=-1, eps=1e-12))

    def effective_weight(self) -> Tensor:
        if not self.spectral_norm:
            return self.weight
        if self.training:
            self._power_iteration()
        sigma = torch.einsum("ei,eio,eo->e", self.sn_v, self.weight, self.sn_u)
        return self.weight / sigma[:, None, None]

    def forward(self, x: Tensor) -> Tensor:
        return torch.baddbmm(self.bias, x, self.effective_weight())

    def member_forward(self, member: int, x: Tensor) -> Tensor:
        """One member alone on (B, in); the reference the batched forward must equal."""
        return x @ self.effective_weight()[member] + self.bias[member]


class DynamicsEnsemble(nn.Module):
    """E Gaussian MLPs on (s_norm, a) predicting (delta s_norm, r) with soft-bounded log-std.

    Rewards are z-scored inside the model (`reward_mean`, `reward_std`) and returned raw.
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        members: int = 5,
        hidden: tuple[int, ...] = (256, 256),
        spectral_norm: bool = False,
        loss_form: str = "gaussian_nll",
        bound_loss_weight: float = 0.01,
        init_max_log_std: float = 2.0,
        init_min_log_std: float = -10.0,
    ):
        super().__init__()
        if loss_form not in LOSS_FORMS:
            raise ValueError(f"dynamics loss form '{loss_form}': expected one of {LOSS_FORMS}")
        self.state_dim, self.action_dim, self.members = state_dim, action_dim, members
        self.loss_form, self.bound_loss_weight = loss_form, bound_loss_weight
        sizes = (state_dim + action_dim, *hidden)
        self.hidden_layers = nn.ModuleList(
            EnsembleLinear(members, i, o, spectral_norm)
            for i, o in zip(sizes[:-1], sizes[1:], strict=True)
        )
        out = state_dim + 1
        self.mean_head = EnsembleLinear(members, sizes[-1], out, spectral_norm)
        self.log_std_head = EnsembleLinear(members, sizes[-1], out, spectral_norm=False)
        self.max_log_std = nn.Parameter(torch.full((members, 1, out), init_max_log_std))
        self.min_log_std = nn.Parameter(torch.full((members, 1, out), init_min_log_std))
        self.register_buffer("reward_mean", torch.zeros(()))
        self.register_buffer("reward_std", torch.ones(()))
        # members sample() draws from (chosen after training, not part of the weights); None: all
        self.elites: list[int] | None = None

    def set_elites(self, members: list[int] | None) -> None:
        if members is not None and not (members and all(0 <= m < self.members for m in members)):
            raise ValueError(f"elites {members}: expected member indices in [0, {self.members})")
        self.elites = None if members is None else sorted(set(members))

    def set_reward_scale(self, mean: float, std: float) -> None:
        self.reward_mean.fill_(float(mean))
        self.reward_std.fill_(float(std))

    def stats(self, states: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        """(B, .) shared by all members, or (E, B, .) per member -> mean, log_std (E, B, ds + 1)."""
        x = torch.cat([states, actions], dim=-1)
        if x.dim() == 2:
            x = x.unsqueeze(0).expand(self.members, -1, -1)
        for layer in self.hidden_layers:
            x = F.relu(layer(x))
        mean = self.mean_head(x)
        log_std = self.log_std_head(x)
        log_std = self.max_log_std - F.softplus(self.max_log_std - log_std)
        log_std = self.min_log_std + F.softplus(log_std - self.min_log_std)
        return mean, log_std

    def member_stats(self, member: int, states: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        """One member computed on its own (for checks); equals stats(...)[:, member]."""
        x = torch.cat([states, actions], dim=-1)
        for layer in self.hidden_layers:
            x = F.relu(layer.member_forward(member, x))
        mean = self.mean_head.member_forward(member, x)
        log_std = self.log_std_head.member_forward(member, x)
        hi, lo = self.max_log_std[member], self.min_log_std[member]
        log_std = hi - F.softplus(hi - log_std)
        return mean, lo + F.softplus(log_std - lo)

    def _targets(self, states: Tensor, rewards: Tensor, next_states: Tensor) -> Tensor:
        reward = (rewards - self.reward_mean) / self.reward_std
        return torch.cat([next_states - states, reward.unsqueeze(-1)], dim=-1)

    def member_losses(
        self, states: Tensor, actions: Tensor, rewards: Tensor, next_states: Tensor
    ) -> Tensor:
        """Per-member, per-row loss (E, B) without the bound term; inputs (B, .) or (E, B, .)."""
        mean, log_std = self.stats(states, actions)
        mean, log_std = mean.float(), log_std.float()
        target = self._targets(states, rewards, next_states)
        if self.loss_form == "gaussian_nll":
            return (0.5 * (mean - target).pow(2) * torch.exp(-2 * log_std) + log_std).mean(-1)
        # d3rlpy 1.x: squared error scaled by exp(-log_std), plus the summed log-std
        return ((mean - target).pow(2) * torch.exp(-log_std)).mean(-1) + log_std.sum(-1)

    def loss(
        self,
        states: Tensor,
        actions: Tensor,
        rewards: Tensor,
        next_states: Tensor,
        generator: torch.Generator | None = None,
    ) -> tuple[Tensor, Tensor]:
        """(total, nll): each member learns from its own random half of the batch.

        The halves are gathered, (E, B/2, .), rather than masked, so a member computes only
        the rows it learns from: half the arithmetic of d3rlpy's mask, same expected gradient.
        """
        batch = states.shape[0]
        scores = torch.rand((self.members, batch), generator=generator, device=states.device)
        rows = scores.argsort(dim=1)[:, : max(1, batch // 2)]
        losses = self.member_losses(states[rows], actions[rows], rewards[rows], next_states[rows])
        nll = losses.mean(-1)
        bound = self.max_log_std.sum() - self.min_log_std.sum()
        return nll.sum() + self.bound_loss_weight * bound, nll.mean()

    @torch.no_grad()
    def heldout_losses(
        self, states: Tensor, actions: Tensor, rewards: Tensor, next_states: Tensor
    ) -> Tensor:
        """Per-member loss on held-out rows, (E,)."""
        return self.member_losses(states, actions, rewards, next_states).mean(-1)

    def elite_stats(self, states: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        """`stats` of the elite members only (all members when no elites are set)."""
        mean, log_std = self.stats(states, actions)
        if self.elites is None:
            return mean, log_std
        elites = torch.as_tensor(self.elites, device=mean.device)
        return mean[elites], log_std[elites]

    @torch.no_grad()
    def predictive(self, states_norm: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        """The ensemble's (elites') predictive mean and variance of (delta s_norm, reward in
        model units, i.e. z-scored), (B, ds + 1) each: the members' mean variance plus the
        variance of their means (total variance)."""
        mean, log_std = self.elite_stats(states_norm, actions)
        mean, log_std = mean.float(), log_std.float()
        variance = (2 * log_std).exp().mean(0) + mean.var(0, unbiased=False)
        center = mean.mean(0)
        raw_reward = center[:, -1] * self.reward_std + self.reward_mean
        return torch.cat([center[:, :-1], raw_reward[:, None]], dim=1), variance

    @torch.no_grad()
    def sample(
        self,
        states_norm: Tensor,
        actions: Tensor,
        generator: torch.Generator | None = None,
        use_mean: bool = False,
    ) -> tuple[Tensor, Tensor]:
        """Next normalized states (B, ds) and raw rewards (B,).

        Default: per row, a Gaussian sample from a uniformly drawn member (d3rlpy semantics);
        `use_mean`: the members' mean prediction averaged over the ensemble. Only the elite
        members take part when elites are set.
        """
        mean, log_std = self.elite_stats(states_norm, actions)
        if use_mean:
            delta = mean.float().mean(0)
        else:
            noise_device = generator.device if generator is not None else mean.device
            batch = states_norm.shape[0]
            drawn_from = mean.shape[0]
            member = torch.randint(drawn_from, (batch,), generator=generator, device=noise_device)
            eps = torch.randn((batch, self.state_dim + 1), generator=generator, device=noise_device)
            member, eps = member.to(mean.device), eps.to(mean.device)
            rows = torch.arange(batch, device=mean.device)
            delta = mean[member, rows].float() + log_std[member, rows].float().exp() * eps
        next_states = states_norm + delta[:, :-1]
        rewards = delta[:, -1] * self.reward_std + self.reward_mean
        return next_states, rewards
