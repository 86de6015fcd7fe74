"""HIPODE's five generators as one object: configuration, training (or loading from the cache
under datasets/ keyed by source sha256, config hash and seed) and the sampling interface the
generation step uses."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from hipode_pipeline.console import progress as progress_display
from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.device import fast_bf16, select_device
from hipode_pipeline.errors import DataFormatError, HipodeError, SettingError
from hipode_pipeline.files import (
    file_sha256,
    output_lock,
    save_torch_atomic,
    write_bytes_atomic,
    write_json_atomic,
)
from hipode_pipeline.models import training
from hipode_pipeline.models.cvae import CVAE
from hipode_pipeline.models.dynamics import LOSS_FORMS, DynamicsEnsemble
from hipode_pipeline.models.value import PENALTY_FORMS, PENALTY_SCALES, ValueEstimator
from hipode_pipeline.seeding import derive_seed
from hipode_pipeline.versions import GENERATOR_CODE, code_digest

MODEL_NAMES = ("state_transition", "value", "inverse_action", "inverse_reward", "dynamics")
# "paper": the appendix's sizes and this project's first fixed budgets, kept as they are while
# "full" (the defaults) may change with measurements; "quick": a few hundred steps per model
PROFILES = ("full", "paper", "quick")
CVAE_MODELS = ("state_transition", "inverse_action", "inverse_reward")
# fields that only some models read; any field not listed here is in every model's cache key
FIELD_OWNERS: dict[str, tuple[str, ...]] = {
    **{f: CVAE_MODELS for f in ("cvae_hidden", "latent_per_state_dim", "cvae_kl_weight")},
    **{f: CVAE_MODELS for f in ("cvae_log_std_min", "cvae_log_std_max", "latent_clip")},
    **{f: CVAE_MODELS for f in ("cvae_lr", "cvae_batch_size", "cvae_keep_best", "cvae_precision")},
    "state_transition_steps": ("state_transition",),
    "inverse_action_steps": ("inverse_action",),
    "inverse_reward_steps": ("inverse_reward",),
    **{
        f: ("value",)
        for f in (
            "value_hidden",
            "value_gamma",
            "value_tau",
            "value_target_every",
            "value_lr",
            "value_batch_size",
            "value_steps",
            "value_precision",
            "penalty",
            "penalty_scale",
            "alpha",
            "sigma",
        )
    },
    # stopping and budgets apply to the models whose best weights are kept (not the value net)
    **{
        f: (*CVAE_MODELS, "dynamics")
        for f in ("plateau_patience", "plateau_tolerance", "budget_epochs")
    },
    # elites are chosen after training from the members' held-out losses: no model's weights
    "dynamics_elites": (),
    **{
        f: ("dynamics",)
        for f in (
            "dynamics_members",
            "dynamics_hidden",
            "dynamics_plateau_patience",
            "dynamics_budget_epochs",
            "dynamics_lr_schedule",
            "dynamics_spectral_norm",
            "dynamics_loss",
            "dynamics_bound_loss_weight",
            "dynamics_lr",
            "dynamics_weight_decay",
            "dynamics_batch_size",
            "dynamics_steps",
            "dynamics_precision",
        )
    },
}


# the appendix's model sizes and the budgets every artifact was built with before the "full"
# defaults were allowed to move (fixed steps, no stopping, 5 members, raw penalty units)
PAPER_PROFILE: dict[str, Any] = {
    "cvae_hidden": 750,
    "latent_per_state_dim": 2,
    "value_hidden": 256,
    "dynamics_members": 5,
    "dynamics_elites": 0,
    "dynamics_hidden": (256, 256),
    "state_transition_steps": 30_000,
    "inverse_action_steps": 20_000,
    "inverse_reward_steps": 15_000,
    "value_steps": 50_000,
    "dynamics_steps": 30_000,
    "plateau_patience": 0,
    "budget_epochs": 0.0,
    "dynamics_plateau_patience": -1,
    "dynamics_budget_epochs": -1.0,
    "dynamics_lr_schedule": "constant",
    "penalty_scale": "raw",
}


@dataclass(frozen=True)
class GeneratorConfig:
    """Every setting of the five generators; [paper] and [decided] defaults from METHOD.md.

    The CVAEs' budgets are passes over the data (budget_epochs) stopped on a held-out plateau;
    the ensemble and the value net train fixed step budgets. Profile "paper" keeps the fixed
    budgets every model had before these became the defaults.
    """

    # --- the three CVAEs (state transition, inverse action, inverse reward) ---
    cvae_hidden: int = 750  # [paper] one hidden layer of this width in encoder and decoder
    latent_per_state_dim: int = 2  # [paper] latent dimension = this x state dimension
    cvae_kl_weight: float = 0.5  # [decided, BCQ] loss = reconstruction MSE + this x KL
    cvae_log_std_min: float = -4.0  # [decided, BCQ] encoder log sigma clamped from below
    cvae_log_std_max: float = 15.0  # [decided, BCQ] encoder log sigma clamped from above
    latent_clip: float = 0.5  # [decided, BCQ] sampling draws z ~ N(0, I) clipped to +-this
    cvae_lr: float = 1e-3  # Adam step size of the CVAEs (BCQ's VAE setting)
    cvae_batch_size: int = 256  # CVAE minibatch (BCQ: 100; 256 keeps the matmuls efficient)
    cvae_keep_best: bool = True  # restore each CVAE's weights of lowest held-out loss
    state_transition_steps: int = 30_000  # gradient steps of D_psi(s, z) -> s'
    inverse_action_steps: int = 20_000  # steps of D_eps(s, s', z) -> a, tanh-bounded to data range
    inverse_reward_steps: int = 15_000  # gradient steps of D_zeta(s, s', z) -> r
    standardize_rewards: bool = True  # z-score rewards inside reward CVAE and dynamics; raw out
    # --- value estimator with negative sampling ---
    value_hidden: int = 256  # [paper] one hidden layer of this width
    value_gamma: float = 0.99  # [decided] TD(0) discount on dataset transitions
    value_tau: float = 0.005  # [paper] soft target update rate
    value_target_every: int = 2  # [paper] soft-update the target every this many gradient steps
    value_lr: float = 3e-4  # Adam step size of V (CORL's critic setting)
    value_batch_size: int = 256  # value minibatch; as many negatives are drawn per step
    value_steps: int = 50_000  # steps of V; final weights kept (TD loss moves with the target)
    penalty: str = "target"  # [decided] negative-sampling penalty: target | l2 | contrastive
    # units of the target penalty's alpha: "raw" (reward units per z-scored unit of offset, the
    # paper's) or "value" (the batch's std of V-bar(s) per unit: the same meaning on every task)
    penalty_scale: str = "raw"
    alpha: float = 1.0  # [paper] penalty weight (per task: stages/tasks.toml)
    sigma: float = 1.0  # [paper] negatives s + U(-sigma, sigma)^d, z-scored units
    # --- forward dynamics ensemble (d3rlpy 1.x ProbabilisticEnsembleDynamics) ---
    dynamics_members: int = 5  # [paper via d3rlpy] ensemble size
    # members the dynamics check draws from: the lowest held-out losses (0: all; MOPO: 5 of 7)
    dynamics_elites: int = 0
    dynamics_hidden: tuple[int, ...] = (256, 256)  # [d3rlpy 1.x encoder] hidden layers per member
    dynamics_spectral_norm: bool = False  # d3rlpy 1.x: on; off here: it made members underfit
    dynamics_loss: str = "gaussian_nll"  # gaussian_nll | d3rlpy (e^2 / std + sum log std)
    dynamics_bound_loss_weight: float = 0.01  # [d3rlpy 1.x] pulls the log-std bounds together
    dynamics_lr: float = 1e-3  # [d3rlpy 1.x] Adam step size
    dynamics_lr_schedule: str = "constant"  # constant | cosine (decays to 0 over the budget)
    dynamics_weight_decay: float = 1e-4  # [d3rlpy 1.x] Adam weight decay
    dynamics_batch_size: int = 256  # minibatch (d3rlpy: 100); each member learns from half of it
    # steps of the ensemble, best weights kept per member [decided]: twice the paper profile's
    # 30k, which left it undertrained (bench/results/dynamics_fit.md, verify.md arm "fitted")
    dynamics_steps: int = 60_000
    # --- shared training settings ---
    heldout_fraction: float = 0.05  # [decided] share of source transitions never trained on
    heldout_eval_rows: int = 8192  # held-out rows used per evaluation (caps its cost)
    eval_every: int = 500  # evaluate the held-out loss (and keep bests) every this many steps
    # stop a CVAE or the ensemble after this many evaluations in a row without its best held-out
    # loss falling by more than plateau_tolerance of it (0: always the whole budget)
    plateau_patience: int = 8
    plateau_tolerance: float = 1e-3
    # > 0: CVAE and ensemble budgets are this many passes over the training rows (at their batch
    # size) instead of the fixed *_steps, so they scale with the dataset
    budget_epochs: float = 60.0
    # the ensemble's own stopping and budget: -1 follows plateau_patience / budget_epochs (as
    # the CVAEs); 0 trains it for dynamics_steps whatever the CVAEs do (the default: stopped on
    # a plateau it ended worse, bench/results/verify.md)
    dynamics_plateau_patience: int = 0
    dynamics_budget_epochs: float = 0.0
    checkpoint_every: int = 2_000  # write a resumable checkpoint every this many steps
    # fp32 | bf16 autocast, per model family: bf16 kept held-out losses equal within seed noise
    # and ran 1.3-1.7x faster on the CVAEs and the ensemble (bench/results/models_precision.md);
    # the 256-wide value net gains nothing and its targets (~100s) need fp32 resolution
    cvae_precision: str = "bf16"  # the three CVAEs' training matmuls
    value_precision: str = "fp32"  # the value net's training matmuls
    dynamics_precision: str = "bf16"  # the ensemble's training matmuls
    normalizer_eps: float = 1e-3  # [decided] added to the state std before z-scoring

    def __post_init__(self) -> None:
        object.__setattr__(self, "dynamics_hidden", tuple(int(h) for h in self.dynamics_hidden))
        checks = {
            "penalty": (self.penalty in PENALTY_FORMS, f"one of {PENALTY_FORMS}"),
            "dynamics_loss": (self.dynamics_loss in LOSS_FORMS, f"one of {LOSS_FORMS}"),
            "heldout_fraction": (0 < self.heldout_fraction < 1, "a fraction in (0, 1)"),
            "latent_clip": (self.latent_clip > 0, "a positive number"),
            "sigma": (math.isfinite(self.sigma) and self.sigma >= 0, "a finite number >= 0"),
            "alpha": (math.isfinite(self.alpha), "a finite number"),
            "penalty_scale": (
                self.penalty_scale in PENALTY_SCALES
                and (self.penalty_scale == "raw" or self.penalty == "target"),
                f"one of {PENALTY_SCALES} ('value' only with penalty 'target')",
            ),
            "plateau_patience": (self.plateau_patience >= 0, "a non-negative integer"),
            "plateau_tolerance": (
                math.isfinite(self.plateau_tolerance) and 0 <= self.plateau_tolerance < 1,
                "a fraction in [0, 1)",
            ),
            "budget_epochs": (
                math.isfinite(self.budget_epochs) and self.budget_epochs >= 0,
                "a finite number >= 0",
            ),
            "dynamics_plateau_patience": (
                self.dynamics_plateau_patience >= -1,
                "-1 (as plateau_patience) or a non-negative integer",
            ),
            "dynamics_budget_epochs": (
                math.isfinite(self.dynamics_budget_epochs)
                and (self.dynamics_budget_epochs >= 0 or self.dynamics_budget_epochs == -1),
                "-1 (as budget_epochs) or a finite number >= 0",
            ),
            "dynamics_lr_schedule": (
                self.dynamics_lr_schedule in training.LR_SCHEDULES,
                f"one of {training.LR_SCHEDULES}",
            ),
            "dynamics_elites": (
                0 <= self.dynamics_elites <= self.dynamics_members,
                f"an integer in [0, dynamics_members = {self.dynamics_members}]",
            ),
        }
        for name in self.to_dict():
            if name.endswith("_precision") and getattr(self, name) not in training.PRECISIONS:
                checks[name] = (False, f"one of {training.PRECISIONS}")
            if name.endswith(("_steps",)) and getattr(self, name) < 0:
                checks[name] = (False, "a non-negative integer")
            if (
                name.endswith(("_batch_size", "_hidden", "_every", "_eval_rows", "_members"))
                and name != "dynamics_hidden"
            ):
                if getattr(self, name) < 1:
                    checks[name] = (False, "a positive integer")
        for name, (ok, expected) in checks.items():
            if not ok:
                raise SettingError(
                    f"generator config field '{name}': expected {expected}, "
                    f"found {getattr(self, name)!r}"
                )

    @classmethod
    def profile(cls, name: str, **overrides: Any) -> GeneratorConfig:
        """Profile "full" (the defaults), "paper" (the appendix's sizes and the first fixed
        budgets, whatever the defaults become) or "quick" (a few hundred steps per model)."""
        if name not in PROFILES:
            raise SettingError(f"generator profile '{name}': expected one of {PROFILES}")
        values: dict[str, Any] = {}
        if name == "paper":
            values = dict(PAPER_PROFILE)
        if name == "quick":
            values = {
                "plateau_patience": 0,
                "budget_epochs": 0.0,
                "state_transition_steps": 300,
                "inverse_action_steps": 300,
                "inverse_reward_steps": 300,
                "value_steps": 300,
                "dynamics_steps": 300,
                "eval_every": 50,
                "checkpoint_every": 100,
                "heldout_eval_rows": 2048,
            }
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise SettingError(
                f"generator config override {unknown}: expected fields among {sorted(known)}"
            )
        return cls(**{**values, **overrides})

    def to_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["dynamics_hidden"] = list(self.dynamics_hidden)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> GeneratorConfig:
        return cls(**data)

    def on_device(
        self, device: torch.device, asked: Collection[str] = ()
    ) -> tuple[GeneratorConfig, list[str]]:
        """This config for `device`, and the precision fields it moved: a bf16 precision that
        was not `asked` for becomes fp32 where bf16 is not native (torch emulates it there, far
        slower than fp32), so a cache key and a manifest name the precision that trained."""
        if fast_bf16(device):
            return self, []
        moved = [
            name
            for name in self.to_dict()
            if name.endswith("_precision") and getattr(self, name) == "bf16" and name not in asked
        ]
        return dataclasses.replace(self, **{name: "fp32" for name in moved}), moved

    def hash(self) -> str:
        """sha256 over the sorted JSON of every field: the cache key of trained generators."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()

    def model_key(self, name: str) -> str:
        """sha256 over the fields model `name` depends on: every field except those that only
        other models use (FIELD_OWNERS), so an alpha ablation can reuse the four other models."""
        relevant = {
            field: value
            for field, value in self.to_dict().items()
            if name in FIELD_OWNERS.get(field, MODEL_NAMES)
        }
        return hashlib.sha256(json.dumps(relevant, sort_keys=True).encode()).hexdigest()


