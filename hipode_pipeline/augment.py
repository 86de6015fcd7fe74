"""Stage one's driver: load -> train or reuse the generators -> generate -> write the artifact.

The algorithm itself is `hipode_pipeline.generate` (no file I/O); this module decides what is
asked for (a learner's table row and overrides), whether an existing file already answers it,
and what the manifest records.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hipode_pipeline import console
from hipode_pipeline.artifact import SCHEMA_VERSION, read_artifact, write_artifact
from hipode_pipeline.contract import METHODS, ArtifactSettings, default_artifact_path, table_row
from hipode_pipeline.data.bands import check_source_band
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
from hipode_pipeline.evaluate import check_data_fits_env
from hipode_pipeline.files import check_output_file, file_sha256, output_lock, write_json_atomic
from hipode_pipeline.generate import (
    GenerationConfig,
    GenerationResult,
    generate,
    novelty,
    synthetic_rows,
)
from hipode_pipeline.machine import utc_now
from hipode_pipeline.models.generators import GeneratorConfig, Generators, train_generators
from hipode_pipeline.overrides import check_fields
from hipode_pipeline.paths import use_datasets_root
from hipode_pipeline.rollouts import RolloutConfig, behaviour_config, behaviour_cvae, model_rollouts
from hipode_pipeline.seeding import SEED_MAX, derive_seed
from hipode_pipeline.tasks import LEARNERS, Task, get_task
from hipode_pipeline.threads import stage_one_threads, torch_threads
from hipode_pipeline.versions import ARTIFACT_CODE, ROLLOUT_CODE, code_digest, package_versions

COUNTED = ("source_states_drawn", "next_states_sampled", "nonfinite_dropped", "kept")


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
    # the learner whose table row gave the defaults: {"learner", "table", "from_paper"}
    table_row: dict[str, Any] = field(default_factory=dict)
    reused_artifact: bool = False  # the file already matched this request and was kept as is
    # the source's behaviour policies against their bands (data.bands); None: none recorded
    source_band: dict[str, Any] | None = None
    allowed_off_band: bool = False  # built on an off-band source because --allow-off-band

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
            ["defaults from", _table_text(self.table_row)],
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
class ArtifactRequest:
    """Everything that determines an artifact's arrays: equal requests give equal arrays. The
    learner that asked for it is not part of it (the manifest records its table row apart)."""

    task: str
    source_sha256: str
    generation: dict[str, Any]
    generator_config: dict[str, Any]
    seed: int
    schema_version: str = SCHEMA_VERSION
    code_digest: str = field(default_factory=lambda: code_digest(ARTIFACT_CODE))

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
                names.append(
                    "code (the package's stage-one code changed)" if name == "code_digest" else name
                )
        return names


def run_augment(
    task_name: str,
    *,
    learner: str = "td3bc",
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
    uncertainty_check: bool = False,
    project_next_state: bool = False,
    method: str = "hipode",
    profile: str = "full",
    seed: int = 0,
    out: Path | None = None,
    root: Path | None = None,
    force: bool = False,
    device: str | None = None,
    show_progress: bool = True,
    allow_off_band: bool = False,
    generator_settings: dict[str, Any] | None = None,
) -> AugmentSummary:
    """Stage one end to end: load (collecting first if the task's own dataset is missing), train
    or reuse the generators, generate, write the artifact and its summary JSON.

    Unset hyper-parameters take `learner`'s table row for the task (TD3+BC: Table 6, CQL:
    Table 5, IQL: Table 7). An existing artifact built from the same request is verified and
    kept; any other existing file needs `force`. `method` "model-rollouts" writes the plain
    model-rollout baseline instead (`hipode_pipeline.rollouts`): the same generators and η·N
    rows, one rollout per drawn state and no selection, so λ and n do not apply.
    """
    with contextlib.ExitStack() as held:
        seconds: dict[str, float] = {}
        clock = time.perf_counter()
        task = get_task(task_name)
        if learner not in LEARNERS:
            raise SettingError(
                f"--learner: expected one of {LEARNERS} (a learner with a table row in the paper), "
                f"found {learner!r}"
            )
        params = task.augment_params(learner)
        rollouts = method == "model-rollouts"
        check_method(
            method,
            lam=lam,
            n=n,
            selection=selection,
            candidates=candidates,
            uncertainty_check=uncertainty_check,
            project_next_state=project_next_state,
        )
        generation = GenerationConfig(
            eta=params.eta if eta is None else eta,
            # a rollout is one proposal per state, all kept: what λ = 1, n = 1 mean for HIPODE
            lam=1.0 if rollouts else params.lam if lam is None else lam,
            n=1 if rollouts else params.n if n is None else n,
            selection=selection,
            candidates=candidates,
            dynamics_mean=dynamics_mean,
            uncertainty_check=uncertainty_check,
            project_next_state=project_next_state,
        )
        overrides = {
            "alpha": params.alpha if alpha is None else alpha,
            "sigma": params.sigma if sigma is None else sigma,
        }
        if penalty is not None:
            overrides["penalty"] = penalty
        extra = check_fields(
            GeneratorConfig, dict(generator_settings or {}), "--set/--config (GeneratorConfig)"
        )
        given = {"alpha": alpha, "sigma": sigma, "penalty": penalty}
        twice = sorted(key for key in extra if given.get(key) is not None)
        if twice:
            raise SettingError(f"--set/--config and --{twice[0]}: give {twice[0]} once")
        generator_config = GeneratorConfig.profile(profile, **{**overrides, **extra})
        check_seed(seed)
        stage_one_threads("generate")  # a bad OMP_NUM_THREADS fails here, before any work
        torch_device = select_device(device)
        as_asked = generator_config
        generator_config, emulated = generator_config.on_device(torch_device, asked=extra)
        if emulated:
            console.err.print(
                console.plain(
                    f"bf16 matmuls are emulated on {torch_device} (native on CPUs with "
                    f"AVX512-BF16 or AMX and on GPUs with bf16): {', '.join(emulated)} set to "
                    f"fp32 (--set {emulated[0]}=bf16 insists)"
                ),
                soft_wrap=True,
            )
        root = use_datasets_root(root)
        out_given = out is not None
        if out_given:
            check_output_file(Path(out), "--out")
        transitions, info = _load_or_collect(task, source, root, show_progress, allow_off_band)
        band = check_source_band(info.metadata, str(info.id), allow_off_band=allow_off_band)
        env_id = info.env_id or task.env_id
        # the data must fit the task's env before minutes of training: rule, layout and row count
        termination_rule(env_id, transitions.obs_dim, origin=f"source {info.id} (env {env_id})")
        check_data_fits_env(env_id, transitions.obs_dim, transitions.act_dim, str(info.id))
        synthetic_rows(generation.eta, len(transitions))
        seconds["load"] = time.perf_counter() - clock

        settings = ArtifactSettings(
            eta=generation.eta,
            lam=generation.lam,
            n=generation.n,
            alpha=generator_config.alpha,
            sigma=generator_config.sigma,
            penalty=generator_config.penalty,
            selection=generation.selection,
            candidates=generation.candidates,
            dynamics_mean=generation.dynamics_mean,
            uncertainty_check=generation.uncertainty_check,
            project_next_state=generation.project_next_state,
            profile=profile,
            method=method,
        )
        own_source = source is None or source in (task.name, task.local_dataset_id)
        out = (
            Path(out)
            if out is not None
            else default_artifact_path(
                task,
                settings,
                seed=seed,
                root=root,
                source_tag=None if own_source else info.sha256[:8],
            )
        )
        if not out_given:
            check_output_file(out, "the default artifact path")
        if rollouts:
            rollout_config = RolloutConfig(eta=generation.eta, dynamics_mean=dynamics_mean)
            behaviour = behaviour_config(profile)
            request = ArtifactRequest(
                task.name,
                info.sha256,
                {**asdict(rollout_config), "method": method, "behaviour": asdict(behaviour)},
                generator_config.to_dict(),
                seed,
                code_digest=code_digest(ROLLOUT_CODE),
            )
        else:
            request = ArtifactRequest(
                task.name, info.sha256, asdict(generation), generator_config.to_dict(), seed
            )
        # held to the end: a second augment into `out` waits, then finds it up to date
        held.enter_context(output_lock(out, command="hipode augment"))
        if out.exists() and not force:
            # one built where bf16 is native answers the same command here too
            native = replace(request, generator_config=as_asked.to_dict()) if emulated else None
            return _reuse_existing(out, request, seconds, also=native)

        console.err.print(
            console.plain(
                _plan_line(
                    task,
                    info,
                    len(transitions),
                    generation,
                    generator_config,
                    profile,
                    torch_device,
                )
                + f"; {torch_device}, {stage_one_threads('train')} thread(s) training, "
                f"{stage_one_threads('generate')} generating; -> {out}"
            ),
            soft_wrap=True,
        )
        clock = time.perf_counter()
        # each phase on the threads it was measured to want (collection sets its own)
        with torch_threads(stage_one_threads("train")):
            generators = train_generators(
                transitions,
                info.sha256,
                generator_config,
                cache_root=root / "cache" / "generators",
                seed=seed,
                device=torch_device,
                show_progress=show_progress,
            )
            behaviour_record = None
            if rollouts:
                policy, behaviour_record = behaviour_cvae(
                    transitions,
                    generators.normalizer,
                    behaviour,
                    cache_dir=generators.cache_dir,
                    seed=seed,
                    device=generators.device,
                )
        seconds["train"] = time.perf_counter() - clock

        clock = time.perf_counter()
        with torch_threads(stage_one_threads("generate")):
            if rollouts:
                result = model_rollouts(
                    generators,
                    policy,
                    transitions,
                    rollout_config,
                    env_id=env_id,
                    seed=seed,
                    show_progress=show_progress,
                )
            else:
                result = generate(
                    generators,
                    transitions,
                    generation,
                    env_id=env_id,
                    seed=seed,
                    show_progress=show_progress,
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
                r.get("cached", False)
                for r in [*generators.training_report.values(), *filter(None, [behaviour_record])]
            ),
            "device": str(generators.device),
            "profile": profile,
            "table_row": table_row(task, learner),
            "source_band": band,
            "allowed_off_band": bool(band and band["in_band"] is False),
        }
        manifest = _manifest(
            task,
            info,
            env_id,
            generation,
            generator_config,
            generators,
            seed,
            result,
            record,
            request,
            behaviour_record,
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


# HIPODE's proposal and selection settings, unset: they have no meaning for one rollout per state
HIPODE_ONLY_UNSET = {
    "lam": None,
    "n": None,
    "selection": "batch",
    "candidates": "model",
    "uncertainty_check": False,
    "project_next_state": False,
}


def check_method(method: str, **given: Any) -> None:
    """`method` is known, and the plain rollouts get none of HIPODE's selection settings."""
    if method not in METHODS:
        raise SettingError(f"--method: expected one of {METHODS}, found {method!r}")
    if method == "hipode":
        return
    misplaced = [name for name, value in given.items() if value != HIPODE_ONLY_UNSET[name]]
    if misplaced:
        flags = ", ".join("--" + name.replace("_", "-") for name in misplaced)
        raise SettingError(
            f"--method {method}: {flags} do not apply (one rollout per drawn state, every "
            "finite one kept); leave them out"
        )


