"""The training loop all five generators share: minibatches gathered by vectorized indices from
tensors preallocated on the device, a held-out split, best-weights keeping (whole model or per
ensemble member), rich progress, and resumable checkpoints written atomically."""

from __future__ import annotations

import contextlib
import copy
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from rich.progress import Progress, TaskID
from torch import Tensor, nn

from hipode_pipeline.console import rate_text
from hipode_pipeline.errors import TrainingDivergedError
from hipode_pipeline.files import load_torch, save_torch_atomic
from hipode_pipeline.seeding import derive_seed

KEEP_BEST_MODES = ("none", "model", "member")
PRECISIONS = ("fp32", "bf16")
LR_SCHEDULES = ("constant", "cosine")  # cosine: lr * (1 + cos(pi * step / steps)) / 2

Batch = dict[str, Tensor]
# (batch, generator) -> (loss to minimize, loss to report)
LossFn = Callable[[Batch, torch.Generator], tuple[Tensor, Tensor]]
# held-out batch -> loss, a scalar or one value per ensemble member
HeldoutFn = Callable[[Batch], Tensor]


@dataclass(frozen=True)
class TrainingRecord:
    """What one model's training did; saved as JSON beside its weights."""

    steps: int  # gradient steps taken in total (across resumes)
    seconds: float  # wall time spent training, summed across resumes
    initial_heldout_loss: float  # before the first step (mean over members)
    best_heldout_loss: float  # lowest seen at an evaluation (mean of per-member bests)
    final_heldout_loss: float  # after the last step, before best weights are restored
    cached: bool = False  # True when loaded from a finished weights file instead of trained
    budget_steps: int = 0  # the step budget asked for (steps < budget_steps: stopped early)
    stopped_on_plateau: bool = False  # the held-out loss stopped improving before the budget
    # per ensemble member: lowest held-out loss seen (what elites are chosen by); None otherwise
    member_best_heldout_losses: list[float] | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@contextlib.contextmanager
def seeded_init(seed: int) -> Iterator[None]:
    """Build modules under a fixed global torch seed without disturbing the caller's RNG."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


def autocast(device: torch.device, precision: str):
    """bf16 autocast for matmuls when asked; losses are still reduced in fp32."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision '{precision}': expected one of {PRECISIONS}")
    return torch.autocast(
        device_type=device.type, dtype=torch.bfloat16, enabled=precision == "bf16"
    )


def load_tensors(path: Path, what: str) -> Any:
    return load_torch(path, f"{what}; delete it to retrain")


def heldout_count(rows: int, heldout_fraction: float) -> int:
    """Rows of a `rows`-row dataset put aside as held-out (at least one, never all)."""
    return min(max(1, round(rows * heldout_fraction)), rows - 1)


def split_rows(rows: int, heldout_fraction: float, seed: int) -> tuple[Tensor, Tensor]:
    """(train rows, held-out rows) of a `rows`-row dataset for training seed `seed`: the one
    split every model of that seed trains with, and what diagnostics call held out."""
    order = torch.randperm(
        rows, generator=torch.Generator().manual_seed(derive_seed(seed, "split"))
    )
    n_heldout = heldout_count(rows, heldout_fraction)
    return order[n_heldout:], order[:n_heldout]


class TensorData:
    """Transition tensors preallocated on one device, split once into train and held-out rows."""

    def __init__(self, tensors: Batch, heldout_fraction: float, heldout_eval_rows: int, seed: int):
        self.tensors = tensors
        n = next(iter(tensors.values())).shape[0]
        device = next(iter(tensors.values())).device
        train_rows, heldout_rows = split_rows(n, heldout_fraction, seed)
        self.heldout_rows = heldout_rows.to(device)
        self.train_rows = train_rows.to(device)
        self._heldout = {k: t[self.heldout_rows[:heldout_eval_rows]] for k, t in tensors.items()}

    def sample(self, batch_size: int, generator: torch.Generator) -> Batch:
        picks = torch.randint(
            len(self.train_rows), (batch_size,), generator=generator, device=generator.device
        )
        rows = self.train_rows[picks.to(self.train_rows.device)]
        return {k: t[rows] for k, t in self.tensors.items()}

    def heldout(self) -> Batch:
        return self._heldout


def checkpoint_written(name: str, step: int) -> None:
    """Called after each resumable checkpoint; tests replace it to simulate an interruption."""


@dataclass
class _BestWeights:
    """Best-so-far weights: the whole model, or per ensemble member along dim 0."""

    mode: str
    loss: Tensor  # (E,) or (1,)
    state: dict[str, Tensor] | None

    def update(self, model: nn.Module, loss: Tensor) -> None:
        improved = loss < self.loss
        if self.mode != "none" and bool(improved.any()):
            current = model.state_dict()
            if self.mode == "model":
                self.state = copy.deepcopy(current)
            else:
                for key, value in current.items():
                    # tensors without a member axis (scales, bounds) do not change in training
                    if value.dim() >= 1 and value.shape[0] == loss.shape[0]:
                        rows = improved.to(value.device)
                        self.state[key][rows] = value[rows]
        self.loss = torch.minimum(self.loss, loss)


