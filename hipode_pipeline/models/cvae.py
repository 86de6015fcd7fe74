"""One conditional VAE class, configured three times: the state-transition model D_psi(s, z) -> s',
the inverse action model D_eps(s, s', z) -> a and the inverse reward model D_zeta(s, s', z) -> r."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class CVAE(nn.Module):
    """Encoder (x, cond) -> (mu, log sigma), decoder (cond, z) -> x; one hidden layer each.

    The decoder predicts x in "model units": identity, a z-score given by `output_mean` and
    `output_std` (rewards), or tanh squashed into [`output_low`, `output_high`] (actions).
    """

    def __init__(
        self,
        output_dim: int,
        cond_dim: int,
        latent_dim: int,
        hidden: int = 750,
        log_std_min: float = -4.0,
        log_std_max: float = 15.0,
        kl_weight: float = 0.5,
        latent_clip: float = 0.5,
        squash: bool = False,
        standardize_output: bool = False,
    ):
        super().__init__()
        self.output_dim, self.cond_dim, self.latent_dim = output_dim, cond_dim, latent_dim
        self.log_std_min, self.log_std_max = log_std_min, log_std_max
        self.kl_weight, self.latent_clip = kl_weight, latent_clip
        self.squash, self.standardize_output = squash, standardize_output
        self.encoder = nn.Sequential(nn.Linear(output_dim + cond_dim, hidden), nn.ReLU())
        self.encoder_head = nn.Linear(hidden, 2 * latent_dim)
        self.decoder = nn.Sequential(
            nn.Linear(cond_dim + latent_dim, hidden), nn.ReLU(), nn.Linear(hidden, output_dim)
        )
        # buffers, so that bounds and scales travel with the weights file
        self.register_buffer("output_low", -torch.ones(output_dim))
        self.register_buffer("output_high", torch.ones(output_dim))
        self.register_buffer("output_mean", torch.zeros(output_dim))
        self.register_buffer("output_std", torch.ones(output_dim))

    def set_output_bounds(self, low: Tensor, high: Tensor) -> None:
        self.output_low.copy_(torch.as_tensor(low, dtype=torch.float32))
        self.output_high.copy_(torch.as_tensor(high, dtype=torch.float32))

    def set_output_scale(self, mean: Tensor, std: Tensor) -> None:
        self.output_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.output_std.copy_(torch.as_tensor(std, dtype=torch.float32))

    def encode(self, x: Tensor, cond: Tensor) -> tuple[Tensor, Tensor]:
        h = self.encoder(torch.cat([x, cond], dim=-1))
        mu, log_std = self.encoder_head(h).chunk(2, dim=-1)
        return mu, log_std.clamp(self.log_std_min, self.log_std_max)

    def decode(self, cond: Tensor, z: Tensor) -> Tensor:
        """Decoder output in data units (bounded for actions, de-standardized for rewards)."""
        return self._to_data_units(self.decoder(torch.cat([cond, z], dim=-1)))

    def _to_data_units(self, raw: Tensor) -> Tensor:
        if self.squash:
            return (
                self.output_low + (self.output_high - self.output_low) * (torch.tanh(raw) + 1) / 2
            )
        if self.standardize_output:
            return raw * self.output_std + self.output_mean
        return raw

    def _to_loss_units(self, x: Tensor) -> Tensor:
        """Reconstruction error is measured with rewards z-scored so its scale is task-free."""
        return (x - self.output_mean) / self.output_std if self.standardize_output else x

    def loss(
        self, x: Tensor, cond: Tensor, generator: torch.Generator | None = None
    ) -> tuple[Tensor, Tensor]:
        """(total, reconstruction): MSE + kl_weight * KL(q(z|x,c) || N(0, I)), BCQ-style means."""
        mu, log_std = self.encode(x, cond)
        std = log_std.exp()
        eps = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
        recon = self.decode(cond, mu + std * eps)
        recon_loss = F.mse_loss(self._to_loss_units(recon), self._to_loss_units(x))
        kl = -0.5 * (1 + 2 * log_std - mu.pow(2) - std.pow(2)).mean()
        return recon_loss + self.kl_weight * kl, recon_loss

    def draw_latent(
        self, batch: int, num_samples: int, generator: torch.Generator | None = None
    ) -> Tensor:
        """z ~ N(0, I) clipped to [-latent_clip, latent_clip], drawn on the generator's device."""
        device = generator.device if generator is not None else self.output_low.device
        z = torch.randn((batch, num_samples, self.latent_dim), generator=generator, device=device)
        return z.to(self.output_low.device).clamp(-self.latent_clip, self.latent_clip)

    @torch.no_grad()
    def sample(
        self, cond: Tensor, num_samples: int, generator: torch.Generator | None = None
    ) -> Tensor:
        """(B, cond_dim) -> (B, num_samples, output_dim) in data units."""
        z = self.draw_latent(cond.shape[0], num_samples, generator)
        cond = cond.to(z.device).unsqueeze(1).expand(-1, num_samples, -1)
        return self.decode(cond, z)
