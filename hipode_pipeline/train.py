"""One training run of stage two: a learner on source ⊕ synthetic (or the source alone),
evaluated at intervals and at the end, in a run folder that makes it resumable:

    runs/<task>/<learner>-<data>-seed<seed>/
        config.json     what was run: task, data (source sha256, artifact path + checksum),
                        learner settings, η, seeds, package versions
        metrics.jsonl   one line per log interval: step, losses, updates/s, evaluation
        checkpoint.pt   weights, optimizers, step and RNG states (atomic; weights_only loadable)
        scores.json     the last evaluation (the result) and the best one (labelled as such)

Rerunning the same command on an unfinished run resumes from its checkpoint and continues
exactly as an uninterrupted run would.
"""

from __future__ import annotations

import json
import shutil
import time
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from hipode_pipeline import console
from hipode_pipeline.artifact import default_artifact_path
from hipode_pipeline.device import select_device
from hipode_pipeline.errors import DatasetNotFoundError, HipodeError, OverwriteError
from hipode_pipeline.evaluate import EvalResult, evaluate_policy
from hipode_pipeline.files import (
    load_torch,
    save_torch_atomic,
    write_json_atomic,
    write_text_atomic,
)
from hipode_pipeline.learners import LEARNERS, learner_class
from hipode_pipeline.merge import MergedData, load_merged
from hipode_pipeline.paths import stages_dir
from hipode_pipeline.replay import MIXING_MODES, MixedReplay
from hipode_pipeline.tasks import get_task
from hipode_pipeline.versions import package_versions

DATA_CHOICES = ("merged", "source")
BEST_LABEL = "best of all evaluations (optimistic: picked on the evaluation episodes themselves)"
# config.json keys that must match for a rerun to continue an existing run
IDENTITY_KEYS = (
    "task",
    "learner",
    "learner_config",
    "data",
    "eta",
    "mixing",
    "batch_size",
    "seed",
    "source_sha256",
    "artifact_checksum",
)


@dataclass
class TrainResult:
    """What a finished run reports; also written as scores.json."""

    run_dir: str  # the run folder
    task: str
    learner: str
    data: str  # merged | source
    eta: float  # synthetic fraction per batch
    steps: int  # updates done
    last: dict[str, Any]  # the final evaluation: step, return and score mean/std
    best: dict[str, Any] | None  # the best evaluation, labelled as such
    updates_per_second: float  # training throughput (evaluation time excluded)
    resumed_from: int  # step the run continued from (0: fresh)
    evaluations: list[dict[str, Any]] = field(default_factory=list)  # every evaluation

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def train_settings() -> dict[str, Any]:
    with open(stages_dir() / "train.toml", "rb") as f:
        return tomllib.load(f)


def run_folder(out_dir: Path, task: str, learner: str, data: str, seed: int) -> Path:
    return Path(out_dir) / task / f"{learner.replace(':', '-')}-{data}-seed{seed}"


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    save_torch_atomic(path, state)


def load_checkpoint(path: Path) -> dict[str, Any]:
    return load_torch(path, "a checkpoint written by `hipode train` (delete it or pass --force)")


