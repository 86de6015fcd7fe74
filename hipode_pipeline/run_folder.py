"""The run folder of stage two: what a run is (its identity), where it lives, and the files that
make it resumable and readable, for our learners and for other libraries' alike:

    <out>/<task>/<learner>-<data>[-eta<η>]-<identity[:8]>-seed<seed>/   (or <out>/<task>/<name>/)
        config.json     what was run: task, data (source sha256, artifact path + checksum),
                        learner settings, η, seeds, package versions (the latest session's),
                        and each session's start step, stacked seeds, start time, CPU and commit
        metrics.jsonl   one line per log interval: step, each metric's mean over the interval,
                        updates/s, wall time, evaluation
        checkpoint.pt   weights, optimizers, step and RNG states (atomic; weights_only loadable)
        scores.json     the last evaluation (the result) and the best one (labelled as such)

The identity hashes everything that makes two runs different experiments (data, η, mixing,
learner settings, batch size), so a sweep over any of them never lands in one folder.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from hipode_pipeline.errors import OverwriteError, SettingError
from hipode_pipeline.files import (
    load_torch,
    save_torch_atomic,
    write_json_atomic,
    write_text_atomic,
)
from hipode_pipeline.machine import cpu_name, utc_now

BEST_LABEL = "best of all evaluations (optimistic: picked on the evaluation episodes themselves)"
# config.json keys that make a run a different experiment; the seed is in the folder name
IDENTITY_KEYS = (
    "task",
    "learner",
    "learner_config",
    "data",
    "eta",
    "mixing",
    "batch_size",
    "source_sha256",
    "artifact_checksum",
)
RUN_NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._=+-]{0,127}")


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
    seed: int | None = None  # training and evaluation seed
    env_id: str | None = None  # the env the policy was evaluated in
    data_identity: dict[str, Any] = field(default_factory=dict)  # source sha, artifact, η
    finished_earlier: bool = False  # read back from scores.json instead of trained now
    # when and where the last session of the run finished: its figures come with their machine
    finished_utc: str | None = None
    cpu: str | None = None
    load_average: list[float] | None = None  # 1, 5 and 15 minutes, at the finish

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainResult:
        known = {f.name for f in fields(cls)}
        return cls(**{key: value for key, value in data.items() if key in known})


def run_identity(config: dict[str, Any]) -> str:
    """sha256 over the identity keys of a run's config (JSON, sorted)."""
    identity = {key: config.get(key) for key in IDENTITY_KEYS}
    return hashlib.sha256(json.dumps(identity, sort_keys=True, default=str).encode()).hexdigest()


def run_folder(out_dir: Path, config: dict[str, Any], name: str | None = None) -> Path:
    """Where the run described by `config` lives: a readable prefix, the identity and the seed,
    or `name` when the user gave one."""
    task_dir = Path(out_dir) / config["task"]
    if name is not None:
        if not RUN_NAME_PATTERN.fullmatch(name) or name in (".", ".."):
            raise SettingError(
                f"--name: expected letters, digits and ._=+- (at most 128, no '/'), found {name!r}"
            )
        return task_dir / name
    learner = str(config["learner"]).replace(":", "-")
    eta = f"-eta{config['eta']:g}" if config["data"] != "source" else ""
    mixing = "-union" if config.get("mixing") == "union" else ""
    identity = run_identity(config)[:8]
    return task_dir / f"{learner}-{config['data']}{eta}{mixing}-{identity}-seed{config['seed']}"


def data_identity(config: dict[str, Any]) -> dict[str, Any]:
    """What a run trained on, as scores.json records it."""
    keys = ("source_id", "source_sha256", "artifact_path", "artifact_checksum", "artifact_seed")
    return {
        **{key: config.get(key) for key in keys},
        "eta": config["eta"],
        "mixing": config["mixing"],
        "artifact_hyper_parameters": config.get("artifact_hyper_parameters"),
    }


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    save_torch_atomic(path, state)


def load_checkpoint(path: Path) -> dict[str, Any]:
    return load_torch(path, "a checkpoint written by `hipode train` (delete it or pass --force)")


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
    result.finished_utc = utc_now()
    result.cpu = cpu_name()
    result.load_average = [round(x, 2) for x in os.getloadavg()]
    write_json_atomic(Path(result.run_dir) / "scores.json", result.to_dict())
    return result


def differing_settings(run_dir: Path, expected: dict[str, Any]) -> list[str]:
    """The keys of `expected` whose value differs from the run folder's config.json."""
    config_path = run_dir / "config.json"
    previous = read_run_json(config_path) if config_path.is_file() else {}
    return [
        key
        for key, value in expected.items()
        if previous.get(key) != json.loads(json.dumps(value, default=str))
    ]


