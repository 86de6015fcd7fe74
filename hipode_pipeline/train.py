"""Stage two's driver: data -> learner -> evaluate -> run folder.

The data comes from the stage contract (`hipode_pipeline.contract`): the artifact whose manifest
matches the learner's table row, or a given one; batch η defaults to what that artifact was
built for. The run lives in a folder named by its identity (`hipode_pipeline.run_folder`), so
rerunning the same command resumes it, or prints its scores when it is finished.
"""

from __future__ import annotations

import json
import math
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from hipode_pipeline import console
from hipode_pipeline.contract import find_artifact, table_learner, table_row
from hipode_pipeline.data.load import load_source
from hipode_pipeline.device import select_device
from hipode_pipeline.errors import HipodeError, SettingError
from hipode_pipeline.evaluate import EvalResult, check_data_fits_env, evaluate_policy
from hipode_pipeline.files import output_lock, write_json_atomic
from hipode_pipeline.generate import MAX_ETA
from hipode_pipeline.learners import learner_class
from hipode_pipeline.learners.base import Learner
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


@dataclass(frozen=True)
class RunData:
    """A run's data and where it came from: the merged rows and the artifact's choice."""

    merged: MergedData
    artifact_choice: str  # "table": found by the learner's table row; "given": --artifact; "none"
    artifact_eta: float | None  # the synthetic rate the artifact was built with, if recorded


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
) -> RunData:
    """The source (the task's collected dataset unless `source` names another) and, for
    data=merged, the artifact the learner's table row asks for (or `artifact`), checked."""
    if data not in DATA_CHOICES:
        raise HipodeError(f"--data: expected one of {DATA_CHOICES}, found {data!r}")
    loaded = load_source(source or task.name, root, task=task)
    if data == "source":
        return RunData(load_merged("", None, loaded=loaded), "none", None)
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
    return RunData(merged, choice, None if artifact_eta is None else float(artifact_eta))


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
        origin=f"learner settings ({learner}.config / {learner}.tasks.{task.name} of "
        "stages/train.toml, overrides)",
    ).to_dict()


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
    run_dir: Path | None = None,
    force: bool = False,
    show_progress: bool = True,
) -> TrainResult:
    """Train `learner` on `task`'s data (merged: source ⊕ its artifact; source: η = 0), evaluate
    it, and write the run folder. Everything is checked before the folder is touched; an
    unfinished run with the same identity resumes, a finished one returns its stored scores."""
    task_obj = get_task(task)
    settings = train_settings()
    family = "d3rlpy" if learner.startswith("d3rlpy:") else learner
    if family not in settings:
        learner_class(learner)  # raises the clear "unknown learner" error
    per_learner, run = settings[family], settings["run"]
    if mixing not in MIXING_MODES:
        raise HipodeError(f"--mixing: expected one of {MIXING_MODES}, found {mixing!r}")
    for flag, value in (("--seed", seed), ("--artifact-seed", artifact_seed)):
        if not 0 <= value <= SEED_MAX:
            raise SettingError(f"{flag}: expected an integer in [0, {SEED_MAX}], found {value}")
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

    manifest = merged.artifact_manifest or {}
    config = {
        "task": task_obj.name,
        "learner": learner,
        "learner_config": learner_config,
        "data": data,
        "eta": eta,
        "mixing": mixing,
        "batch_size": batch_size,
        "seed": seed,
        "steps": steps,
        "eval_every": eval_every,
        "eval_episodes": eval_episodes,
        "log_every": log_every,
        "env_id": env_id,
        "ref_min_score": ref_min,
        "ref_max_score": ref_max,
        "source_id": merged.source["id"],
        "source_sha256": merged.source["sha256"],
        "n_real": len(merged.real),
        "n_synthetic": 0 if merged.synthetic is None else len(merged.synthetic),
        "artifact_path": None if merged.artifact_path is None else str(merged.artifact_path),
        "artifact_checksum": manifest.get("checksum"),
        "artifact_choice": run_data.artifact_choice,
        "artifact_eta": run_data.artifact_eta,
        "artifact_seed": (manifest.get("seeds") or {}).get("seed")
        if isinstance(manifest.get("seeds"), dict)
        else None,
        "artifact_hyper_parameters": _scalars(manifest.get("hyper_parameters")),
        "table_row": table_row(task_obj, learner),
        "device": str(device_obj),
        "torch_threads": torch.get_num_threads(),
        "versions": package_versions(),
    }
    run_dir = Path(run_dir) if run_dir is not None else run_folder(out_dir, config, name)
    if data == "source" and (artifact is not None or requested_eta is not None):
        console.err.print(
            "[yellow]note:[/] --data source trains on the source alone: "
            "--artifact and --eta are not used"
        )
    # one writer per run folder: a second identical command waits, then finds it finished
    with output_lock(run_dir, command="hipode train"):
        state, scores = check_run_dir(run_dir, config, steps, force)
        if scores is not None:
            console.err.print(
                f"{run_dir} already finished {scores.get('steps')} updates: its scores"
            )
            return TrainResult.from_dict({**scores, "finished_earlier": True})
        if eta_note:
            console.err.print(f"[yellow]note:[/] {eta_note}")
        if run_data.artifact_choice == "table":
            console.err.print(f"synthetic data: {merged.artifact_path} (the learner's table row)")

        if cls is None:
            from hipode_pipeline.learners.external import train_d3rlpy

            return train_d3rlpy(
                learner.split(":", 1)[1],
                merged,
                config=config,
                run_dir=run_dir,
                run_state=state,
                device=device_obj,
                show_progress=show_progress,
            )

        model = cls(
            merged.real.obs_dim,
            merged.real.act_dim,
            cls.config_class.from_dict(learner_config),
            device=device_obj,
            seed=seed,
        )
        model.fit_statistics(merged.real)
        config["bf16_autocast"] = bool(getattr(model, "use_bf16", False))
        replay = MixedReplay(
            merged.real, merged.synthetic, eta=eta, mixing=mixing, device=device_obj, seed=seed
        )
        checkpoint = open_run_dir(run_dir, state)
        evaluations: list[dict[str, Any]] = []
        resumed_from = 0
        if checkpoint is not None:
            model.load_state_dict(checkpoint["learner"])
            replay.load_state_dict(checkpoint["replay"])
            evaluations = list(checkpoint["evaluations"])
            resumed_from = model.step
            console.err.print(f"resuming {run_dir} from step {resumed_from}")
        truncate_metrics(run_dir / "metrics.jsonl", resumed_from)
        write_json_atomic(run_dir / "config.json", config)

        train_seconds = _train_loop(
            model, replay, config, run_dir, evaluations, show_progress=show_progress
        )
        ran = model.step - resumed_from
        return finish_run(
            TrainResult(
                run_dir=str(run_dir),
                task=task_obj.name,
                learner=learner,
                data=data,
                eta=eta,
                steps=model.step,
                last={},
                best=None,
                updates_per_second=ran / train_seconds if train_seconds > 0 else 0.0,
                resumed_from=resumed_from,
                evaluations=evaluations,
                seed=seed,
                env_id=env_id,
                data_identity=data_identity(config),
            ),
            eval_episodes,
        )


