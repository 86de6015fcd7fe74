"""Stage one: HIPODE's generation (Algorithm 1, lines 4-11) and its orchestration.

For batches of source states: n candidate next states from the state-transition model, the one
with the highest value, an action and a reward from the inverse models, a dynamics-model check,
and the lambda fraction with the smallest dynamics error kept, until exactly round(eta * N)
transitions survived. Everything runs batched on z-scored states; the output holds raw values.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import torch

import hipode_pipeline
from hipode_pipeline import console
from hipode_pipeline.artifact import (
    SCHEMA_VERSION,
    default_artifact_path,
    read_artifact,
    write_artifact,
)
from hipode_pipeline.data.load import load_source
from hipode_pipeline.data.transitions import SourceInfo, Transitions
from hipode_pipeline.device import select_device
from hipode_pipeline.envs import termination_rule
from hipode_pipeline.errors import (
    DataFormatError,
    DatasetNotFoundError,
    OverwriteError,
    SettingError,
)
from hipode_pipeline.files import file_sha256, write_json_atomic
from hipode_pipeline.models.generators import GeneratorConfig, Generators, train_generators
from hipode_pipeline.paths import use_datasets_root
from hipode_pipeline.tasks import Task, get_task
from hipode_pipeline.versions import package_versions

SELECTIONS = ("batch", "global")
CANDIDATE_SOURCES = ("model", "uniform")
PROFILES = ("full", "quick")
COUNTED = ("source_states_drawn", "next_states_sampled", "nonfinite_dropped", "kept")


@dataclass(frozen=True)
class GenerationConfig:
    """How synthetic transitions are drawn and selected (the generators' own settings live in
    GeneratorConfig)."""

    eta: float = 0.2  # synthetic rate: round(eta * N) transitions are kept
    lam: float = 0.2  # selecting rate: fraction of candidates kept by dynamics consistency
    n: int = 10  # candidate next states per source state
    batch_size: int = 2048  # source states per generation batch: the unit of top-lambda selection
    selection: str = (
        "batch"  # "batch": top-lambda per generation batch (as CABI); "global": over all
    )
    candidates: str = (
        "model"  # "model": state-transition CVAE; "uniform": source bounding box (Table 12)
    )
    dynamics_mean: bool = (
        False  # check against the ensemble mean instead of a random member's sample
    )

    def __post_init__(self) -> None:
        checks = {
            "eta": (self.eta > 0, "a positive rate"),
            "lam": (0 < self.lam <= 1, "a fraction in (0, 1]"),
            "n": (self.n >= 1, "a positive integer"),
            "batch_size": (self.batch_size >= 1, "a positive integer"),
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


def derive_seed(seed: int, stream: str) -> int:
    """An independent 63-bit seed per named random stream of one run."""
    return int.from_bytes(hashlib.sha256(f"{seed}:{stream}".encode()).digest()[:8], "little") >> 1


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
    dyna_next, dyna_rewards = generators.dynamics.sample(
        states_norm, actions, generator=sampling, use_mean=config.dynamics_mean
    )
    errors = torch.linalg.vector_norm(dyna_next - next_norm, dim=1)
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
    target = synthetic_count(config.eta, len(source))
    if target < 1:
        raise SettingError(
            f"--eta {config.eta}: keeps no transition of the source's {len(source)}; "
            f"expected eta >= {0.5 / len(source):.2g}"
        )
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
        "value": kept["value"].numpy().astype(np.float32),
        "source_index": source_index,
        "candidate_index": kept["candidate_index"].numpy().astype(np.int64),
        "dynamics_reward": kept["dynamics_reward"].numpy().astype(np.float32),
        "batch_index": kept["batch_index"].numpy().astype(np.int64),
        "error_rank": kept["error_rank"].numpy().astype(np.int64),
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


@dataclass
class AugmentSummary:
    """What stage one did: counts, quality of the synthetic data, time per phase, the file."""

    task: str  # task short name
    source_id: str  # source dataset id or path
    source_sha256: str  # content hash of the source transitions
    n_source: int  # N, source transitions
    eta: float  # synthetic rate
    lam: float  # selecting rate
    n: int  # candidates per source state
    source_states_drawn: int  # candidates ranked, one per drawn source state (~ eta*N/lam)
    next_states_sampled: int  # n per drawn source state
    nonfinite_dropped: int  # drawn source states whose candidate was NaN/inf anywhere
    kept: int  # synthetic transitions written: round(eta * N)
    terminals: int  # kept transitions the env's termination rule ends
    dynamics_error_mean: float  # ||s~'_dyna - s~'|| of the kept, z-scored units
    dynamics_error_median: float
    novelty_mean: float  # L2 from kept s~' to the nearest source state, z-scored, on a sample
    novelty_median: float
    novelty_sample: int  # how many kept next states the novelty was measured on
    seconds: dict[str, float]  # wall time per phase: load, train, generate, write, total
    generators_cached: bool  # every generator came from the cache
    artifact: str  # path of the synthetic file
    artifact_sha256: str  # sha256 of the file's bytes (differs per run: the manifest has a time)
    content_checksum: str  # the manifest's checksum of the arrays (equal for equal requests)
    device: str  # torch device used
    profile: str  # generator profile
    reused_artifact: bool = False  # the file already matched this request and was kept as is

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def rows(self) -> list[list[Any]]:
        """(quantity, value) rows for the summary table."""
        seconds = ", ".join(f"{name} {value:.1f}s" for name, value in self.seconds.items())
        return [
            ["task", self.task],
            ["source", f"{self.source_id} (sha256 {self.source_sha256[:16]})"],
            ["N (source transitions)", self.n_source],
            ["eta / lambda / n", f"{self.eta} / {self.lam} / {self.n}"],
            ["candidates drawn", self.source_states_drawn],
            ["next states sampled", self.next_states_sampled],
            ["non-finite dropped", self.nonfinite_dropped],
            ["kept", self.kept],
            ["terminals among kept", self.terminals],
            [
                "dynamics error mean / median",
                f"{self.dynamics_error_mean:.4f} / {self.dynamics_error_median:.4f}",
            ],
            [
                f"novelty mean / median (n={self.novelty_sample})",
                f"{self.novelty_mean:.4f} / {self.novelty_median:.4f}",
            ],
            ["time", seconds],
            ["generators", "cached" if self.generators_cached else "trained"],
            ["device / profile", f"{self.device} / {self.profile}"],
            ["artifact", self.artifact + (" (up to date, kept)" if self.reused_artifact else "")],
            ["artifact sha256", self.artifact_sha256],
            ["content checksum", self.content_checksum],
        ]


@dataclass(frozen=True)
class _Request:
    """Everything that determines an artifact's arrays; equal requests give equal arrays."""

    task: str
    source_sha256: str
    generation: dict[str, Any]
    generator_config: dict[str, Any]
    seed: int
    schema_version: str = SCHEMA_VERSION
    code_version: str = field(default=hipode_pipeline.__version__)

    def key(self) -> str:
        return hashlib.sha256(
            json.dumps(asdict(self), sort_keys=True, default=str).encode()
        ).hexdigest()

    def differences(self, stored: dict[str, Any]) -> list[str]:
        """Names of what differs from a stored request (nested settings by field name)."""
        names = []
        for name, value in asdict(self).items():
            old = stored.get(name)
            if isinstance(value, dict) and isinstance(old, dict):
                names += [
                    f"{name}.{k}"
                    for k in sorted(set(value) | set(old))
                    if value.get(k) != old.get(k)
                ]
            elif value != old:
                names.append(name)
        return names