def check_seed(seed: int) -> None:
    """Seeds must fit every generator they reach (numpy and torch take 63 bits)."""
    if not 0 <= seed <= SEED_MAX:
        raise SettingError(f"--seed: expected an integer in [0, {SEED_MAX}], found {seed}")


def _table_text(row: dict[str, Any]) -> str:
    if not row:
        return "not recorded"
    return f"{row.get('learner')} row of {row.get('table')}, then any overrides"


def _plan_line(
    task: Task,
    info: SourceInfo,
    rows: int,
    generation: GenerationConfig,
    config: GeneratorConfig,
    profile: str,
    device: torch.device,
) -> str:
    """What stage one is about to do, before it trains: data, settings, what differs."""
    # the profile as it trains on this device: a precision moved there has its own line
    base = GeneratorConfig.profile(profile).on_device(device)[0].to_dict()
    # alpha and sigma are shown anyway (they are per task); the rest only when overridden
    changed = {
        k: v
        for k, v in config.to_dict().items()
        if base.get(k) != v and k not in ("alpha", "sigma")
    }
    differs = ", ".join(f"{k}={v}" for k, v in sorted(changed.items()))
    return (
        f"stage one on {task.name}: {info.id} ({rows:,} rows, {info.env_id}); "
        f"eta {generation.eta:g}, lambda {generation.lam:g}, n {generation.n}, "
        f"alpha {config.alpha:g}, sigma {config.sigma:g}; profile {profile}"
        + (f" with {differs}" if differs else "")
    )


