"""Stage two's driver: data -> learner -> evaluate -> run folder.

The data comes from the stage contract (`hipode_pipeline.contract`): the artifact whose manifest
matches the learner's table row, or a given one; batch η defaults to what that artifact was
built for. The run lives in a folder named by its identity (`hipode_pipeline.run_folder`), so
rerunning the same command resumes it, or prints its scores when it is finished.
"""

from __future__ import annotations

import contextlib
import json
import math
import signal
import threading
import time
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from hipode_pipeline import console
from hipode_pipeline.contract import find_artifact, table_learner, table_row
from hipode_pipeline.data.bands import check_source_band
from hipode_pipeline.data.load import load_source
from hipode_pipeline.device import fast_bf16, select_device
from hipode_pipeline.errors import HipodeError, SettingError, TrainingInterrupted
from hipode_pipeline.evaluate import EvalResult, check_data_fits_env, evaluate_policies
from hipode_pipeline.files import display_path, output_lock, write_json_atomic
from hipode_pipeline.generate import MAX_ETA
from hipode_pipeline.learners import learner_class
from hipode_pipeline.learners.base import Learner
from hipode_pipeline.loggers import check_logger, close_loggers, make_logger
from hipode_pipeline.machine import cpu_name, utc_now
from hipode_pipeline.merge import MergedData, load_merged
from hipode_pipeline.paths import stages_dir
from hipode_pipeline.replay import MIXING_MODES, MixedReplay
from hipode_pipeline.run_folder import (
    TrainResult,
    check_run_dir,
    data_identity,
    finish_run,
    open_run_dir,
    run_folder,
    save_checkpoint,
    truncate_metrics,
)
from hipode_pipeline.seeding import SEED_MAX
from hipode_pipeline.simulator import check_env_id
from hipode_pipeline.tasks import Task, all_tasks, get_task
from hipode_pipeline.versions import package_versions

DATA_CHOICES = ("merged", "source")
# a batch η above the artifact's own makes each synthetic row recur this many times more often
# than the artifact was built for; beyond this factor the run is refused
MAX_SYNTHETIC_OVERUSE = 2.0
MAX_STEPS = 100_000_000
MAX_BATCH_SIZE = 1 << 20
MAX_EVAL_EPISODES = 10_000
MAX_SEEDS = 256  # seeds trained side by side in one process
MAX_EVAL_ENVS = 4096  # MuJoCo envs an evaluation of all seeds opens at once
PRECISIONS = ("fp32", "bf16")


@dataclass(frozen=True)
class RunData:
    """A run's data and where it came from: the merged rows and the artifact's choice."""

    merged: MergedData
    artifact_choice: str  # "table": found by the learner's table row; "given": --artifact; "none"
    artifact_eta: float | None  # the synthetic rate the artifact was built with, if recorded
    source_band: dict[str, Any] | None = None  # the source's band verdict (data.bands)


def train_settings() -> dict[str, Any]:
    with open(stages_dir() / "train.toml", "rb") as f:
        return tomllib.load(f)


def resolve_data(
    task: Task,
    learner: str,
    data: str,
    *,
    source: str | None,
    artifact: Path | None,
    artifact_seed: int = 0,
    root: Path | None = None,
    allow_off_band: bool = False,
) -> RunData:
    """The source (the task's collected dataset unless `source` names another) and, for
    data=merged, the artifact the learner's table row asks for (or `artifact`), checked."""
    if data not in DATA_CHOICES:
        raise HipodeError(f"--data: expected one of {DATA_CHOICES}, found {data!r}")
    loaded = load_source(source or task.name, root, task=task)
    band = check_source_band(loaded[1].metadata, str(loaded[1].id), allow_off_band=allow_off_band)
    if data == "source":
        return RunData(load_merged("", None, loaded=loaded), "none", None, band)
    choice = "given"
    if artifact is None:
        info = loaded[1]
        own = source is None or source in (task.name, task.local_dataset_id)
        artifact, _ = find_artifact(
            task,
            learner,
            source_sha256=info.sha256,
            artifact_seed=artifact_seed,
            root=root,
            source_tag=None if own else info.sha256[:8],
            source_spec=None if own else source,
        )
        choice = "table"
    merged = load_merged(source or task.name, artifact, root=root, loaded=loaded)
    params = (merged.artifact_manifest or {}).get("hyper_parameters")
    artifact_eta = params.get("eta") if isinstance(params, dict) else None
    # a rate outside (0, MAX_ETA] (or a bool) is no rate: the file records none we can use
    if (
        isinstance(artifact_eta, bool)
        or not isinstance(artifact_eta, int | float)
        or not 0 < artifact_eta <= MAX_ETA
    ):
        artifact_eta = None
    return RunData(merged, choice, None if artifact_eta is None else float(artifact_eta), band)


