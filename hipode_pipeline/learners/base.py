"""What every built-in learner shares: the batch type, state statistics from real data only,
fused twin critics, device choice, checkpoints that resume exactly and deterministic acting."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import nn

from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.device import select_device
from hipode_pipeline.errors import HipodeError
from hipode_pipeline.replay import Batch

__all__ = [
    "MLP",
    "Batch",
    "Learner",
    "LearnerConfig",
    "TwinCritic",
    "adam",
    "fast_bf16",
    "orthogonal_init_",
    "polyak_",
    "select_device",
]


@dataclass
class LearnerConfig:
    """Fields every learner config has; each learner adds its own below these."""

    discount: float = 0.99  # gamma
    tau: float = 0.005  # Polyak rate of the target networks
    hidden_dim: int = 256  # width of every hidden layer
    normalize_states: bool = True  # z-score states with the real data's statistics
    max_action: float = 1.0  # actions live in [-max_action, max_action]

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any], origin: str = "learner settings"):
        """Build from a dict (a TOML table, CLI overrides), naming unknown keys clearly."""
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise HipodeError(
                f"{origin}: unknown setting(s) {unknown} for {cls.__name__}; "
                f"expected some of {sorted(known)}"
            )
        return cls(**values)


def orthogonal_init_(weight: torch.Tensor, gain: float) -> None:
    """Orthogonal init for a (members, in, out) or (in, out) weight, one matrix per member."""
    for matrix in weight.view(-1, *weight.shape[-2:]):
        nn.init.orthogonal_(matrix, gain=gain)


class MLP(nn.Sequential):
    """Linear-ReLU stack with an optional output activation (torch's default init)."""

    def __init__(self, dims: list[int], output_activation: nn.Module | None = None):
        layers: list[nn.Module] = []
        for i in range(len(dims) - 1):
            layers.append(nn.Linear(dims[i], dims[i + 1]))
            layers.append(nn.ReLU())
        layers.pop()
        if output_activation is not None:
            layers.append(output_activation)
        super().__init__(*layers)


class TwinCritic(nn.Module):
    """Two Q-networks Q(s, a) evaluated as one batched matmul per layer (members stacked)."""

    def __init__(
        self, obs_dim: int, act_dim: int, hidden_dim: int = 256, n_hidden: int = 2, members: int = 2
    ):
        super().__init__()
        dims = [obs_dim + act_dim, *([hidden_dim] * n_hidden), 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(dims[:-1], dims[1:], strict=True):
            # nn.Linear's default init, drawn per member
            bound = 1.0 / math.sqrt(fan_in)
            self.weights.append(
                nn.Parameter(torch.empty(members, fan_in, fan_out).uniform_(-bound, bound))
            )
            self.biases.append(
                nn.Parameter(torch.empty(members, 1, fan_out).uniform_(-bound, bound))
            )

    def forward(self, observations: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """(..., ds), (..., da) -> (members, ...) Q-values; inputs are shared by every member."""
        x = torch.cat([observations, actions], dim=-1)
        lead = x.shape[:-1]
        h = x.reshape(1, -1, x.shape[-1])
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = torch.baddbmm(b, h.expand(w.shape[0], -1, -1) if i == 0 else h, w)
            if i < last:
                h = torch.relu(h)
        return h.reshape(h.shape[0], *lead)

    def first(
        self, observations: torch.Tensor, actions: torch.Tensor, *, frozen: bool = False
    ) -> torch.Tensor:
        """Q1 alone; `frozen` detaches the weights so only the inputs get gradients (actor step)."""
        h = torch.cat([observations, actions], dim=-1)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            w0, b0 = (w[0].detach(), b[0].detach()) if frozen else (w[0], b[0])
            h = torch.addmm(b0, h, w0) if h.dim() == 2 else h @ w0 + b0
            if i < last:
                h = torch.relu(h)
        return h.squeeze(-1)


def fast_bf16(device: torch.device) -> bool:
    """Whether bfloat16 matmuls run natively here (CUDA with bf16, CPUs with AVX512-BF16/AMX)."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    check = getattr(torch.cpu, "_is_avx512_bf16_supported", None)
    return bool(check and check())


def polyak_(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- (1 - tau) target + tau source, as one batched op over all tensors."""
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def adam(params, lr: float, device: torch.device) -> torch.optim.Adam:
    """Adam with the fused kernel (one op for all tensors) where this torch has one."""
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, lr=lr, foreach=True)


class Learner:
    """Base of TD3BC, IQL and CQL: subclasses build `modules` and `optimizers` and implement
    `update` and `_policy_actions`; everything else (statistics, acting, checkpoints) is here."""

    name = "learner"
    config_class = LearnerConfig

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        config: LearnerConfig | None = None,
        *,
        device=None,
        seed: int = 0,
    ):
        self.config = config or self.config_class()
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.device = select_device(device) if not isinstance(device, torch.device) else device
        self.step = 0
        # every random draw inside update() comes from here, so a resumed run continues identically
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)
        torch.manual_seed(seed)  # network initialization
        self.state_mean = torch.zeros(obs_dim, device=self.device)
        self.state_std = torch.ones(obs_dim, device=self.device)
        self.modules: dict[str, nn.Module] = {}
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.schedulers: dict[str, Any] = {}

    # ---- data statistics (real data only) -------------------------------------------------
    def fit_statistics(self, real: Transitions) -> None:
        """State mean/std from the real (source) data only: synthetic states must not shift them."""
        if self.config.normalize_states:
            normalizer = StateNormalizer.fit(real.observations)
            self.state_mean = torch.as_tensor(normalizer.mean, device=self.device)
            self.state_std = torch.as_tensor(normalizer.std, device=self.device)

    def normalize(self, observations: torch.Tensor) -> torch.Tensor:
        return (observations - self.state_mean) / self.state_std

    # ---- acting -------------------------------------------------------------------------
    def _policy_actions(self, observations: torch.Tensor) -> torch.Tensor:
        """Deterministic actions for normalized observations (B, ds) -> (B, da)."""
        raise NotImplementedError

    @torch.no_grad()
    def act(self, observations: np.ndarray) -> np.ndarray:
        """Deterministic actions for raw observations: (ds,) -> (da,) or (B, ds) -> (B, da)."""
        obs = torch.as_tensor(np.asarray(observations, dtype=np.float32), device=self.device)
        single = obs.dim() == 1
        actions = self._policy_actions(self.normalize(obs.reshape(-1, self.obs_dim)))
        actions = actions.clamp(-self.config.max_action, self.config.max_action).cpu().numpy()
        return actions[0] if single else actions

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One update; its metrics as 0-dim tensors on the device, read by the driver only at
        log time (a float() per update would wait for the device every step)."""
        raise NotImplementedError

    # ---- checkpoints --------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """All a resumed run needs: weights, optimizers, schedulers, step, RNG, statistics."""
        return {
            "learner": self.name,
            "config": self.config.to_dict(),
            "step": self.step,
            "generator": self.generator.get_state(),
            "state_mean": self.state_mean,
            "state_std": self.state_std,
            "modules": {k: m.state_dict() for k, m in self.modules.items()},
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "schedulers": {k: s.state_dict() for k, s in self.schedulers.items()},
            **self._extra_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("learner") != self.name:
            raise HipodeError(
                f"checkpoint: field 'learner': expected '{self.name}', "
                f"found {state.get('learner')!r}"
            )
        self.step = int(state["step"])
        self.generator.set_state(state["generator"])
        self.state_mean = state["state_mean"].to(self.device)
        self.state_std = state["state_std"].to(self.device)
        for key, module in self.modules.items():
            module.load_state_dict(state["modules"][key])
        for key, optimizer in self.optimizers.items():
            optimizer.load_state_dict(state["optimizers"][key])
        for key, scheduler in self.schedulers.items():
            scheduler.load_state_dict(state["schedulers"][key])
        self._load_extra_state(state)

    def _extra_state(self) -> dict[str, Any]:
        return {}

    def _load_extra_state(self, state: dict[str, Any]) -> None:
        """Subclasses restore what `_extra_state` saved."""