def resolve_data(
    task_name: str,
    learner: str,
    data: str,
    *,
    source: str | None,
    artifact: Path | None,
    root: Path | None,
) -> MergedData:
    """The source (the task's collected dataset unless `source` names another) and, for
    data=merged, the artifact `hipode augment` wrote for this task (or `artifact`)."""
    if data not in DATA_CHOICES:
        raise HipodeError(f"--data: expected one of {DATA_CHOICES}, found {data!r}")
    task = get_task(task_name)
    if data == "merged" and artifact is None:
        # `hipode augment` writes the td3bc-named file; any learner may train on it
        candidates = [
            default_artifact_path(task.name, learner=name, seed=0, root=root)
            for name in dict.fromkeys([learner if learner in LEARNERS else "td3bc", "td3bc"])
        ]
        artifact = next((path for path in candidates if path.is_file()), candidates[-1])
        if not artifact.is_file():
            raise DatasetNotFoundError(
                f"no synthetic artifact for {task.name} at {artifact}; "
                f"run `make augment TASK={task.name}` (or `hipode augment {task.name}`) first, "
                "pass --artifact FILE, or train on --data source"
            )
    return load_merged(source or task.name, artifact if data == "merged" else None, root=root)


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
    eta: float | None = None,
    mixing: str = "mixed",
    batch_size: int | None = None,
    log_every: int | None = None,
    learner_settings: dict[str, Any] | None = None,
    device: str | None = None,
    root: Path | None = None,
    force: bool = False,
    show_progress: bool = True,
) -> TrainResult:
    """Train `learner` on `task`'s data (merged: source ⊕ its artifact; source: η = 0), evaluate
    it, and write the run folder. Resumes an unfinished run with the same settings."""
    task_obj = get_task(task)
    settings = train_settings()
    family = "d3rlpy" if learner.startswith("d3rlpy:") else learner
    if family not in settings:
        learner_class(learner)  # raises the clear "unknown learner" error
    per_learner, run = settings[family], settings["run"]
    device_obj = select_device(device)
    if steps is None:
        steps = per_learner["steps"] if device_obj.type == "cuda" else per_learner["cpu_steps"]
    eval_every = eval_every or per_learner["eval_every"]
    eval_episodes = eval_episodes or run["eval_episodes"]
    batch_size = batch_size or run["batch_size"]
    log_every = log_every or run["log_every"]
    if steps < 1 or eval_every < 1 or eval_episodes < 1 or batch_size < 1 or log_every < 1:
        raise HipodeError(
            "steps, eval_every, eval_episodes, batch_size and log_every: expected positive integers"
        )
    if mixing not in MIXING_MODES:
        raise HipodeError(f"--mixing: expected one of {MIXING_MODES}, found {mixing!r}")

    merged = resolve_data(task_obj.name, learner, data, source=source, artifact=artifact, root=root)
    params = task_obj.augment_params(learner if learner in LEARNERS else "td3bc")
    if data == "source":
        eta = 0.0
    elif eta is None:
        eta = params.eta
    env_id = merged.env_id or task_obj.env_id
    ref_min, ref_max = merged.ref_scores()
    if ref_min is None or ref_max is None:
        ref_min, ref_max = task_obj.ref_min_score, task_obj.ref_max_score

    if family == "d3rlpy":
        from hipode_pipeline.learners.external import train_d3rlpy

        return train_d3rlpy(
            learner.split(":", 1)[1],
            merged,
            task=task_obj.name,
            data=data,
            eta=eta,
            steps=steps,
            seed=seed,
            eval_every=eval_every,
            eval_episodes=eval_episodes,
            env_id=env_id,
            ref_scores=(ref_min, ref_max),
            run_dir=run_folder(out_dir, task_obj.name, learner, data, seed),
            batch_size=batch_size,
            device=device_obj,
            learner_alpha=params.learner_alpha,
            force=force,
            show_progress=show_progress,
        )

    cls = learner_class(learner)
    overrides = {**per_learner.get("config", {}), **(learner_settings or {})}
    if params.learner_alpha is not None and learner in ("td3bc", "cql"):
        overrides.setdefault(
            "alpha" if learner == "td3bc" else "cql_alpha", float(params.learner_alpha)
        )
    if learner == "iql":
        overrides.setdefault("max_steps", steps)
    learner_config = cls.config_class.from_dict(
        overrides,
        origin=f"learner settings (table {learner}.config of stages/train.toml, overrides)",
    )

    config = {
        "task": task_obj.name,
        "learner": learner,
        "learner_config": learner_config.to_dict(),
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
        "artifact_checksum": (merged.artifact_manifest or {}).get("checksum"),
        "device": str(device_obj),
        "torch_threads": torch.get_num_threads(),
        "versions": package_versions(),
    }
    run_dir = run_folder(out_dir, task_obj.name, learner, data, seed)
    checkpoint_path, metrics_path = run_dir / "checkpoint.pt", run_dir / "metrics.jsonl"
    checkpoint = _prepare_run_dir(run_dir, config, steps, force)

    model = cls(
        merged.real.obs_dim, merged.real.act_dim, learner_config, device=device_obj, seed=seed
    )
    model.fit_statistics(merged.real)
    config["bf16_autocast"] = bool(getattr(model, "use_bf16", False))
    replay = MixedReplay(
        merged.real, merged.synthetic, eta=eta, mixing=mixing, device=device_obj, seed=seed
    )
    evaluations: list[dict[str, Any]] = []
    resumed_from = 0
    if checkpoint is not None:
        model.load_state_dict(checkpoint["learner"])
        replay.load_state_dict(checkpoint["replay"])
        evaluations = list(checkpoint["evaluations"])
        resumed_from = model.step
        console.err.print(f"resuming {run_dir} from step {resumed_from}")
    _truncate_metrics(metrics_path, resumed_from)
    write_json_atomic(run_dir / "config.json", config)

    def evaluate() -> EvalResult:
        return evaluate_policy(
            model.act,
            env_id,
            episodes=eval_episodes,
            seed=seed,
            ref_min_score=ref_min,
            ref_max_score=ref_max,
        )

    train_seconds, window_start, window_steps = 0.0, time.perf_counter(), 0
    bar_time, bar_step = window_start, model.step
    with (
        console.progress(disable=not show_progress) as prog,
        open(metrics_path, "a") as metrics_file,
    ):
        bar = prog.add_task(
            f"train {learner} {task_obj.name}", total=steps, completed=model.step, rate="", info=""
        )
        while model.step < steps:
            losses = model.update(replay.sample(batch_size))
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
                **losses,
                "updates_per_s": window_steps / elapsed,
            }
            if evaluate_now:
                result = evaluate()
                evaluations.append({"step": step, **result.summary()})
                record.update({f"eval_{k}": v for k, v in evaluations[-1].items() if k != "step"})
            metrics_file.write(json.dumps(record) + "\n")
            metrics_file.flush()
            # after the metrics line: a resume drops any line newer than its checkpoint
            save_checkpoint(
                checkpoint_path,
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
        result = evaluate()
        evaluations.append({"step": model.step, **result.summary()})
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
        ),
        eval_episodes,
    )