def run_augment(
    task_name: str,
    *,
    source: str | None = None,
    eta: float | None = None,
    lam: float | None = None,
    n: int | None = None,
    alpha: float | None = None,
    sigma: float | None = None,
    penalty: str | None = None,
    selection: str = "batch",
    candidates: str = "model",
    dynamics_mean: bool = False,
    profile: str = "full",
    seed: int = 0,
    out: Path | None = None,
    root: Path | None = None,
    force: bool = False,
    device: str | None = None,
    show_progress: bool = True,
) -> AugmentSummary:
    """Stage one end to end: load (collecting first if the task's own dataset is missing), train
    or reuse the generators, generate, write the artifact and its summary JSON.

    Unset hyper-parameters take the task's Table 6 (TD3+BC) values. An existing artifact built
    from the same request is verified and kept; any other existing file needs `force`.
    """
    seconds: dict[str, float] = {}
    clock = time.perf_counter()
    task = get_task(task_name)
    root = use_datasets_root(root)
    params = task.augment_params("td3bc")
    generation = GenerationConfig(
        eta=params.eta if eta is None else eta,
        lam=params.lam if lam is None else lam,
        n=params.n if n is None else n,
        selection=selection,
        candidates=candidates,
        dynamics_mean=dynamics_mean,
    )
    overrides = {
        "alpha": params.alpha if alpha is None else alpha,
        "sigma": params.sigma if sigma is None else sigma,
    }
    if penalty is not None:
        overrides["penalty"] = penalty
    generator_config = GeneratorConfig.profile(profile, **overrides)
    torch_device = select_device(device)
    transitions, info = _load_or_collect(task, source, root, show_progress)
    seconds["load"] = time.perf_counter() - clock

    out = (
        Path(out)
        if out is not None
        else default_artifact_path(task.name, learner="td3bc", seed=seed, root=root)
    )
    request = _Request(task.name, info.sha256, asdict(generation), generator_config.to_dict(), seed)
    if out.exists() and not force:
        return _reuse_existing(out, request, seconds)

    clock = time.perf_counter()
    generators = train_generators(
        transitions,
        info.sha256,
        generator_config,
        cache_root=root / "cache" / "generators",
        seed=seed,
        device=torch_device,
        show_progress=show_progress,
    )
    seconds["train"] = time.perf_counter() - clock

    clock = time.perf_counter()
    env_id = info.env_id or task.env_id
    result = generate(
        generators, transitions, generation, env_id=env_id, seed=seed, show_progress=show_progress
    )
    source_norm = generators.normalizer.normalize(
        torch.as_tensor(transitions.observations, device=generators.device)
    )
    distances = novelty(result.next_states_normalized, source_norm, seed=seed)
    seconds["generate"] = time.perf_counter() - clock

    clock = time.perf_counter()
    errors = result.diagnostics["dynamics_error"]
    statistics = {
        "dynamics_error_mean": float(errors.mean()),
        "dynamics_error_median": float(np.median(errors)),
        "novelty_mean": float(distances.mean()),
        "novelty_median": float(np.median(distances)),
        "novelty_sample": int(distances.size),
        "terminals": int(result.transitions.terminals.sum()),
    }
    # the summary's fields that describe the file's content; the manifest keeps them too
    record = {
        "task": task.name,
        "source_id": info.id,
        "source_sha256": info.sha256,
        "n_source": len(transitions),
        "eta": generation.eta,
        "lam": generation.lam,
        "n": generation.n,
        **{key: result.counts[key] for key in COUNTED},
        **statistics,
        "generators_cached": all(
            r.get("cached", False) for r in generators.training_report.values()
        ),
        "device": str(generators.device),
        "profile": profile,
    }
    manifest = _manifest(
        task, info, env_id, generation, generator_config, generators, seed, result, record, request
    )
    stored = write_artifact(out, result.transitions, result.diagnostics, manifest, force=force)
    seconds["write"] = time.perf_counter() - clock
    seconds["total"] = sum(seconds.values())
    summary = AugmentSummary(
        **record,
        seconds={name: round(value, 3) for name, value in seconds.items()},
        artifact=str(out),
        artifact_sha256=file_sha256(out),
        content_checksum=stored["checksum"],
    )
    write_json_atomic(summary_path(out), summary.to_dict())
    return summary