def fit(
    name: str,
    model: nn.Module,
    loss_fn: LossFn,
    heldout_fn: HeldoutFn,
    data: TensorData,
    *,
    steps: int,
    batch_size: int,
    lr: float,
    weight_decay: float,
    seed: int,
    precision: str,
    eval_every: int,
    checkpoint_every: int,
    checkpoint_path: Path,
    keep_best: str,
    plateau_patience: int = 0,
    plateau_tolerance: float = 0.0,
    lr_schedule: str = "constant",
    after_step: Callable[[int], None] | None = None,
    progress: Progress | None = None,
) -> TrainingRecord:
    """Train `model` for `steps` Adam steps on minibatches of `data`, resuming from
    `checkpoint_path` when it exists; returns the record and leaves the kept weights loaded.

    With `plateau_patience` > 0 (and best weights kept), training stops once that many
    held-out evaluations in a row failed to lower the best held-out loss (mean over members) by
    more than `plateau_tolerance` of it.
    """
    if keep_best not in KEEP_BEST_MODES:
        raise ValueError(f"keep_best '{keep_best}': expected one of {KEEP_BEST_MODES}")
    if lr_schedule not in LR_SCHEDULES:
        raise ValueError(f"lr_schedule '{lr_schedule}': expected one of {LR_SCHEDULES}")
    if plateau_patience and keep_best == "none":
        raise ValueError("plateau stopping needs kept best weights (keep_best 'model'/'member')")
    device = next(model.parameters()).device
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=lr, weight_decay=weight_decay, fused=True)
    generator = torch.Generator(device=device).manual_seed(derive_seed(seed, name))

    def heldout_loss() -> Tensor:
        model.eval()
        with torch.no_grad():
            loss = heldout_fn(data.heldout()).float().reshape(-1).cpu()
        model.train()
        return loss

    model.train()
    if checkpoint_path.exists():
        state = load_tensors(checkpoint_path, "a training checkpoint")
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        generator.set_state(state["rng"])
        step, seconds = int(state["step"]), float(state["seconds"])
        initial, last = state["initial_loss"], state["last_loss"]
        best = _BestWeights(keep_best, state["best_loss"], state["best_state"])
        stale, plateau_best = int(state["stale_evals"]), float(state["plateau_best"])
    else:
        step, seconds = 0, 0.0
        initial = last = heldout_loss()
        kept = copy.deepcopy(model.state_dict()) if keep_best != "none" else None
        best = _BestWeights(keep_best, initial.clone(), kept)
        # evaluations since the monitored best last improved by more than the tolerance
        stale, plateau_best = 0, float(initial.mean())

    def save_checkpoint() -> None:
        save_torch_atomic(
            checkpoint_path,
            {
                "model": model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "rng": generator.get_state(),
                "step": step,
                "seconds": seconds + time.perf_counter() - started,
                "initial_loss": initial,
                "last_loss": last,
                "best_loss": best.loss,
                "best_state": best.state,
                "stale_evals": stale,
                "plateau_best": plateau_best,
            },
        )
        checkpoint_written(name, step)

    task: TaskID | None = None
    if progress is not None:
        task = progress.add_task(
            name, total=steps, completed=step, rate="", info=_info(initial, last, best)
        )
    started, start_step = time.perf_counter(), step
    refresh_every = max(1, min(50, eval_every))
    stopped = False
    while step < steps and not stopped:
        if lr_schedule == "cosine":
            # a function of the step alone, so a resumed run follows the same schedule
            for group in optimizer.param_groups:
                group["lr"] = lr * (1 + math.cos(math.pi * step / steps)) / 2
        batch = data.sample(batch_size, generator)
        with autocast(device, precision):
            loss, _ = loss_fn(batch, generator)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        step += 1
        if after_step is not None:
            after_step(step)
        if step % eval_every == 0 or step == steps:
            last = heldout_loss()
            best.update(model, last)
            monitored = float(best.loss.mean())
            if monitored < plateau_best - plateau_tolerance * abs(plateau_best):
                stale, plateau_best = 0, monitored
            else:
                stale += 1
            stopped = bool(plateau_patience) and stale >= plateau_patience and step < steps
        if step % checkpoint_every == 0 and step < steps and not stopped:
            save_checkpoint()
        if task is not None and (step % refresh_every == 0 or step == steps or stopped):
            elapsed = time.perf_counter() - started
            progress.update(
                task,
                completed=step,
                rate=rate_text(step - start_step, elapsed),
                info=_info(initial, last, best),
            )
    seconds += time.perf_counter() - started
    if best.state is not None:
        model.load_state_dict(best.state)
    state = model.state_dict().values()
    if not all(bool(torch.isfinite(t).all()) for t in state if t.is_floating_point()):
        # nothing non-finite may reach the cache, where every later run would reuse it
        checkpoint_path.unlink(missing_ok=True)
        raise TrainingDivergedError(
            f"generator '{name}': expected finite weights after {step} steps, found NaN/inf "
            f"(held-out loss {float(last.mean()):.4g}); nothing was cached. Lower the "
            "penalty weight or the learning rate, or check the source for extreme values"
        )
    return TrainingRecord(
        steps=step,
        seconds=round(seconds, 3),
        initial_heldout_loss=float(initial.mean()),
        best_heldout_loss=float(best.loss.mean()),
        final_heldout_loss=float(last.mean()),
        budget_steps=steps,
        stopped_on_plateau=stopped,
        member_best_heldout_losses=[float(x) for x in best.loss] if keep_best == "member" else None,
    )


def _info(initial: Tensor, last: Tensor, best: _BestWeights) -> str:
    text = f"held-out {float(last.mean()):.4g} (start {float(initial.mean()):.4g}"
    if best.mode != "none":
        text += f", best {float(best.loss.mean()):.4g}"
    return text + ")"