@dataclass(eq=False)
class Generators:
    """The five trained models, in eval mode on `device`, with where they came from."""

    normalizer: StateNormalizer
    state_transition: CVAE  # .sample(s_norm (B, ds), n) -> (B, n, ds) normalized next states
    value: ValueEstimator  # (..., ds) normalized states -> (...) values
    inverse_action: CVAE  # .sample(cat[s_norm, s'_norm] (B, 2ds), n) -> (B, n, da) raw actions
    inverse_reward: CVAE  # .sample(cat[s_norm, s'_norm] (B, 2ds), n) -> (B, n, 1) raw rewards
    dynamics: DynamicsEnsemble  # .sample(s_norm, a) -> (s'_norm (B, ds), r (B,))
    config: GeneratorConfig
    device: torch.device
    cache_dir: Path
    checkpoint_hashes: dict[str, str] = field(
        default_factory=dict
    )  # model -> sha256 of its weights file
    training_report: dict[str, dict] = field(
        default_factory=dict
    )  # model -> TrainingRecord as a dict

    def models(self) -> dict[str, nn.Module]:
        return {name: getattr(self, name) for name in MODEL_NAMES}


def cache_dir_for(cache_root: Path, source_sha256: str, config: GeneratorConfig, seed: int) -> Path:
    """<source sha256>-<code digest>-<config hash>-seed<seed>: the code that trains the models is
    part of the key, so edited model code never reuses weights trained by the old one."""
    code = code_digest(GENERATOR_CODE)[:12]
    return Path(cache_root) / f"{source_sha256[:16]}-{code}-{config.hash()[:12]}-seed{seed}"