def summary_path(artifact: Path) -> Path:
    """The summary JSON written beside an artifact."""
    return artifact.with_name(artifact.name + ".summary.json")


def _load_or_collect(
    task: Task, source: str | None, root: Path, show_progress: bool
) -> tuple[Transitions, SourceInfo]:
    spec = source or task.name
    try:
        return load_source(spec, root)
    except DatasetNotFoundError:
        own_dataset = source is None or source in (task.name, task.local_dataset_id)
        if not (own_dataset and task.collectable):
            raise
    # collection pulls in policy training; only needed when the task's own source is missing
    from hipode_pipeline.data.collect import collect

    console.err.print(
        f"[yellow]source {task.local_dataset_id} is not under {root}: collecting it first "
        f"(hipode collect {task.name}); this takes a while once[/]"
    )
    collect(task, root=root, show_progress=show_progress)
    return load_source(spec, root)


def _reuse_existing(out: Path, request: _Request, seconds: dict[str, float]) -> AugmentSummary:
    """Keep an existing artifact built from the same request (after verifying it); refuse others."""
    clock = time.perf_counter()
    try:
        artifact = read_artifact(out)
    except DataFormatError as error:
        raise OverwriteError(
            f"{out} exists but is not a valid artifact ({error}); pass --force to replace it"
        ) from None
    if artifact.manifest.get("request_key") != request.key():
        stored_request = artifact.manifest.get("request")
        changed = request.differences(stored_request) if isinstance(stored_request, dict) else []
        raise OverwriteError(
            f"{out} exists and was built with other settings "
            f"({', '.join(changed[:6]) or 'source, hyper-parameters, profile or seed'}); "
            "pass --force to replace it, or --out to write elsewhere"
        )
    stored = artifact.manifest.get("summary", {})
    sha256 = file_sha256(out)
    seconds["verify"] = time.perf_counter() - clock
    seconds["total"] = seconds["load"] + seconds["verify"]
    console.err.print(f"{out} is up to date (same source, settings and seed): kept as is")
    try:
        return AugmentSummary(
            **{
                **stored,
                "seconds": {name: round(value, 3) for name, value in seconds.items()},
                "artifact": str(out),
                "artifact_sha256": sha256,
                "content_checksum": artifact.manifest["checksum"],
                "generators_cached": True,
                "reused_artifact": True,
            }
        )
    except TypeError:
        raise OverwriteError(
            f"{out} has no usable summary in its manifest; pass --force to rebuild it"
        ) from None