def _scalars(values: Any) -> dict[str, Any] | None:
    if not isinstance(values, dict):
        return None
    return {k: v for k, v in values.items() if isinstance(v, str | int | float | bool)}


def make_evaluator(policy, config: dict[str, Any]):
    """The run's evaluation: its env, episodes and seed, scored with its reference returns."""

    def evaluate() -> EvalResult:
        return evaluate_policy(
            policy,
            config["env_id"],
            episodes=config["eval_episodes"],
            seed=config["seed"],
            ref_min_score=config["ref_min_score"],
            ref_max_score=config["ref_max_score"],
        )

    return evaluate


def _train_loop(
    model: Learner,
    replay: MixedReplay,
    config: dict[str, Any],
    run_dir: Path,
    evaluations: list[dict[str, Any]],
    *,
    show_progress: bool,
) -> float:
    """Update until `config["steps"]`, logging, evaluating and checkpointing on schedule;
    appends to `evaluations` and returns the seconds spent training (evaluation excluded)."""
    steps, eval_every, log_every = config["steps"], config["eval_every"], config["log_every"]
    batch_size = config["batch_size"]
    evaluate = make_evaluator(model.act, config)
    train_seconds, window_start, window_steps = 0.0, time.perf_counter(), 0
    bar_time, bar_step = window_start, model.step
    with (
        console.progress(disable=not show_progress) as prog,
        open(run_dir / "metrics.jsonl", "a") as metrics_file,
    ):
        bar = prog.add_task(
            f"train {config['learner']} {config['task']}",
            total=steps,
            completed=model.step,
            rate="",
            info="",
        )
        # metric sums stay on the device between log lines: no host sync per update
        sums: dict[str, torch.Tensor] = {}
        counts: dict[str, int] = {}
        while model.step < steps:
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
                    rate = (step - bar_step) / (now - bar_time)
                    prog.update(bar, completed=step, rate=f"{rate:,.0f} upd/s")
                    bar_time, bar_step = now, step
                continue
            elapsed = time.perf_counter() - window_start
            train_seconds += elapsed
            record: dict[str, Any] = {
                "step": step,
                # each metric's mean over the updates since the last line
                **{name: float(total) / counts[name] for name, total in sums.items()},
                "updates_per_s": window_steps / elapsed,
                "wall_s": round(elapsed, 3),
            }
            sums, counts = {}, {}
            if evaluate_now:
                result = evaluate()
                evaluations.append({"step": step, **result.summary()})
                record.update({f"eval_{k}": v for k, v in evaluations[-1].items() if k != "step"})
            metrics_file.write(json.dumps(record) + "\n")
            metrics_file.flush()
            # after the metrics line: a resume drops any line newer than its checkpoint
            save_checkpoint(
                run_dir / "checkpoint.pt",
                {
                    "learner": model.state_dict(),
                    "replay": replay.state_dict(),
                    "evaluations": evaluations,
                },
            )
            last = evaluations[-1] if evaluations else None
            info = (
                f"score {last['score_mean']:.1f} @ {last['step']}"
                if last and last["score_mean"] is not None
                else ""
            )
            prog.update(
                bar, completed=step, rate=f"{record['updates_per_s']:,.0f} upd/s", info=info
            )
            window_start, window_steps = time.perf_counter(), 0
            bar_time, bar_step = window_start, step
    if not evaluations or evaluations[-1]["step"] != model.step:
        evaluations.append({"step": model.step, **evaluate().summary()})
    return train_seconds