def build_models(
    state_dim: int, action_dim: int, config: GeneratorConfig, seed: int
) -> dict[str, nn.Module]:
    """The five untrained models with seeded initial weights (on CPU)."""
    latent = config.latent_per_state_dim * state_dim
    cvae_args = dict(
        latent_dim=latent,
        hidden=config.cvae_hidden,
        log_std_min=config.cvae_log_std_min,
        log_std_max=config.cvae_log_std_max,
        kl_weight=config.cvae_kl_weight,
        latent_clip=config.latent_clip,
    )
    makers = {
        "state_transition": lambda: CVAE(state_dim, state_dim, **cvae_args),
        "value": lambda: ValueEstimator(
            state_dim,
            hidden=config.value_hidden,
            gamma=config.value_gamma,
            tau=config.value_tau,
            target_update_every=config.value_target_every,
            penalty=config.penalty,
            penalty_scale=config.penalty_scale,
            alpha=config.alpha,
            sigma=config.sigma,
        ),
        "inverse_action": lambda: CVAE(action_dim, 2 * state_dim, squash=True, **cvae_args),
        "inverse_reward": lambda: CVAE(
            1, 2 * state_dim, standardize_output=config.standardize_rewards, **cvae_args
        ),
        "dynamics": lambda: DynamicsEnsemble(
            state_dim,
            action_dim,
            members=config.dynamics_members,
            hidden=config.dynamics_hidden,
            spectral_norm=config.dynamics_spectral_norm,
            loss_form=config.dynamics_loss,
            bound_loss_weight=config.dynamics_bound_loss_weight,
        ),
    }
    models = {}
    for name, make in makers.items():
        with training.seeded_init(derive_seed(seed, f"init:{name}")):
            models[name] = make()
    return models