def _manifest(
    task: Task,
    info: SourceInfo,
    env_id: str,
    generation: GenerationConfig,
    generator_config: GeneratorConfig,
    generators: Generators,
    seed: int,
    result: GenerationResult,
    summary: dict[str, Any],
    request: _Request,
) -> dict[str, Any]:
    """The provenance stored in the artifact (DESIGN.md's manifest; the writer adds schema and
    checksum)."""
    source_record = {key: value for key, value in info.to_dict().items() if key != "metadata"}
    if isinstance(info.metadata.get("hipode"), dict):
        source_record["recipe"] = info.metadata["hipode"]
    return {
        "task": task.name,
        "env_id": env_id,
        "ref_min_score": info.ref_min_score
        if info.ref_min_score is not None
        else task.ref_min_score,
        "ref_max_score": info.ref_max_score
        if info.ref_max_score is not None
        else task.ref_max_score,
        "source": source_record,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "hyper_parameters": {
            **asdict(generation),
            "alpha": generator_config.alpha,
            "sigma": generator_config.sigma,
            "penalty": generator_config.penalty,
            "profile": summary["profile"],
            "generator_config": generator_config.to_dict(),
            "generator_config_hash": generator_config.hash(),
        },
        "seeds": {
            "seed": seed,
            "generator_training": seed,
            "source_order": derive_seed(seed, "source-order"),
            "sampling": derive_seed(seed, "sampling"),
            "novelty_sample": derive_seed(seed, "novelty"),
        },
        "generators": {
            "device": str(generators.device),
            "checkpoint_hashes": generators.checkpoint_hashes,
            "training_report": generators.training_report,
        },
        "versions": package_versions(),
        "counts": result.counts,
        "summary": summary,
        "request": asdict(request),
        "request_key": request.key(),
    }
