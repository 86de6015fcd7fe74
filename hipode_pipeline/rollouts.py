"""The policy-decoupled baseline HIPODE is compared with: plain one-step model rollouts.

From a source state s, an action a ~ a behaviour CVAE a | s trained on the source, then
(s', r) ~ the dynamics ensemble HIPODE itself checks with, and the env's own termination rule
on s'. No candidate next states, no value, no selection: every finite rollout is kept. This is
the paper's "MB" comparison (Appendix C.5: data from a dynamics model, driven by the data's
behaviour policy) with HIPODE's own models, so only the way data is proposed differs.

`hipode augment --method model-rollouts` writes such an artifact (the same contract as HIPODE's,
η·N rows) and `hipode verify` steps the simulator from the same rollouts as its baseline.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hipode_pipeline import console
from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.envs import termination_rule
from hipode_pipeline.errors import SettingError
from hipode_pipeline.files import save_torch_atomic, write_json_atomic
from hipode_pipeline.generate import (
    MAX_ETA,
    GenerationResult,
    SourceOrder,
    kept_result,
    synthetic_rows,
)
from hipode_pipeline.models import training
from hipode_pipeline.models.cvae import CVAE
from hipode_pipeline.models.generators import Generators
from hipode_pipeline.seeding import derive_seed


@dataclass(frozen=True)
class BehaviourCVAEConfig:
    """The baseline's behaviour policy: a CVAE a | s trained on the source (small budget)."""

    steps: int = 5_000  # Adam steps
    batch_size: int = 256  # transitions per step
    lr: float = 1e-3  # Adam learning rate
    hidden: int = 750  # hidden width of encoder and decoder (as the generators' CVAEs)
    latent_per_action_dim: int = 2  # latent size = this * action dim (BCQ's choice)
    kl_weight: float = 0.5  # weight of the KL term
    latent_clip: float = 0.5  # |z| bound when sampling
    heldout_fraction: float = 0.05  # share of source transitions never trained on
    heldout_eval_rows: int = 4096  # held-out rows per evaluation
    eval_every: int = 500  # evaluate and keep the best weights every this many steps
    checkpoint_every: int = 2_000  # resumable checkpoint every this many steps

    def hash(self) -> str:
        """The cache key of trained weights."""
        return hashlib.sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()


def behaviour_config(profile: str) -> BehaviourCVAEConfig:
    """The behaviour model's budget for a generator profile: a few hundred steps for "quick"
    (tests), the default otherwise."""
    if profile == "quick":
        return BehaviourCVAEConfig(
            steps=300, eval_every=50, checkpoint_every=100, heldout_eval_rows=2048
        )
    return BehaviourCVAEConfig()


def behaviour_cvae(
    source: Transitions,
    normalizer: StateNormalizer,
    config: BehaviourCVAEConfig,
    *,
    cache_dir: Path,
    seed: int,
    device: torch.device,
    progress=None,
) -> tuple[CVAE, dict[str, Any]]:
    """A CVAE a | s (s z-scored) trained on the source, or loaded from
    `cache_dir/behaviour_cvae-<config hash[:12]>-seed<seed>.pt`; returns the model and its
    training record."""
    weights = cache_dir / f"behaviour_cvae-{config.hash()[:12]}-seed{seed}.pt"
    record_path = weights.with_suffix(".json")
    with training.seeded_init(derive_seed(seed, "init:behaviour_cvae")):
        model = CVAE(
            source.act_dim,
            source.obs_dim,
            latent_dim=config.latent_per_action_dim * source.act_dim,
            hidden=config.hidden,
            kl_weight=config.kl_weight,
            latent_clip=config.latent_clip,
            squash=True,
        )
    # the source's action range bounds the decoder, as for the inverse action model
    model.set_output_bounds(
        torch.from_numpy(source.actions.min(0)), torch.from_numpy(source.actions.max(0))
    )
    model.to(device)
    if weights.exists() and record_path.exists():
        model.load_state_dict(training.load_tensors(weights, "a behaviour CVAE weights file"))
        record = {**json.loads(record_path.read_text()), "cached": True}
    else:
        # minutes of training before any baseline row: say so, and that it happens once
        console.err.print(
            console.plain(
                f"training the baseline's behaviour CVAE (a | s, {config.steps:,} steps); "
                f"cached in {weights.parent} for later runs"
            )
        )
        tensors = {
            "s": torch.from_numpy(normalizer.normalize(source.observations).astype(np.float32)),
            "a": torch.from_numpy(np.ascontiguousarray(source.actions, dtype=np.float32)),
        }
        data = training.TensorData(
            {k: v.to(device) for k, v in tensors.items()},
            config.heldout_fraction,
            config.heldout_eval_rows,
            seed,
        )

        def heldout(batch):
            generator = torch.Generator(device=batch["s"].device).manual_seed(0)
            return model.loss(batch["a"], batch["s"], generator)[0]

        result = training.fit(
            "behaviour_cvae",
            model,
            lambda batch, generator: model.loss(batch["a"], batch["s"], generator),
            heldout,
            data,
            steps=config.steps,
            batch_size=config.batch_size,
            lr=config.lr,
            weight_decay=0.0,
            seed=seed,
            precision="fp32",
            eval_every=config.eval_every,
            checkpoint_every=config.checkpoint_every,
            checkpoint_path=weights.with_suffix(".ckpt.pt"),
            keep_best="model",
            progress=progress,
        )
        save_torch_atomic(weights, model.state_dict())
        record = {**result.to_dict(), "config": asdict(config)}
        write_json_atomic(record_path, record)
        weights.with_suffix(".ckpt.pt").unlink(missing_ok=True)
    model.eval().requires_grad_(False)
    return model, {**record, "weights": str(weights.name)}