def finish_run(result: TrainResult, eval_episodes: int) -> TrainResult:
    """Label the last evaluation (the result) and the best one, and write scores.json."""
    evaluations = result.evaluations
    best = max(
        evaluations,
        key=lambda e: e["score_mean"] if e["score_mean"] is not None else e["return_mean"],
    )
    result.last = {
        **evaluations[-1],
        "episodes": eval_episodes,
        "label": "last evaluation (the result)",
    }
    result.best = {**best, "label": BEST_LABEL}
    write_json_atomic(Path(result.run_dir) / "scores.json", result.to_dict())
    return result


def differing_settings(run_dir: Path, expected: dict[str, Any]) -> list[str]:
    """The keys of `expected` whose value differs from the run folder's config.json."""
    config_path = run_dir / "config.json"
    previous = json.loads(config_path.read_text()) if config_path.is_file() else {}
    return [
        key
        for key, value in expected.items()
        if previous.get(key) != json.loads(json.dumps(value, default=str))
    ]


def _scores_if_finished(run_dir: Path, steps: int) -> dict[str, Any] | None:
    """scores.json of a run finished to at least `steps` updates; None if unfinished or absent."""
    scores_path = run_dir / "scores.json"
    if not scores_path.is_file():
        return None
    scores = json.loads(scores_path.read_text())
    return scores if scores.get("steps", 0) >= steps else None


def finished_scores(run_dir: Path, steps: int, expected: dict[str, Any]) -> dict[str, Any] | None:
    """scores.json of a run in `run_dir` finished to at least `steps` updates; None if there is
    none yet. Read-only; a finished run whose settings differ from `expected` is refused."""
    scores = _scores_if_finished(run_dir, steps)
    if scores is None:
        return None  # unfinished at this budget: run_training continues it
    differing = differing_settings(run_dir, expected)
    if differing:
        raise OverwriteError(
            f"{run_dir}: holds a finished run with other settings ({', '.join(differing)} "
            "differ); pass --force to train it again or --out for another folder"
        )
    return scores


def _prepare_run_dir(
    run_dir: Path, config: dict[str, Any], steps: int, force: bool
) -> dict[str, Any] | None:
    """Make the run folder; return the checkpoint to resume from, if any."""
    checkpoint_path = run_dir / "checkpoint.pt"
    if force and run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if not (run_dir / "config.json").is_file():
        return None
    differing = differing_settings(run_dir, {key: config[key] for key in IDENTITY_KEYS})
    if differing:
        raise OverwriteError(
            f"{run_dir} holds a run with other settings ({', '.join(differing)} differ); "
            "pass --force to replace it or --out for another folder"
        )
    if _scores_if_finished(run_dir, steps) is not None:
        raise OverwriteError(
            f"{run_dir} already finished {steps} steps (see scores.json); "
            "pass --force to train again"
        )
    return load_checkpoint(checkpoint_path) if checkpoint_path.is_file() else None


def _truncate_metrics(path: Path, step: int) -> None:
    """Drop metric lines written after the checkpoint we resume from (they will be rewritten)."""
    if not path.is_file():
        return
    kept = [
        line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step
    ]
    write_text_atomic(path, "".join(line + "\n" for line in kept))


def score_table_rows(result: TrainResult) -> list[list[Any]]:
    """One row: the last evaluation is the result; the best one is shown apart, labelled."""
    last, best = result.last, result.best or {}
    best_score = best.get("score_mean")
    return [
        [
            result.task,
            f"{result.learner} ({result.data}, η={result.eta:g})",
            result.steps,
            _pm(last.get("score_mean"), last.get("score_std"), "{:.1f}"),
            _pm(last.get("return_mean"), last.get("return_std"), "{:.0f}"),
            "n/a" if best_score is None else f"{best_score:.1f} @ {best.get('step')}",
            f"{result.updates_per_second:.0f}",
        ]
    ]


SCORE_COLUMNS = ["task", "learner", "steps", "score", "return", "best (optimistic)", "upd/s"]
SCORE_TITLE = "Last evaluation (D4RL-normalized score; best over all evaluations apart)"


def _pm(mean: float | None, std: float | None, fmt: str) -> str:
    return "n/a" if mean is None else f"{fmt.format(mean)} ± {fmt.format(std or 0.0)}"
