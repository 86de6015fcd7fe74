"""Value estimator V_theta(s): TD(0) on dataset transitions plus a penalty on negative samples
(states perturbed off the data), so that off-data candidates rank below data-like ones."""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import Tensor, nn

PENALTY_FORMS = ("target", "l2", "contrastive")
# units of the target penalty: raw value units, or the batch's spread of V-bar(s)
PENALTY_SCALES = ("raw", "value")


class ValueEstimator(nn.Module):
    """MLP V(s) with a soft-updated target copy V-bar; called on (..., ds) normalized states."""

    def __init__(
        self,
        state_dim: int,
        hidden: int = 256,
        gamma: float = 0.99,
        tau: float = 0.005,
        target_update_every: int = 2,
        penalty: str = "target",
        penalty_scale: str = "raw",
        alpha: float = 1.0,
        sigma: float = 1.0,
    ):
        super().__init__()
        if penalty not in PENALTY_FORMS:
            raise ValueError(f"penalty form '{penalty}': expected one of {PENALTY_FORMS}")
        if penalty_scale not in PENALTY_SCALES:
            raise ValueError(f"penalty scale '{penalty_scale}': expected one of {PENALTY_SCALES}")
        self.penalty_scale = penalty_scale
        self.gamma, self.tau, self.target_update_every = gamma, tau, target_update_every
        self.penalty, self.alpha, self.sigma = penalty, alpha, sigma
        self.net = nn.Sequential(nn.Linear(state_dim, hidden), nn.ReLU(), nn.Linear(hidden, 1))
        self.target = copy.deepcopy(self.net).requires_grad_(False)

    def forward(self, states: Tensor) -> Tensor:
        return self.net(states).squeeze(-1)

    def td_loss(self, s: Tensor, r: Tensor, s_next: Tensor, terminal: Tensor) -> Tensor:
        with torch.no_grad():
            target = r + self.gamma * (1.0 - terminal) * self.target(s_next).squeeze(-1)
        return F.mse_loss(self(s).float(), target.float())

    def loss(
        self,
        s: Tensor,
        r: Tensor,
        s_next: Tensor,
        terminal: Tensor,
        generator: torch.Generator | None = None,
    ) -> tuple[Tensor, Tensor]:
        """(total, td): TD(0) error plus the penalty on negatives s + U(-sigma, sigma)."""
        td = self.td_loss(s, r, s_next, terminal)
        offset = (torch.rand(s.shape, generator=generator, device=s.device) * 2 - 1) * self.sigma
        negatives = s + offset
        v_negative = self(negatives).float()
        if self.penalty == "target":
            with torch.no_grad():
                target_values = self.target(s).squeeze(-1).float()
                unit = self.penalty_unit(target_values)
                anchor = target_values - self.alpha * unit * offset.norm(dim=-1)
            penalty = F.mse_loss(v_negative, anchor)
        elif self.penalty == "l2":
            penalty = self.alpha * v_negative.pow(2).mean()
        else:
            penalty = self.alpha * (v_negative.mean() - self(s).float().mean())
        return td + penalty, td

    def penalty_unit(self, target_values: Tensor) -> Tensor:
        """What one unit of alpha x offset norm costs: 1 (raw), or the spread of V-bar over the
        batch's data states, so that alpha means the same on tasks of any reward scale."""
        if self.penalty_scale == "raw":
            return torch.ones((), device=target_values.device)
        return target_values.std().clamp_min(1e-6)

    @torch.no_grad()
    def update_target(self, step: int) -> None:
        """Polyak-average V-bar towards V every `target_update_every` steps (step is 1-based)."""
        if step % self.target_update_every:
            return
        online, target = list(self.net.parameters()), list(self.target.parameters())
        torch._foreach_lerp_(target, online, self.tau)