def fit_settings(config: GeneratorConfig, train_rows: int) -> dict[str, dict[str, Any]]:
    """Per model: budget, optimizer settings, stopping and what best-weights keeping means for
    it; `train_rows` (the source's rows outside the held-out split) sizes epoch budgets."""
    cvae_keep = "model" if config.cvae_keep_best else "none"
    stopping = dict(
        plateau_patience=config.plateau_patience, plateau_tolerance=config.plateau_tolerance
    )
    cvae = dict(
        batch_size=config.cvae_batch_size,
        lr=config.cvae_lr,
        weight_decay=0.0,
        keep_best=cvae_keep,
        precision=config.cvae_precision,
        **(stopping if config.cvae_keep_best else {}),
    )

    def budget(fixed_steps: int, batch_size: int, epochs: float = config.budget_epochs) -> int:
        if epochs <= 0:
            return fixed_steps
        return max(1, math.ceil(epochs * train_rows / batch_size))

    def own_or_shared(own: float, shared: float) -> float:
        return shared if own == -1 else own  # -1: the ensemble follows the CVAEs' setting

    dynamics_epochs = own_or_shared(config.dynamics_budget_epochs, config.budget_epochs)
    dynamics_patience = int(
        own_or_shared(config.dynamics_plateau_patience, config.plateau_patience)
    )

    return {
        "state_transition": dict(
            steps=budget(config.state_transition_steps, config.cvae_batch_size), **cvae
        ),
        "value": dict(
            steps=config.value_steps,
            batch_size=config.value_batch_size,
            lr=config.value_lr,
            weight_decay=0.0,
            keep_best="none",
            precision=config.value_precision,
        ),
        "inverse_action": dict(
            steps=budget(config.inverse_action_steps, config.cvae_batch_size), **cvae
        ),
        "inverse_reward": dict(
            steps=budget(config.inverse_reward_steps, config.cvae_batch_size), **cvae
        ),
        "dynamics": dict(
            steps=budget(config.dynamics_steps, config.dynamics_batch_size, dynamics_epochs),
            batch_size=config.dynamics_batch_size,
            lr=config.dynamics_lr,
            weight_decay=config.dynamics_weight_decay,
            keep_best="member",
            precision=config.dynamics_precision,
            plateau_patience=dynamics_patience,
            plateau_tolerance=config.plateau_tolerance,
            lr_schedule=config.dynamics_lr_schedule,
        ),
    }