def batch_eta(
    data: RunData, requested: float | None, table_eta: float, mixing: str
) -> tuple[float, str | None]:
    """The synthetic fraction per batch and a note for the user, if any.

    Default: the artifact's own synthetic rate (the paper mixes batches at the η the artifact
    was built with), else the learner's table value. A larger η re-draws each synthetic row
    more often than real ones by η / η_artifact: up to MAX_SYNTHETIC_OVERUSE it is allowed with
    a warning, beyond it refused.
    """
    if data.merged.synthetic is None:
        return 0.0, None
    if requested is not None and not (math.isfinite(requested) and 0.0 <= requested <= 1.0):
        raise SettingError(f"--eta: expected a synthetic fraction in [0, 1], found {requested}")
    built = data.artifact_eta
    if requested is None:
        if built is None:
            return table_eta, (
                f"the artifact records no synthetic rate: batch η = {table_eta:g} "
                "from the learner's table row"
            )
        if built > 1.0 and mixing == "mixed":
            raise SettingError(
                f"{data.merged.artifact_path}: built with eta {built:g} (more synthetic rows "
                "than real ones); pass --eta in [0, 1] for the batch fraction"
            )
        return min(built, 1.0), None
    if built is None or mixing != "mixed" or requested <= built:
        return requested, None
    factor = requested / built
    path, ceiling = data.merged.artifact_path, built * MAX_SYNTHETIC_OVERUSE
    if factor > MAX_SYNTHETIC_OVERUSE:
        raise SettingError(
            f"--eta {requested:g}: {path} holds round({built:g}·N) synthetic rows, built for "
            f"batch η ≤ {built:g}; η = {requested:g} would draw each of them {factor:.1f}× as "
            f"often (at most {MAX_SYNTHETIC_OVERUSE:g}× is allowed). Pass --eta ≤ {ceiling:g}, "
            f"or build an artifact with `hipode augment TASK --eta {requested:g}` (plus the "
            "learner's other settings) and train on it with --artifact FILE"
        )
    return requested, (
        f"--eta {requested:g} draws each synthetic row {factor:.1f}× as often as {path.name} "
        f"was built for (η {built:g})"
    )


