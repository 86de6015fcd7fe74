"""What every built-in learner shares: the batch type, K seeds trained side by side, state
statistics from real data only, device choice, per-seed checkpoints that resume exactly and
deterministic acting."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.device import select_device
from hipode_pipeline.errors import HipodeError
from hipode_pipeline.learners.stacked import init_generators
from hipode_pipeline.overrides import check_fields
from hipode_pipeline.replay import Batch

__all__ = [
    "Batch",
    "Learner",
    "LearnerConfig",
    "adam",
    "polyak_",
    "select_device",
    "as_seed_batch",
]


@dataclass
class LearnerConfig:
    """Fields every learner config has; each learner adds its own below these."""

    discount: float = 0.99  # gamma
    tau: float = 0.005  # Polyak rate of the target networks
    hidden_dim: int = 256  # width of every hidden layer
    normalize_states: bool = True  # z-score states with the real data's statistics
    max_action: float = 1.0  # actions live in [-max_action, max_action]
    # bfloat16 hidden-layer matmuls (heads, targets and losses stay fp32); None: fp32 here, and
    # in `hipode train` the default stages/train.toml [<learner>.precision] sets per device
    bf16: bool | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any], origin: str = "learner settings"):
        """Build from a dict (a TOML table, CLI overrides), naming unknown keys and values of
        the wrong type clearly."""
        return cls(**check_fields(cls, values, f"{origin} ({cls.__name__})"))


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


def as_seed_batch(batch: Batch, n_seeds: int) -> Batch:
    """A (K, B, ...) batch as is; a one-seed learner also takes a plain (B, ...) batch."""
    if batch.rewards.dim() == 2:
        if batch.rewards.shape[0] != n_seeds:
            raise HipodeError(
                f"batch: expected {n_seeds} seed rows (K, B, ...), found {batch.rewards.shape[0]}"
            )
        return batch
    if n_seeds != 1:
        raise HipodeError(f"batch: expected a (K={n_seeds}, B, ...) batch, found (B, ...)")
    return Batch(*(field.unsqueeze(0) for field in batch))


def _slice_state(value: Any, k: int) -> Any:
    """Seed k's part of a module or optimizer state: every tensor with a seed axis sliced to
    k:k+1 (the layout a one-seed learner has), scalars (Adam's step) kept."""
    if isinstance(value, torch.Tensor):
        return value[k : k + 1].clone() if value.dim() > 0 else value.clone()
    if isinstance(value, dict):
        return {key: _slice_state(v, k) for key, v in value.items()}
    if isinstance(value, list):
        return [_slice_state(v, k) for v in value]
    return value


def _stack_states(values: list[Any]) -> Any:
    """The inverse of _slice_state over all seeds: tensors concatenated on the seed axis."""
    first = values[0]
    if isinstance(first, torch.Tensor):
        return torch.cat(values) if first.dim() > 0 else first.clone()
    if isinstance(first, dict):
        return {key: _stack_states([v[key] for v in values]) for key in first}
    if isinstance(first, list):
        return [_stack_states([v[i] for v in values]) for i in range(len(first))]
    return first


class Learner:
    """Base of TD3BC, IQL and CQL, trained for K seeds at once (K = 1 is a plain run): every
    network is stacked over seeds (`stacked`), each seed has its own random stream, and a seed's
    state (weights, optimizer moments, RNG) is saved and restored on its own, in the layout a
    one-seed learner has. Subclasses build `modules` and `optimizers` and implement `update` and
    `_policy_actions`; statistics, acting and checkpoints are here."""

    name = "learner"
    config_class = LearnerConfig

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        config: LearnerConfig | None = None,
        *,
        device=None,
        seed: int | Sequence[int] = 0,
    ):
        self.config = config or self.config_class()
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.device = select_device(device) if not isinstance(device, torch.device) else device
        self.seeds = [int(seed)] if isinstance(seed, int) else [int(s) for s in seed]
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise HipodeError(f"seeds: expected distinct training seeds, found {self.seeds}")
        self.n_seeds = len(self.seeds)
        self.step = 0
        # every random draw inside update() comes from these, so a resumed run continues
        # identically and seed k's draws do not depend on which other seeds run beside it
        self.generators = [torch.Generator(device=self.device).manual_seed(s) for s in self.seeds]
        self.init_generators = init_generators(self.seeds)  # network initialization
        self.state_mean = torch.zeros(obs_dim, device=self.device)
        self.state_std = torch.ones(obs_dim, device=self.device)
        self.use_bf16 = bool(self.config.bf16)
        self.modules: dict[str, nn.Module] = {}
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.schedulers: dict[str, Any] = {}

    def apply_precision(self) -> None:
        """Tell every stacked network in `modules` whether its hidden matmuls run in bf16."""
        for module in self.modules.values():
            for part in module.modules():
                if hasattr(part, "use_bf16"):
                    part.use_bf16 = self.use_bf16

    # ---- random draws, one stream per seed ----------------------------------------------------
    def randn(self, *shape: int) -> torch.Tensor:
        """(K, *shape) standard normals, seed k's from its own generator."""
        return torch.stack(
            [torch.randn(shape, generator=g, device=self.device) for g in self.generators]
        )

    def uniform(self, low: float, high: float, *shape: int) -> torch.Tensor:
        """(K, *shape) uniforms on [low, high), seed k's from its own generator."""
        return torch.stack(
            [
                torch.empty(shape, device=self.device).uniform_(low, high, generator=g)
                for g in self.generators
            ]
        )

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
        """Deterministic actions for normalized observations (K, n, ds) -> (K, n, da)."""
        raise NotImplementedError

    @torch.no_grad()
    def act_all(self, observations: np.ndarray) -> np.ndarray:
        """Every seed's deterministic actions for its own raw observations: (K, n, ds) ->
        (K, n, da)."""
        obs = torch.as_tensor(np.asarray(observations, dtype=np.float32), device=self.device)
        if obs.dim() != 3 or obs.shape[0] != self.n_seeds:
            raise HipodeError(
                f"act_all: expected observations ({self.n_seeds}, n, {self.obs_dim}), "
                f"found {tuple(obs.shape)}"
            )
        actions = self._policy_actions(self.normalize(obs))
        return actions.clamp(-self.config.max_action, self.config.max_action).cpu().numpy()

    def act(self, observations: np.ndarray) -> np.ndarray:
        """A one-seed learner's deterministic actions: (ds,) -> (da,) or (B, ds) -> (B, da)."""
        if self.n_seeds != 1:
            raise HipodeError(f"act: this learner trains {self.n_seeds} seeds; use act_all")
        obs = np.asarray(observations, dtype=np.float32)
        actions = self.act_all(obs.reshape(1, -1, self.obs_dim))[0]
        return actions[0] if obs.ndim == 1 else actions

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One update of every seed on its own (K, B, ...) batch; its metrics as (K,) tensors on
        the device, read by the driver only at log time (a float() per update would wait for
        the device every step)."""
        raise NotImplementedError

    # ---- checkpoints --------------------------------------------------------------------
    def seed_state(self, k: int = 0) -> dict[str, Any]:
        """All a resumed run of seed index k needs (weights, optimizer moments, schedulers,
        step, its RNG, statistics), in a one-seed learner's layout."""
        return {
            "learner": self.name,
            "config": self.config.to_dict(),
            "seed": self.seeds[k],
            "step": self.step,
            "generator": self.generators[k].get_state(),
            "state_mean": self.state_mean,
            "state_std": self.state_std,
            "modules": {key: _slice_state(m.state_dict(), k) for key, m in self.modules.items()},
            "optimizers": {
                key: _slice_state(o.state_dict(), k) for key, o in self.optimizers.items()
            },
            "schedulers": {key: s.state_dict() for key, s in self.schedulers.items()},
            **self._extra_state(),
        }

    def load_seed_states(self, states: list[dict[str, Any]], origin: str = "checkpoint") -> None:
        """Restore every seed from its own state (seed_state's), all at the same step."""
        if len(states) != self.n_seeds:
            raise HipodeError(f"{origin}: expected {self.n_seeds} seed states, found {len(states)}")
        for state in states:
            if state.get("learner") != self.name:
                raise HipodeError(
                    f"{origin}: field 'learner': expected '{self.name}', "
                    f"found {state.get('learner')!r}"
                )
        steps = sorted({int(state["step"]) for state in states})
        if len(steps) != 1:
            raise HipodeError(f"{origin}: expected seeds at one step, found steps {steps}")
        self.step = steps[0]
        # the states say which seeds these are: their streams continue under their own names
        self.seeds = [
            int(state.get("seed", seed)) for state, seed in zip(states, self.seeds, strict=True)
        ]
        first = states[0]
        for generator, state in zip(self.generators, states, strict=True):
            generator.set_state(state["generator"])
        self.state_mean = first["state_mean"].to(self.device)
        self.state_std = first["state_std"].to(self.device)
        try:
            for key, module in self.modules.items():
                module.load_state_dict(_stack_states([s["modules"][key] for s in states]))
            for key, optimizer in self.optimizers.items():
                optimizer.load_state_dict(_stack_states([s["optimizers"][key] for s in states]))
        except (KeyError, RuntimeError, ValueError) as error:
            detail = " ".join(line.strip() for line in str(error).splitlines()[:3])[:400]
            raise HipodeError(
                f"{origin}: its weights do not fit this {self.name} learner (saved by an older "
                f"layout or other settings: {detail}); rerun with --force to start the run "
                "afresh"
            ) from error
        for key, scheduler in self.schedulers.items():
            scheduler.load_state_dict(first["schedulers"][key])
        self._load_extra_state(first)

    def state_dict(self) -> dict[str, Any]:
        """A one-seed learner's state (seed_state(0))."""
        if self.n_seeds != 1:
            raise HipodeError(f"state_dict: {self.n_seeds} seeds; use seed_state(k)")
        return self.seed_state(0)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.load_seed_states([state])

    def _extra_state(self) -> dict[str, Any]:
        return {}

    def _load_extra_state(self, state: dict[str, Any]) -> None:
        """Subclasses restore what `_extra_state` saved."""