def model_losses(
    models: dict[str, nn.Module],
) -> dict[str, tuple[training.LossFn, training.HeldoutFn]]:
    """Per model: (training loss on a batch, held-out loss on a batch)."""
    state, value, action, reward, dynamics = (models[n] for n in MODEL_NAMES)

    def eval_generator(device: torch.device) -> torch.Generator:
        # the same noise at every evaluation, so held-out readings are comparable
        return torch.Generator(device=device).manual_seed(0)

    def pair(b):
        return torch.cat([b["s"], b["s_next"]], dim=-1)

    return {
        "state_transition": (
            lambda b, g: state.loss(b["s_next"], b["s"], g),
            lambda b: state.loss(b["s_next"], b["s"], eval_generator(b["s"].device))[0],
        ),
        "value": (
            lambda b, g: value.loss(b["s"], b["r"], b["s_next"], b["terminal"], g),
            lambda b: value.td_loss(b["s"], b["r"], b["s_next"], b["terminal"]),
        ),
        "inverse_action": (
            lambda b, g: action.loss(b["a"], pair(b), g),
            lambda b: action.loss(b["a"], pair(b), eval_generator(b["s"].device))[0],
        ),
        "inverse_reward": (
            lambda b, g: reward.loss(b["r"].unsqueeze(-1), pair(b), g),
            lambda b: reward.loss(b["r"].unsqueeze(-1), pair(b), eval_generator(b["s"].device))[0],
        ),
        "dynamics": (
            lambda b, g: dynamics.loss(b["s"], b["a"], b["r"], b["s_next"], g),
            lambda b: dynamics.heldout_losses(b["s"], b["a"], b["r"], b["s_next"]),
        ),
    }


