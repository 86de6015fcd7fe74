"""HIPODE's generation, Algorithm 1 lines 4-11: pure computation on arrays, no file I/O.

For batches of source states: n candidate next states from the state-transition model, the one
with the highest value, an action and a reward from the inverse models, a dynamics-model check,
and the lambda fraction with the smallest dynamics error kept, until exactly round(eta * N)
transitions survived. Everything runs batched on z-scored states; the output holds raw values.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from hipode_pipeline import console
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.envs import termination_rule
from hipode_pipeline.errors import SettingError
from hipode_pipeline.models.generators import Generators
from hipode_pipeline.seeding import derive_seed

SELECTIONS = ("batch", "global")
CANDIDATE_SOURCES = ("model", "uniform")
# more synthetic rows than this many times the source, or candidates per state, is a typo
MAX_ETA = 10.0
MAX_CANDIDATES = 1000
COUNTED = ("source_states_drawn", "next_states_sampled", "nonfinite_dropped", "kept")


@dataclass(frozen=True)
class GenerationConfig:
    """How synthetic transitions are drawn and selected (the generators' own settings live in
    GeneratorConfig)."""

    eta: float = 0.2  # synthetic rate: round(eta * N) transitions are kept
    lam: float = 0.2  # selecting rate: fraction of candidates kept by dynamics consistency
    n: int = 10  # candidate next states per source state
    batch_size: int = 2048  # source states per generation batch: the unit of top-lambda selection
    # "batch": top-lambda per generation batch (as CABI); "global": over all candidates
    selection: str = "batch"
    # "model": state-transition CVAE; "uniform": the source's bounding box (Table 12)
    candidates: str = "model"
    # check against the ensemble mean instead of a random member's sample
    dynamics_mean: bool = False
    # rank by the distance to the ensemble's mean prediction in its own predicted stds (the
    # members' mean variance plus their disagreement), not in z-scored state units
    uncertainty_check: bool = False
    # write the ensemble's mean next state for (s, a~) instead of the state model's proposal
    # s~' (which still picks a~ and is what the check ranks); an ablation, not the paper's
    project_next_state: bool = False

    def __post_init__(self) -> None:
        checks = {
            "eta": (0 < self.eta <= MAX_ETA, f"a synthetic rate in (0, {MAX_ETA:g}]"),
            "lam": (0 < self.lam <= 1, "a fraction in (0, 1]"),
            "n": (1 <= self.n <= MAX_CANDIDATES, f"an integer in [1, {MAX_CANDIDATES}]"),
            "batch_size": (1 <= self.batch_size <= 1 << 20, "an integer in [1, 1048576]"),
            "selection": (self.selection in SELECTIONS, f"one of {SELECTIONS}"),
            "candidates": (self.candidates in CANDIDATE_SOURCES, f"one of {CANDIDATE_SOURCES}"),
        }
        for name, (ok, expected) in checks.items():
            if not ok:
                raise SettingError(
                    f"generation setting '{name}': expected {expected}, "
                    f"found {getattr(self, name)!r}"
                )


@dataclass(frozen=True, eq=False)
class GenerationResult:
    """The kept synthetic transitions (raw values), their diagnostics and what it took."""

    transitions: Transitions  # round(eta * N) synthetic transitions
    diagnostics: dict[str, np.ndarray]  # per-transition (M,) arrays, float32 or int64
    counts: dict[str, int]  # source states drawn, next states sampled, non-finite dropped, kept
    next_states_normalized: np.ndarray  # (M, ds) the kept s~' in z-scored units (for novelty)


def synthetic_count(eta: float, n_source: int) -> int:
    """round(eta * N) with halves rounded up (Python's round() would round them to even)."""
    return int(math.floor(eta * n_source + 0.5))


def synthetic_rows(eta: float, n_source: int) -> int:
    """round(eta * N), refused before any work when it keeps nothing."""
    target = synthetic_count(eta, n_source)
    if target < 1:
        raise SettingError(
            f"--eta {eta}: keeps no transition of the source's {n_source}; "
            f"expected eta >= {0.5 / n_source:.2g}"
        )
    return target


class SourceOrder:
    """The seeded order in which source states are drawn: a fresh permutation per pass, so no
    state repeats within a pass, and passes follow each other as long as generation needs."""

    def __init__(self, n_source: int, seed: int):
        self.n_source = n_source
        self._generator = torch.Generator().manual_seed(derive_seed(seed, "source-order"))
        self._pending = np.empty(0, dtype=np.int64)

    def take(self, count: int) -> np.ndarray:
        """The next `count` source indices (int64)."""
        while self._pending.size < count:
            permutation = torch.randperm(self.n_source, generator=self._generator).numpy()
            self._pending = np.concatenate([self._pending, permutation])
        taken, self._pending = self._pending[:count], self._pending[count:]
        return taken


def keep_count(finite: int, lam: float) -> int:
    """How many of a batch's finite candidates the lambda fraction keeps (at least one)."""
    return min(finite, max(1, math.floor(lam * finite + 0.5))) if finite > 0 else 0


def select_top_lambda(errors: torch.Tensor, keep: int) -> torch.Tensor:
    """Indices of the `keep` smallest errors, smallest first; ties go to the earlier row."""
    return torch.sort(errors, stable=True).indices[:keep]


def _evaluate_batch(
    generators: Generators,
    states_norm: torch.Tensor,
    config: GenerationConfig,
    sampling: torch.Generator,
    box: tuple[torch.Tensor, torch.Tensor] | None,
) -> dict[str, torch.Tensor]:
    """Algorithm 1 lines 6-9 for one batch of source states; rows whose candidate is not finite
    anywhere are marked in `finite` (their values are placeholders)."""
    rows, ds = states_norm.shape
    if box is None:
        candidates = generators.state_transition.sample(states_norm, config.n, generator=sampling)
    else:
        low, high = box
        uniform = torch.rand((rows, config.n, ds), generator=sampling, device=states_norm.device)
        candidates = low + (high - low) * uniform
    values = generators.value(candidates)
    candidate_finite = torch.isfinite(candidates).all(-1) & torch.isfinite(values)
    # a non-finite candidate can never win the argmax; a row with none finite is dropped below
    best = torch.where(candidate_finite, values, -torch.inf).argmax(dim=1)
    arange = torch.arange(rows, device=states_norm.device)
    has_finite = candidate_finite[arange, best]
    next_norm = torch.where(has_finite[:, None], candidates[arange, best], 0.0)
    cond = torch.cat([states_norm, next_norm], dim=1)
    actions = generators.inverse_action.sample(cond, 1, generator=sampling)[:, 0]
    rewards = generators.inverse_reward.sample(cond, 1, generator=sampling)[:, 0, 0]
    if config.uncertainty_check or config.project_next_state:
        mean, variance = generators.dynamics.predictive(states_norm, actions)
    if config.uncertainty_check:
        dyna_next, dyna_rewards = states_norm + mean[:, :-1], mean[:, -1]
        errors = ((dyna_next - next_norm).pow(2) / variance[:, :-1]).mean(1).sqrt()
    else:
        dyna_next, dyna_rewards = generators.dynamics.sample(
            states_norm, actions, generator=sampling, use_mean=config.dynamics_mean
        )
        errors = torch.linalg.vector_norm(dyna_next - next_norm, dim=1)
    if config.project_next_state:
        next_norm = torch.where(has_finite[:, None], states_norm + mean[:, :-1], 0.0)
    finite = (
        has_finite
        & torch.isfinite(actions).all(1)
        & torch.isfinite(rewards)
        & torch.isfinite(errors)
        & torch.isfinite(dyna_rewards)
    )
    return {
        "next_norm": next_norm,
        "value": values[arange, best],
        "candidate_index": best,
        "actions": actions,
        "rewards": rewards,
        "dynamics_reward": dyna_rewards,
        "errors": errors,
        "finite": finite,
        "nonfinite_next_states": (~candidate_finite).sum(),
    }


def generate(
    generators: Generators,
    source: Transitions,
    config: GenerationConfig,
    *,
    env_id: str | None,
    seed: int = 0,
    show_progress: bool = True,
) -> GenerationResult:
    """Draw, rank and keep exactly round(eta * N) synthetic transitions from `source`.

    `env_id` picks the termination rule applied to each kept s~' (raw). Same generators, source,
    config and seed give identical arrays on the same device.
    """
    device = generators.device
    normalizer = generators.normalizer
    # fail before any work when the env has no known rule or the layout does not match it
    terminal = termination_rule(env_id, source.obs_dim, origin=f"source (env {env_id})")
    target = synthetic_rows(config.eta, len(source))
    source_norm = normalizer.normalize(torch.as_tensor(source.observations, device=device))
    box = (
        (source_norm.min(0).values, source_norm.max(0).values)
        if config.candidates == "uniform"
        else None
    )
    order = SourceOrder(len(source), seed)
    sampling = torch.Generator(device=device).manual_seed(derive_seed(seed, "sampling"))
    batch_size = min(config.batch_size, len(source))
    # global selection needs a pool of target / lam finite candidates before it ranks them
    pool_target = math.ceil(target / config.lam - 1e-9) if config.selection == "global" else target
    parts: list[dict[str, torch.Tensor]] = []
    counts = {
        "source_states_drawn": 0,
        "next_states_sampled": 0,
        "nonfinite_next_states": 0,
        "nonfinite_dropped": 0,
    }
    collected, batch_index, empty_batches = 0, 0, 0
    started = time.perf_counter()
    with console.progress(disable=not show_progress) as prog, torch.no_grad():
        bar = prog.add_task("generate", total=pool_target, rate="", info="")
        while collected < pool_target:
            indices = order.take(batch_size)
            batch = _evaluate_batch(
                generators,
                source_norm[torch.as_tensor(indices, device=device)],
                config,
                sampling,
                box,
            )
            finite_rows = torch.nonzero(batch["finite"]).squeeze(1)
            counts["source_states_drawn"] += batch_size
            counts["next_states_sampled"] += batch_size * config.n
            counts["nonfinite_next_states"] += int(batch["nonfinite_next_states"])
            counts["nonfinite_dropped"] += batch_size - finite_rows.numel()
            empty_batches = empty_batches + 1 if finite_rows.numel() == 0 else 0
            if empty_batches >= 10:
                raise RuntimeError(
                    "ten generation batches in a row produced only non-finite candidates"
                )
            if config.selection == "global":
                chosen = finite_rows
            else:
                # the last batch is drawn at full size and keeps only the r smallest errors it
                # still needs: those are a subset of its own top-lambda, so selection is unchanged
                keep = min(keep_count(finite_rows.numel(), config.lam), target - collected)
                chosen = finite_rows[select_top_lambda(batch["errors"][finite_rows], keep)]
            part = {
                name: value[chosen]
                for name, value in batch.items()
                if name not in ("finite", "nonfinite_next_states")
            }
            part["source_index"] = torch.as_tensor(indices, device=device)[chosen]
            part["batch_index"] = torch.full(
                (chosen.numel(),), batch_index, dtype=torch.int64, device=device
            )
            part["error_rank"] = torch.arange(chosen.numel(), device=device)
            parts.append({name: value.cpu() for name, value in part.items()})
            collected += chosen.numel()
            batch_index += 1
            elapsed = time.perf_counter() - started
            median_error = float(batch["errors"][chosen].median()) if chosen.numel() else math.nan
            prog.update(
                bar,
                completed=min(collected, pool_target),
                rate=console.rate_text(counts["source_states_drawn"], elapsed, "candidates"),
                info=f"kept {min(collected, target):,}/{target:,}  median e {median_error:.3f}",
            )
    kept = {name: torch.cat([p[name] for p in parts]) for name in parts[0]}
    if config.selection == "global":
        ranked = select_top_lambda(kept["errors"], target)
        kept = {name: value[ranked] for name, value in kept.items()}
        kept["error_rank"] = torch.arange(target)
    counts["candidates"] = counts["source_states_drawn"] - counts["nonfinite_dropped"]
    counts["kept"] = target
    return _as_result(kept, source, normalizer, terminal, counts)


def _as_result(kept, source: Transitions, normalizer, terminal, counts) -> GenerationResult:
    return kept_result(
        kept,
        source,
        normalizer,
        terminal,
        counts,
        float_names=("value", "dynamics_reward"),
        int_names=("candidate_index", "batch_index", "error_rank"),
    )


def kept_result(
    kept: dict[str, torch.Tensor],
    source: Transitions,
    normalizer,
    terminal,
    counts: dict[str, int],
    *,
    float_names: tuple[str, ...],
    int_names: tuple[str, ...],
) -> GenerationResult:
    """Kept rows (z-scored next states, raw actions and rewards, their check's `errors` and the
    source rows they came from) as raw transitions with the env's terminals and diagnostics
    (`float_names` as float32, `int_names` as int64)."""
    next_norm = kept["next_norm"].numpy().astype(np.float32)
    next_raw = normalizer.denormalize(next_norm).astype(np.float32)
    source_index = kept["source_index"].numpy().astype(np.int64)
    transitions = Transitions(
        observations=source.observations[source_index],
        actions=kept["actions"].numpy().astype(np.float32),
        rewards=kept["rewards"].numpy().astype(np.float32),
        next_observations=next_raw,
        terminals=terminal(next_raw),
        timeouts=np.zeros(len(source_index), dtype=np.bool_),
    )
    diagnostics = {
        "dynamics_error": kept["errors"].numpy().astype(np.float32),
        "source_index": source_index,
        **{name: kept[name].numpy().astype(np.float32) for name in float_names},
        **{name: kept[name].numpy().astype(np.int64) for name in int_names},
    }
    return GenerationResult(transitions, diagnostics, counts, next_norm)


def novelty(
    synthetic_norm: np.ndarray,
    source_norm: torch.Tensor,
    *,
    sample: int = 2000,
    seed: int = 0,
    chunk: int = 16384,
) -> np.ndarray:
    """L2 distance (z-scored units) from each of a seeded sample of synthetic next states to its
    nearest source state, with the source scanned in chunks to bound memory."""
    rng = np.random.default_rng(derive_seed(seed, "novelty"))
    picked = rng.choice(len(synthetic_norm), size=min(sample, len(synthetic_norm)), replace=False)
    queries = torch.as_tensor(synthetic_norm[np.sort(picked)], device=source_norm.device)
    nearest = torch.full((len(queries),), torch.inf, device=source_norm.device)
    with torch.no_grad():
        for start in range(0, len(source_norm), chunk):
            distances = torch.cdist(queries, source_norm[start : start + chunk])
            nearest = torch.minimum(nearest, distances.min(dim=1).values)
    return nearest.cpu().numpy()