def builtin_learner_config(
    settings: dict[str, Any],
    learner: str,
    task: Task,
    steps: int,
    overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A built-in learner's settings for `task`: its dataclass defaults, then stages/train.toml's
    [<learner>.config] and [<learner>.tasks.<task>], the paper's learner alpha, then `overrides`."""
    cls = learner_class(learner)
    per_learner = settings.get(learner, {})
    per_task = per_learner.get("tasks", {})
    unknown = sorted(set(per_task) - set(all_tasks()))
    if unknown:
        raise SettingError(
            f"stages/train.toml [{learner}.tasks]: expected task short names, found {unknown}"
        )
    values = {
        **per_learner.get("config", {}),
        **per_task.get(task.name, {}),
        **(overrides or {}),
    }
    learner_alpha = task.augment_params(learner).learner_alpha
    if learner_alpha is not None and learner in ("td3bc", "cql"):
        values.setdefault("alpha" if learner == "td3bc" else "cql_alpha", float(learner_alpha))
    if learner == "iql":
        values.setdefault("max_steps", steps)
    return cls.config_class.from_dict(
        values,
        origin=f"learner settings (stages/train.toml [{learner}.config] and "
        f"[{learner}.tasks.{task.name}], --config, --set)",
    ).to_dict()


def default_bf16(settings: dict[str, Any], learner: str, device: torch.device) -> bool:
    """Whether a learner with bf16 = None runs bf16 matmuls on `device`: the choice of
    stages/train.toml [<learner>.precision] for its kind, and only where bf16 is native."""
    choice = settings.get(learner, {}).get("precision", {}).get(device.type, "fp32")
    if choice not in PRECISIONS:
        raise SettingError(
            f"stages/train.toml [{learner}.precision] {device.type}: expected one of "
            f"{PRECISIONS}, found {choice!r}"
        )
    return choice == "bf16" and fast_bf16(device)


def _positive(name: str, value: int, upper: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= upper:
        raise SettingError(f"{name}: expected an integer in [1, {upper:,}], found {value!r}")
    return value


def run_training(
    task: str,
    learner: str = "td3bc",
    data: str = "merged",
    steps: int | None = None,
    seed: int = 0,
    eval_every: int | None = None,
    eval_episodes: int | None = None,
    out_dir: Path = Path("runs"),
    *,
    run_dir: Path | None = None,
    **options: Any,
) -> TrainResult:
    """One seed's run: `train_seeds` with that seed alone (in `run_dir` if given)."""
    return train_seeds(
        task,
        learner,
        data,
        steps,
        [seed],
        eval_every,
        eval_episodes,
        out_dir,
        run_dirs=None if run_dir is None else [Path(run_dir)],
        **options,
    )[0]


@dataclass
class SeedRun:
    """One seed's run folder and where it stands, inside a group trained together."""

    seed: int
    config: dict[str, Any]
    run_dir: Path
    state: str  # check_run_dir's decision: fresh | resume | replace
    checkpoint: dict[str, Any] | None = None
    evaluations: list[dict[str, Any]] = field(default_factory=list)

    @property
    def resume_step(self) -> int:
        return 0 if self.checkpoint is None else int(self.checkpoint["learner"]["step"])


def train_seeds(
    task: str,
    learner: str = "td3bc",
    data: str = "merged",
    steps: int | None = None,
    seeds: Sequence[int] = (0,),
    eval_every: int | None = None,
    eval_episodes: int | None = None,
    out_dir: Path = Path("runs"),
    *,
    source: str | None = None,
    artifact: Path | None = None,
    artifact_seed: int = 0,
    eta: float | None = None,
    mixing: str = "mixed",
    batch_size: int | None = None,
    log_every: int | None = None,
    learner_settings: dict[str, Any] | None = None,
    device: str | None = None,
    root: Path | None = None,
    name: str | None = None,
    run_dirs: Sequence[Path] | None = None,
    force: bool = False,
    show_progress: bool = True,
    allow_off_band: bool = False,
    logger: str = "none",
) -> list[TrainResult]:
    """Train `learner` on `task`'s data (merged: source ⊕ its artifact; source: η = 0) for each
    of `seeds`, evaluate, and write one run folder per seed, the folder a run of that seed
    alone writes. Built-in learners train all seeds in one process as one stacked model.
    Everything is checked before any folder is touched; unfinished runs with the same identity
    resume, finished ones return their stored scores."""
    task_obj = get_task(task)
    settings = train_settings()
    family = "d3rlpy" if learner.startswith("d3rlpy:") else learner
    if family not in settings:
        learner_class(learner)  # raises the clear "unknown learner" error
    per_learner, run = settings[family], settings["run"]
    if mixing not in MIXING_MODES:
        raise HipodeError(f"--mixing: expected one of {MIXING_MODES}, found {mixing!r}")
    check_logger(logger)
    if logger != "none" and family == "d3rlpy":
        raise SettingError("--logger: for the built-in learners (td3bc, iql, cql)")
    seeds = list(seeds)
    if not seeds or len(set(seeds)) != len(seeds) or len(seeds) > MAX_SEEDS:
        raise SettingError(
            f"--seeds: expected 1 to {MAX_SEEDS} distinct seeds, found {seeds or 'none'}"
        )
    for flag, value in [*(("--seed", s) for s in seeds), ("--artifact-seed", artifact_seed)]:
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= SEED_MAX:
            raise SettingError(f"{flag}: expected an integer in [0, {SEED_MAX}], found {value!r}")
    if run_dirs is not None and len(run_dirs) != len(seeds):
        raise SettingError(
            f"run_dirs: expected one folder per seed ({len(seeds)}), found {len(run_dirs)}"
        )
    device_obj = select_device(device)
    if steps is None:
        steps = per_learner["steps"] if device_obj.type == "cuda" else per_learner["cpu_steps"]
    steps = _positive("--steps", steps, MAX_STEPS)
    eval_every = _positive(
        "--eval-every", per_learner["eval_every"] if eval_every is None else eval_every, MAX_STEPS
    )
    eval_episodes = _positive(
        "--eval-episodes",
        run["eval_episodes"] if eval_episodes is None else eval_episodes,
        MAX_EVAL_EPISODES,
    )
    if len(seeds) * eval_episodes > MAX_EVAL_ENVS:
        raise SettingError(
            f"--seeds × --eval-episodes: expected at most {MAX_EVAL_ENVS:,} evaluation episodes "
            f"stepped together, found {len(seeds)} × {eval_episodes}; train fewer seeds per "
            "command"
        )
    batch_size = _positive(
        "--batch-size", run["batch_size"] if batch_size is None else batch_size, MAX_BATCH_SIZE
    )
    log_every = _positive("log_every", run["log_every"] if log_every is None else log_every, 10**9)

    requested_eta = eta
    run_data = resolve_data(
        task_obj,
        learner,
        data,
        source=source,
        artifact=artifact,
        artifact_seed=artifact_seed,
        root=root,
        allow_off_band=allow_off_band,
    )
    merged = run_data.merged
    params = task_obj.augment_params(table_learner(learner))
    eta, eta_note = batch_eta(run_data, eta if data == "merged" else None, params.eta, mixing)
    env_id = merged.env_id or task_obj.env_id
    origin = str(merged.source.get("id"))
    check_env_id(env_id, origin=origin)
    check_data_fits_env(env_id, merged.real.obs_dim, merged.real.act_dim, origin)
    ref_min, ref_max = merged.ref_scores()
    if ref_min is None or ref_max is None:
        ref_min, ref_max = task_obj.ref_min_score, task_obj.ref_max_score

    if family == "d3rlpy":
        # the paper's learner alpha, and IQL's reward normalization as our IQL runs this task
        iql = builtin_learner_config(settings, "iql", task_obj, steps)
        learner_config: dict[str, Any] = {
            "alpha": params.learner_alpha,
            "normalize_reward": iql["normalize_reward"],
        }
        cls = None
    else:
        cls = learner_class(learner)
        learner_config = builtin_learner_config(
            settings, learner, task_obj, steps, learner_settings
        )
        if learner_config["bf16"] is None:
            learner_config["bf16"] = default_bf16(settings, learner, device_obj)

    manifest = merged.artifact_manifest or {}
    config = {
        "task": task_obj.name,
        "learner": learner,
        "learner_config": learner_config,
        "data": data,
        "eta": eta,
        "mixing": mixing,
        "batch_size": batch_size,
        "seed": seeds[0],
        "steps": steps,
        "eval_every": eval_every,
        "eval_episodes": eval_episodes,
        "log_every": log_every,
        "env_id": env_id,
        "ref_min_score": ref_min,
        "ref_max_score": ref_max,
        # only where the task's horizon is shorter than the env's (Adroit pen), so the configs of
        # every other run stay as they were
        **(
            {"eval_max_episode_steps": task_obj.max_episode_steps}
            if task_obj.max_episode_steps
            else {}
        ),
        "source_id": display_path(merged.source["id"]),
        "source_sha256": merged.source["sha256"],
        "n_real": len(merged.real),
        "n_synthetic": 0 if merged.synthetic is None else len(merged.synthetic),
        "artifact_path": display_path(merged.artifact_path),
        "artifact_checksum": manifest.get("checksum"),
        "artifact_choice": run_data.artifact_choice,
        "artifact_eta": run_data.artifact_eta,
        "artifact_seed": (manifest.get("seeds") or {}).get("seed")
        if isinstance(manifest.get("seeds"), dict)
        else None,
        "artifact_hyper_parameters": _scalars(manifest.get("hyper_parameters")),
        "table_row": table_row(task_obj, learner),
        "source_band": run_data.source_band,
        "allowed_off_band": bool(run_data.source_band and run_data.source_band["in_band"] is False),
        "device": str(device_obj),
        "torch_threads": torch.get_num_threads(),
        "versions": package_versions(),
    }
    runs = []
    for i, seed in enumerate(seeds):
        seed_config = {**config, "seed": seed}
        if run_dirs is not None:
            folder = Path(run_dirs[i])
        else:
            seed_name = name if name is None or len(seeds) == 1 else f"{name}-seed{seed}"
            folder = run_folder(out_dir, seed_config, seed_name)
        runs.append(SeedRun(seed, seed_config, folder, "fresh"))
    if data == "source" and (artifact is not None or requested_eta is not None):
        console.err.print(
            "[yellow]note:[/] --data source trains on the source alone: "
            "--artifact and --eta are not used"
        )
    folders = [seed_run.run_dir.resolve() for seed_run in runs]
    if len(set(folders)) != len(folders):
        raise SettingError(f"run folders: expected one per seed, found repeats in {folders}")
    results: dict[int, TrainResult] = {}
    # one writer per run folder: a second identical command waits, then finds it finished;
    # folders are locked in one order, so two overlapping seed lists never wait on each other
    with contextlib.ExitStack() as locks:
        for seed_run in sorted(runs, key=lambda r: str(r.run_dir)):
            locks.enter_context(output_lock(seed_run.run_dir, command="hipode train"))
        pending = []
        for seed_run in runs:
            seed_run.state, scores = check_run_dir(seed_run.run_dir, seed_run.config, steps, force)
            if scores is not None:
                console.err.print(
                    f"{seed_run.run_dir} already finished {scores.get('steps')} updates: its scores"
                )
                results[seed_run.seed] = TrainResult.from_dict({**scores, "finished_earlier": True})
            else:
                pending.append(seed_run)
        if pending:
            console.err.print(console.plain(_plan_line(config, pending, merged)))
            if eta_note:
                console.err.print(f"[yellow]note:[/] {eta_note}")
            if run_data.artifact_choice == "table":
                console.err.print(
                    f"synthetic data: {merged.artifact_path} (the learner's table row)"
                )
        if cls is None:
            from hipode_pipeline.learners.external import train_d3rlpy

            for seed_run in pending:
                results[seed_run.seed] = train_d3rlpy(
                    learner.split(":", 1)[1],
                    merged,
                    config=seed_run.config,
                    run_dir=seed_run.run_dir,
                    run_state=seed_run.state,
                    device=device_obj,
                    show_progress=show_progress,
                )
            return [results[seed] for seed in seeds]

        for seed_run in pending:
            seed_run.checkpoint = open_run_dir(seed_run.run_dir, seed_run.state)
            if seed_run.checkpoint is not None:
                seed_run.evaluations = list(seed_run.checkpoint["evaluations"])
        # seeds resumed from one step train together; a group per distinct step otherwise
        groups: dict[int, list[SeedRun]] = {}
        for seed_run in pending:
            groups.setdefault(seed_run.resume_step, []).append(seed_run)
        for resume_step, group in sorted(groups.items()):
            for result in _train_group(
                cls,
                learner_config,
                merged,
                group,
                resume_step,
                device=device_obj,
                show_progress=show_progress,
                logger=logger,
            ):
                results[result.seed] = result
    return [results[seed] for seed in seeds]


def _plan_line(config: dict[str, Any], pending: list[SeedRun], merged: MergedData) -> str:
    """What is about to train, in one line: learner, data, seeds, budget, device, precision."""
    seeds = [r.seed for r in pending]
    data = f"{config['source_id']} ({config['n_real']:,} rows)"
    if config["data"] == "merged":
        data += f" ⊕ {Path(str(merged.artifact_path)).name} ({config['n_synthetic']:,} rows, "
        data += f"batch η {config['eta']:g})"
    bf16 = config["learner_config"].get("bf16")
    return (
        f"training {config['learner']} on {config['task']}: {data}; "
        f"seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}; "
        f"{config['steps']:,} updates of {config['batch_size']}; {config['device']}, "
        f"{'bf16 hidden matmuls' if bf16 else 'fp32'}"
    )


def _train_group(
    cls: type[Learner],
    learner_config: dict[str, Any],
    merged: MergedData,
    group: list[SeedRun],
    resume_step: int,
    *,
    device: torch.device,
    show_progress: bool,
    logger: str = "none",
) -> list[TrainResult]:
    """Seeds at one step, trained as one stacked learner; each run folder written as a run of
    that seed alone writes it."""
    config = group[0].config
    seeds = [seed_run.seed for seed_run in group]
    model = cls(
        merged.real.obs_dim,
        merged.real.act_dim,
        cls.config_class.from_dict(learner_config),
        device=device,
        seed=seeds,
    )
    model.fit_statistics(merged.real)
    replay = MixedReplay(
        merged.real,
        merged.synthetic,
        eta=config["eta"],
        mixing=config["mixing"],
        device=device,
        seed=seeds,
    )
    if resume_step:
        origin = ", ".join(str(r.run_dir / "checkpoint.pt") for r in group)
        model.load_seed_states([r.checkpoint["learner"] for r in group], origin=origin)
        replay.load_seed_states([r.checkpoint["replay"] for r in group])
        for seed_run in group:
            console.err.print(f"resuming {seed_run.run_dir} from step {resume_step}")
    precision = "bf16" if getattr(model, "use_bf16", False) else "fp32"
    for seed_run in group:
        seed_run.config["precision"] = precision
        seed_run.config["seeds_trained_together"] = seeds
        # every session of the run, with the seeds it was stacked with: float rounding depends
        # on the group, so a resume in another group continues close to, not exactly as, before
        versions = seed_run.config["versions"]
        seed_run.config["sessions"] = [
            *_previous_sessions(seed_run.run_dir, resume_step),
            {
                "from_step": resume_step,
                "seeds_trained_together": seeds,
                "started_utc": utc_now(),
                "cpu": cpu_name(),
                # config.json's versions are this session's; each session keeps its own code state
                "git_commit": versions["git_commit"],
                "git_modified": versions["git_modified"],
            },
        ]
        truncate_metrics(seed_run.run_dir / "metrics.jsonl", resume_step)
        write_json_atomic(seed_run.run_dir / "config.json", seed_run.config)

    train_seconds = _train_loop(model, replay, group, show_progress=show_progress, logger=logger)
    ran = model.step - resume_step
    results = []
    for seed_run in group:
        c = seed_run.config
        results.append(
            finish_run(
                TrainResult(
                    run_dir=display_path(seed_run.run_dir),
                    task=c["task"],
                    learner=c["learner"],
                    data=c["data"],
                    eta=c["eta"],
                    steps=model.step,
                    last={},
                    best=None,
                    updates_per_second=ran / train_seconds if train_seconds > 0 else 0.0,
                    resumed_from=resume_step,
                    evaluations=seed_run.evaluations,
                    seed=seed_run.seed,
                    env_id=c["env_id"],
                    data_identity=data_identity(c),
                ),
                c["eval_episodes"],
            )
        )
    return results


def _scalars(values: Any) -> dict[str, Any] | None:
    if not isinstance(values, dict):
        return None
    return {k: v for k, v in values.items() if isinstance(v, str | int | float | bool)}


def _previous_sessions(run_dir: Path, resume_step: int) -> list[dict[str, Any]]:
    """The sessions config.json lists that ended at or before `resume_step`."""
    try:
        previous = json.loads((run_dir / "config.json").read_text()).get("sessions", [])
    except (OSError, ValueError, AttributeError):
        return []
    if not isinstance(previous, list):
        return []
    return [
        session
        for session in previous
        if isinstance(session, dict)
        and isinstance(session.get("from_step"), int)
        and session["from_step"] < resume_step
    ]


def make_evaluator(policies, config: dict[str, Any], seeds: Sequence[int]):
    """The runs' evaluation: their env and episodes, seed k's policy on seed k's starts, scored
    with the data's reference returns; `policies` maps (K, n, ds) -> (K, n, da)."""

    def evaluate() -> list[EvalResult]:
        return evaluate_policies(
            policies,
            config["env_id"],
            episodes=config["eval_episodes"],
            seeds=seeds,
            ref_min_score=config["ref_min_score"],
            ref_max_score=config["ref_max_score"],
            max_episode_steps=config.get("eval_max_episode_steps"),
        )

    return evaluate


def _train_loop(
    model: Learner,
    replay: MixedReplay,
    group: list[SeedRun],
    *,
    show_progress: bool,
    logger: str = "none",
) -> float:
    """Update every seed of `group` until `config["steps"]`, logging (metrics.jsonl and
    `logger`), evaluating and checkpointing each seed's folder on schedule; appends to each
    seed's evaluations and returns the seconds spent training (evaluation excluded)."""
    config = group[0].config
    steps, eval_every, log_every = config["steps"], config["eval_every"], config["log_every"]
    batch_size = config["batch_size"]
    evaluate = make_evaluator(model.act_all, config, [r.seed for r in group])
    k = len(group)
    label = f"train {config['learner']} {config['task']}" + (f" ×{k} seeds" if k > 1 else "")
    train_seconds, window_start, window_steps = 0.0, time.perf_counter(), 0
    bar_time, bar_step = window_start, model.step
    with contextlib.ExitStack() as files, console.progress(disable=not show_progress) as prog:
        metrics_files = [files.enter_context(open(r.run_dir / "metrics.jsonl", "a")) for r in group]
        loggers = [make_logger(logger, r.run_dir, r.config) for r in group]
        files.callback(close_loggers, loggers)
        bar = prog.add_task(label, total=steps, completed=model.step, rate="", info="")
        # metric sums stay on the device between log lines: no host sync per update
        sums: dict[str, torch.Tensor] = {}
        counts: dict[str, int] = {}
        interrupted = files.enter_context(interrupt_flag())
        while model.step < steps:
            if interrupted.is_set():
                # between two updates: every seed's state is whole
                _checkpoint_on_interrupt(model, replay, group)
            for name, value in model.update(replay.sample(batch_size)).items():
                if name in sums:
                    sums[name].add_(value)
                else:
                    sums[name] = value.clone()
                counts[name] = counts.get(name, 0) + 1
            step, window_steps = model.step, window_steps + 1
            evaluate_now = step % eval_every == 0 or step == steps
            if step % log_every and not evaluate_now:
                now = time.perf_counter()
                if now - bar_time >= 0.5:  # a live rate without a terminal write per update
                    prog.update(bar, completed=step, rate=_rate(step - bar_step, now - bar_time, k))
                    bar_time, bar_step = now, step
                continue
            elapsed = time.perf_counter() - window_start
            train_seconds += elapsed
            means = _window_means(sums, counts)
            sums, counts = {}, {}
            results = evaluate() if evaluate_now else None
            for i, seed_run in enumerate(group):
                record: dict[str, Any] = {
                    "step": step,
                    **{name: values[i] for name, values in means.items()},
                    "updates_per_s": window_steps / elapsed,
                    "wall_s": round(elapsed, 3),
                }
                if results is not None:
                    seed_run.evaluations.append({"step": step, **results[i].summary()})
                    record.update(
                        {
                            f"eval_{key}": v
                            for key, v in seed_run.evaluations[-1].items()
                            if key != "step"
                        }
                    )
                    record["eval_returns"] = results[i].returns
                metrics_files[i].write(json.dumps(record) + "\n")
                metrics_files[i].flush()
                loggers[i].log(step, record)
                # after the metrics line: a resume drops any line newer than its checkpoint
                _save_seed_checkpoint(model, replay, group, i)
            prog.update(
                bar,
                completed=step,
                rate=_rate(window_steps, elapsed, k),
                info=_score_info(group),
            )
            window_start, window_steps = time.perf_counter(), 0
            bar_time, bar_step = window_start, step
    if any(not r.evaluations or r.evaluations[-1]["step"] != model.step for r in group):
        for seed_run, result in zip(group, evaluate(), strict=True):
            if not seed_run.evaluations or seed_run.evaluations[-1]["step"] != model.step:
                seed_run.evaluations.append({"step": model.step, **result.summary()})
    return train_seconds


def _save_seed_checkpoint(model: Learner, replay: MixedReplay, group: list[SeedRun], i: int):
    save_checkpoint(
        group[i].run_dir / "checkpoint.pt",
        {
            "learner": model.seed_state(i),
            "replay": replay.seed_state(i),
            "evaluations": group[i].evaluations,
        },
    )


@contextlib.contextmanager
def interrupt_flag():
    """A flag Ctrl-C (SIGINT) sets instead of raising, so training stops between updates;
    outside the main thread (no signal handling there) it is never set."""
    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return
    previous = signal.signal(signal.SIGINT, lambda *_: flag.set())
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous)


def _checkpoint_on_interrupt(model: Learner, replay: MixedReplay, group: list[SeedRun]):
    """Ctrl-C: every seed's state at the last finished update goes to its checkpoint, so a
    rerun of the same command resumes from there; then a clear message and exit code 130."""
    for i in range(len(group)):
        _save_seed_checkpoint(model, replay, group, i)
    folders = ", ".join(str(r.run_dir) for r in group)
    raise TrainingInterrupted(
        f"interrupted after update {model.step:,}: checkpoint saved in {folders}; "
        "run the same command again to resume from there"
    ) from None


def _window_means(sums: dict[str, torch.Tensor], counts: dict[str, int]) -> dict[str, list[float]]:
    """Each metric's mean over the updates since the last line, one value per seed, read from
    the device in one transfer."""
    if not sums:
        return {}
    names = list(sums)
    totals = torch.stack([sums[name] for name in names]).cpu().double()
    means = totals / torch.tensor([[counts[name]] for name in names], dtype=torch.float64)
    return dict(zip(names, means.tolist(), strict=True))


def _rate(updates: int, seconds: float, seeds: int) -> str:
    per_seed = updates / seconds if seconds > 0 else 0.0
    if seeds == 1:
        return f"{per_seed:,.0f} upd/s"
    return f"{per_seed:,.0f} upd/s per seed, {per_seed * seeds:,.0f} in all"


def _score_info(group: list[SeedRun]) -> str:
    scores = [
        r.evaluations[-1]["score_mean"]
        for r in group
        if r.evaluations and r.evaluations[-1]["score_mean"] is not None
    ]
    if not scores:
        return ""
    step = group[0].evaluations[-1]["step"]
    if len(scores) == 1:
        return f"score {scores[0]:.1f} @ {step}"
    return f"score {sum(scores) / len(scores):.1f} (mean of {len(scores)}) @ {step}"