def set_data_scales(
    models: dict[str, nn.Module], transitions: Transitions, config: GeneratorConfig
) -> None:
    """Action bounds and reward scales go into model buffers, so cached weights carry them."""
    actions, rewards = transitions.actions, transitions.rewards.astype(np.float64)
    # [decided] action bounds = the source's per-dimension range (D4RL MuJoCo data spans [-1, 1])
    models["inverse_action"].set_output_bounds(
        torch.from_numpy(actions.min(0)), torch.from_numpy(actions.max(0))
    )
    if config.standardize_rewards:
        mean, std = float(rewards.mean()), float(rewards.std()) + 1e-6
        models["inverse_reward"].set_output_scale(torch.tensor([mean]), torch.tensor([std]))
        models["dynamics"].set_reward_scale(mean, std)


def transition_tensors(
    transitions: Transitions,
    normalizer: StateNormalizer,
    config: GeneratorConfig,
    seed: int,
    device: torch.device,
) -> training.TensorData:
    def put(array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32)).to(device)

    tensors = {
        "s": put(normalizer.normalize(transitions.observations)),
        "a": put(transitions.actions),
        "r": put(transitions.rewards),
        "s_next": put(normalizer.normalize(transitions.next_observations)),
        "terminal": put(transitions.terminals),
    }
    return training.TensorData(tensors, config.heldout_fraction, config.heldout_eval_rows, seed)