def summary_path(artifact: Path) -> Path:
    """The summary JSON written beside an artifact."""
    return artifact.with_name(artifact.name + ".summary.json")


def _load_or_collect(
    task: Task, source: str | None, root: Path, show_progress: bool, allow_off_band: bool
) -> tuple[Transitions, SourceInfo]:
    spec = source or task.name
    try:
        return load_source(spec, root, task=task)
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
    collect(task, root=root, show_progress=show_progress, allow_off_band=allow_off_band)
    return load_source(spec, root, task=task)


def _reuse_existing(
    out: Path,
    request: ArtifactRequest,
    seconds: dict[str, float],
    also: ArtifactRequest | None = None,
) -> AugmentSummary:
    """Keep an existing artifact built from the same request, or from `also` (after verifying
    it); refuse others."""
    clock = time.perf_counter()
    try:
        artifact = read_artifact(out)
    except DataFormatError as error:
        raise OverwriteError(
            f"{out} exists but is not a valid artifact ({error}); pass --force to replace it"
        ) from None
    accepted = {request.key()} | ({also.key()} if also is not None else set())
    if artifact.manifest.get("request_key") not in accepted:
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
    request: ArtifactRequest,
    behaviour_record: dict[str, Any] | None = None,
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
        "created_utc": utc_now(),
        "table_row": summary["table_row"],
        "hyper_parameters": {
            **asdict(generation),
            "method": "model-rollouts" if behaviour_record else "hipode",
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
            # the rollouts' behaviour policy (method model-rollouts only)
            **({"behaviour_cvae": behaviour_record} if behaviour_record else {}),
        },
        "versions": package_versions(),
        "counts": result.counts,
        "summary": summary,
        "request": asdict(request),
        "request_key": request.key(),
    }