def read_run_json(path: Path) -> dict[str, Any]:
    """A run folder's JSON record (config.json, scores.json); unreadable content is refused."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise OverwriteError(
            f"{path}: expected a JSON object written by `hipode train`, found unreadable "
            f"content ({error}); pass --force to train again"
        ) from None
    if not isinstance(data, dict):
        raise OverwriteError(f"{path}: expected a JSON object, found {type(data).__name__}")
    return data


def scores_if_finished(run_dir: Path, steps: int) -> dict[str, Any] | None:
    """scores.json of a run finished to at least `steps` updates; None if unfinished or absent."""
    scores_path = run_dir / "scores.json"
    if not scores_path.is_file():
        return None
    scores = read_run_json(scores_path)
    return scores if scores.get("steps", 0) >= steps else None


def finished_scores(run_dir: Path, steps: int, expected: dict[str, Any]) -> dict[str, Any] | None:
    """scores.json of a run in `run_dir` finished to at least `steps` updates; None if there is
    none yet. Read-only; a finished run whose settings differ from `expected` is refused."""
    scores = scores_if_finished(run_dir, steps)
    if scores is None:
        return None  # unfinished at this budget: run_training continues it
    differing = differing_settings(run_dir, expected)
    if differing:
        raise OverwriteError(
            f"{run_dir}: holds a finished run with other settings ({', '.join(differing)} "
            "differ); pass --force to train it again or --out for another folder"
        )
    return scores


def check_run_dir(
    run_dir: Path, config: dict[str, Any], steps: int, force: bool
) -> tuple[str, dict[str, Any] | None]:
    """What to do with `run_dir`, without touching it: "fresh", "resume", "finished" (with its
    scores) or "replace" (--force over an existing folder). A folder of another experiment is
    refused."""
    if run_dir.exists() and not run_dir.is_dir():
        raise OverwriteError(f"{run_dir}: expected a run folder, found a file; remove it first")
    if force:
        return ("replace" if run_dir.exists() else "fresh"), None
    if not (run_dir / "config.json").is_file():
        return "fresh", None
    # the seed and the evaluation schedule must match too: a resumed or finished run keeps its own
    checked = (*IDENTITY_KEYS, "seed", "eval_every", "eval_episodes", "eval_max_episode_steps")
    differing = differing_settings(run_dir, {key: config[key] for key in checked if key in config})
    if differing:
        raise OverwriteError(
            f"{run_dir} holds a run with other settings ({', '.join(differing)} differ); "
            "pass --force to replace it, or --name / --out for another folder"
        )
    scores = scores_if_finished(run_dir, steps)
    return ("finished", scores) if scores is not None else ("resume", None)


def open_run_dir(run_dir: Path, state: str) -> dict[str, Any] | None:
    """Carry out `check_run_dir`'s decision; return the checkpoint to resume from, if any."""
    if state == "replace":
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_path = run_dir / "checkpoint.pt"
    if state == "resume" and checkpoint_path.is_file():
        return load_checkpoint(checkpoint_path)
    return None


def truncate_metrics(path: Path, step: int) -> None:
    """Drop metric lines written after the checkpoint we resume from (they will be rewritten)."""
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except ValueError:
            continue  # a line torn by a kill mid-write: it is rewritten after the resume
        if isinstance(record, dict) and isinstance(record.get("step"), int):
            if record["step"] <= step:
                kept.append(line)
    write_text_atomic(path, "".join(line + "\n" for line in kept))


SCORE_COLUMNS = [
    "task",
    "learner",
    "seed",
    "steps",
    "score",
    "return",
    "best (optimistic)",
    "upd/s",
]
SCORE_TITLE = (
    "Last evaluation: D4RL-normalized score ± std over evaluation episodes (one seed); "
    "best over all evaluations apart"
)


def score_table_rows(result: TrainResult) -> list[list[Any]]:
    """One row: the last evaluation is the result; the best one is shown apart, labelled."""
    last, best = result.last, result.best or {}
    best_score = best.get("score_mean")
    return [
        [
            result.task,
            f"{result.learner} ({result.data}, η={result.eta:g})",
            "" if result.seed is None else result.seed,
            result.steps,
            _pm(last.get("score_mean"), last.get("score_std"), "{:.1f}"),
            _pm(last.get("return_mean"), last.get("return_std"), "{:.0f}"),
            "n/a" if best_score is None else f"{best_score:.1f} @ {best.get('step')}",
            f"{result.updates_per_second:.0f}",
        ]
    ]


def seeds_summary(results: list[TrainResult]) -> str:
    """The last scores of several seeds of one setting: mean, standard error and range."""
    scores = [r.last.get("score_mean") for r in results]
    if any(score is None for score in scores):
        return f"{len(results)} seeds (no reference returns: see the return column)"
    mean = sum(scores) / len(scores)
    sem = (sum((s - mean) ** 2 for s in scores) / (len(scores) - 1) / len(scores)) ** 0.5
    return (
        f"last score over {len(scores)} seeds: mean {mean:.1f}, standard error {sem:.1f} "
        f"(min {min(scores):.1f}, max {max(scores):.1f})"
    )


def _pm(mean: float | None, std: float | None, fmt: str) -> str:
    return "n/a" if mean is None else f"{fmt.format(mean)} ± {fmt.format(std or 0.0)}"