def train_generators(
    transitions: Transitions,
    source_sha256: str,
    config: GeneratorConfig,
    *,
    cache_root: Path,
    seed: int,
    device: str | torch.device | None = None,
    show_progress: bool = True,
) -> Generators:
    """Train the five models, or load the finished ones from their cache folder under
    `cache_root` (`cache_dir_for`); an interrupted model resumes from its last checkpoint there."""
    device = device if isinstance(device, torch.device) else select_device(device)
    cache_dir = cache_dir_for(cache_root, source_sha256, config, seed)
    cache_dir.mkdir(parents=True, exist_ok=True)
    if not (cache_dir / "config.json").exists():
        write_json_atomic(
            cache_dir / "config.json",
            {
                "source_sha256": source_sha256,
                "seed": seed,
                "code_digest": code_digest(GENERATOR_CODE),
                "config": config.to_dict(),
            },
        )
    normalizer = StateNormalizer.fit(transitions.observations, eps=config.normalizer_eps)
    if not (cache_dir / "normalizer.json").exists():
        write_json_atomic(cache_dir / "normalizer.json", normalizer.to_dict())

    models = build_models(transitions.obs_dim, transitions.act_dim, config, seed)
    set_data_scales(models, transitions, config)
    for model in models.values():
        model.to(device)
    train_rows = len(transitions) - training.heldout_count(
        len(transitions), config.heldout_fraction
    )
    settings, losses = fit_settings(config, train_rows), model_losses(models)
    report: dict[str, dict] = {}
    data: training.TensorData | None = None
    with progress_display(disable=not show_progress) as prog:
        for name in MODEL_NAMES:
            weights_path, record_path = cache_dir / f"{name}.pt", cache_dir / f"{name}.json"
            # a second stage one on the same cache waits here, then loads what the first trained
            with output_lock(weights_path, command=f"hipode augment (generator {name})"):
                if not weights_path.exists():
                    _adopt_from_sibling(cache_dir, name, config, weights_path, record_path)
                if weights_path.exists() and record_path.exists():
                    _load_weights(models[name], weights_path)
                    record = json.loads(record_path.read_text())
                    report[name] = {**record, "cached": True}
                    continue
                if data is None:
                    data = transition_tensors(transitions, normalizer, config, seed, device)
                train_loss, heldout_loss = losses[name]
                after_step = models["value"].update_target if name == "value" else None
                record = training.fit(
                    name,
                    models[name],
                    train_loss,
                    heldout_loss,
                    data,
                    seed=seed,
                    eval_every=config.eval_every,
                    checkpoint_every=config.checkpoint_every,
                    checkpoint_path=cache_dir / f"{name}.ckpt.pt",
                    after_step=after_step,
                    progress=prog,
                    **settings[name],
                )
                save_torch_atomic(weights_path, models[name].state_dict())
                write_json_atomic(record_path, record.to_dict())
                (cache_dir / f"{name}.ckpt.pt").unlink(missing_ok=True)
                report[name] = record.to_dict()
    models["dynamics"].set_elites(
        elite_members(report["dynamics"].get("member_best_heldout_losses"), config)
    )
    for model in models.values():
        model.eval().requires_grad_(False)
    hashes = {name: file_sha256(cache_dir / f"{name}.pt") for name in MODEL_NAMES}
    return Generators(
        normalizer=normalizer,
        config=config,
        device=device,
        cache_dir=cache_dir,
        checkpoint_hashes=hashes,
        training_report=report,
        **models,
    )


def elite_members(member_losses: list[float] | None, config: GeneratorConfig) -> list[int] | None:
    """The `dynamics_elites` members of lowest held-out loss, in member order (None: all)."""
    if not config.dynamics_elites or config.dynamics_elites >= config.dynamics_members:
        return None
    if member_losses is None or len(member_losses) != config.dynamics_members:
        raise DataFormatError(
            "dynamics.json",
            "member_best_heldout_losses",
            f"{config.dynamics_members} per-member held-out losses to choose elites from",
            member_losses,
        )
    ranked = sorted(range(len(member_losses)), key=lambda m: (member_losses[m], m))
    return sorted(ranked[: config.dynamics_elites])


def _adopt_from_sibling(
    cache_dir: Path, name: str, config: GeneratorConfig, weights_path: Path, record_path: Path
) -> None:
    """Copy model `name` from another config's cache of the same source and seed when that
    config trained it with identical settings (GeneratorConfig.model_key): same inputs, same
    per-model seeds, so the same weights."""
    source_prefix, code_part, _ = cache_dir.name.split("-", 2)
    seed_suffix = cache_dir.name.rsplit("-", 1)[1]
    key = config.model_key(name)
    # only caches of the same source, code and seed: other code may train other weights
    for sibling in sorted(cache_dir.parent.glob(f"{source_prefix}-{code_part}-*-{seed_suffix}")):
        weights, record = sibling / f"{name}.pt", sibling / f"{name}.json"
        if sibling == cache_dir or not (weights.exists() and record.exists()):
            continue
        try:
            other = GeneratorConfig.from_dict(
                json.loads((sibling / "config.json").read_text())["config"]
            )
        except (OSError, ValueError, KeyError, TypeError, HipodeError):
            continue  # an unreadable or older cache entry is simply not reused
        if other.model_key(name) == key:
            write_bytes_atomic(weights_path, weights.read_bytes())
            data = {**json.loads(record.read_text()), "reused_from": sibling.name}
            write_json_atomic(record_path, data)
            return


def _load_weights(model: nn.Module, path: Path) -> None:
    state = training.load_tensors(path, "a generator weights file")
    try:
        model.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as error:
        raise DataFormatError(
            path,
            "(weights)",
            f"weights matching {type(model).__name__}; delete the file to retrain",
            str(error).splitlines()[0],
        ) from None