@dataclass(frozen=True)
class RolloutConfig:
    """How plain model rollouts are drawn (the models' own settings live elsewhere)."""

    eta: float = 0.2  # synthetic rate: round(eta * N) rollouts are kept
    batch_size: int = 2048  # source states per batch
    dynamics_mean: bool = False  # the ensemble mean instead of a random member's sample

    def __post_init__(self) -> None:
        if not 0 < self.eta <= MAX_ETA:
            raise SettingError(
                f"rollout setting 'eta': expected a synthetic rate in (0, {MAX_ETA:g}], "
                f"found {self.eta!r}"
            )
        if not 1 <= self.batch_size <= 1 << 20:
            raise SettingError(
                "rollout setting 'batch_size': expected an integer in [1, 1048576], "
                f"found {self.batch_size!r}"
            )


def rollout_step(
    generators: Generators,
    policy: CVAE,
    states_norm: torch.Tensor,
    sampling: torch.Generator,
    use_mean: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One model step from z-scored states: (raw actions, z-scored next states, raw rewards)."""
    actions = policy.sample(states_norm, 1, generator=sampling)[:, 0]
    next_norm, rewards = generators.dynamics.sample(
        states_norm, actions, generator=sampling, use_mean=use_mean
    )
    return actions, next_norm, rewards


def model_rollouts(
    generators: Generators,
    policy: CVAE,
    source: Transitions,
    config: RolloutConfig,
    *,
    env_id: str | None,
    seed: int = 0,
    show_progress: bool = True,
) -> GenerationResult:
    """Exactly round(eta * N) finite one-step rollouts from source states drawn in a seeded order.

    Diagnostics match HIPODE's artifact: `dynamics_error` is the distance (z-scored) from the
    written next state to an independent draw of the same ensemble (HIPODE's check, applied to a
    proposal that came from the ensemble itself), `value` the value net's V(s'), `source_index`
    the row the state came from. Same models, source, config and seed give identical arrays.
    """
    device = generators.device
    normalizer = generators.normalizer
    terminal = termination_rule(env_id, source.obs_dim, origin=f"source (env {env_id})")
    target = synthetic_rows(config.eta, len(source))
    source_norm = normalizer.normalize(torch.as_tensor(source.observations, device=device))
    order = SourceOrder(len(source), seed)
    sampling = torch.Generator(device=device).manual_seed(derive_seed(seed, "rollouts"))
    batch_size = min(config.batch_size, len(source))
    parts: list[dict[str, torch.Tensor]] = []
    counts = dict.fromkeys(
        (
            "source_states_drawn",
            "next_states_sampled",
            "nonfinite_next_states",
            "nonfinite_dropped",
        ),
        0,
    )
    collected, batch_index, empty_batches = 0, 0, 0
    started = time.perf_counter()
    with console.progress(disable=not show_progress) as prog, torch.no_grad():
        bar = prog.add_task("model rollouts", total=target, rate="", info="")
        while collected < target:
            indices = torch.as_tensor(order.take(batch_size), device=device)
            states = source_norm[indices]
            actions, next_norm, rewards = rollout_step(
                generators, policy, states, sampling, config.dynamics_mean
            )
            check_next, check_rewards = generators.dynamics.sample(
                states, actions, generator=sampling, use_mean=config.dynamics_mean
            )
            errors = torch.linalg.vector_norm(check_next - next_norm, dim=1)
            values = generators.value(next_norm)
            finite = (
                torch.isfinite(actions).all(1)
                & torch.isfinite(next_norm).all(1)
                & torch.isfinite(rewards)
                & torch.isfinite(errors)
                & torch.isfinite(values)
            )
            rows = torch.nonzero(finite).squeeze(1)[: target - collected]
            counts["source_states_drawn"] += batch_size
            counts["next_states_sampled"] += batch_size
            counts["nonfinite_next_states"] += int((~torch.isfinite(next_norm).all(1)).sum())
            counts["nonfinite_dropped"] += batch_size - int(finite.sum())
            empty_batches = empty_batches + 1 if rows.numel() == 0 else 0
            if empty_batches >= 10:
                raise RuntimeError("ten rollout batches in a row produced only non-finite rows")
            part = {
                "next_norm": next_norm[rows],
                "actions": actions[rows],
                "rewards": rewards[rows],
                "errors": errors[rows],
                "value": values[rows],
                "dynamics_reward": check_rewards[rows],
                "source_index": indices[rows],
                "batch_index": torch.full((rows.numel(),), batch_index, dtype=torch.int64),
            }
            parts.append({name: value.cpu() for name, value in part.items()})
            collected += rows.numel()
            batch_index += 1
            elapsed = time.perf_counter() - started
            prog.update(
                bar,
                completed=collected,
                rate=console.rate_text(counts["source_states_drawn"], elapsed, "states"),
                info=f"kept {collected:,}/{target:,}",
            )
    kept = {name: torch.cat([p[name] for p in parts]) for name in parts[0]}
    counts["candidates"] = counts["source_states_drawn"] - counts["nonfinite_dropped"]
    counts["kept"] = target
    return kept_result(
        kept,
        source,
        normalizer,
        terminal,
        counts,
        float_names=("value", "dynamics_reward"),
        int_names=("batch_index",),
    )
