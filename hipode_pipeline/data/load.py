"""One entry point for every source: a task name, a local Minari id, or a D4RL-format file.

The loaders report what the data itself says; here missing reference scores (and a missing env
id) are completed from the task registry, and SourceInfo.metadata records where they came from.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

from hipode_pipeline.data.d4rl_source import DEFAULT_MAX_EPISODE_STEPS, load_d4rl_hdf5
from hipode_pipeline.data.minari_source import (
    dataset_dir,
    has_local_dataset,
    is_dataset_id,
    load_minari,
)
from hipode_pipeline.data.transitions import SourceInfo, Transitions
from hipode_pipeline.errors import DatasetNotFoundError, UnknownTaskError
from hipode_pipeline.paths import datasets_root
from hipode_pipeline.tasks import Task, all_tasks, get_task

HDF5_SUFFIXES = (".hdf5", ".h5")
# Prefixes of gymnasium ids whose family is the rest of the name (AdroitHandPen -> pen)
ENV_FAMILY_PREFIXES = ("adroithand",)


def load_source(spec: str, root: Path | None = None) -> tuple[Transitions, SourceInfo]:
    """Load a source dataset as flat Transitions plus its SourceInfo.

    `spec` is a path to a D4RL-format .hdf5/.h5 file, a Minari id in the local store
    (`root`, default $MINARI_DATASETS_PATH or ./datasets), or a registered task name, which
    stands for the task's collected dataset (`Task.local_dataset_id`).
    Raises DatasetNotFoundError when nothing local matches and DataFormatError for a bad file.
    """
    root = (root or datasets_root()).resolve()
    spec = spec.strip()
    if spec.lower().endswith(HDF5_SUFFIXES):
        path = _find_file(spec, root)
        transitions, info = load_d4rl_hdf5(path, max_episode_steps=DEFAULT_MAX_EPISODE_STEPS)
        info = dataclasses.replace(info, id=spec)
        return transitions, complete_from_registry(info, task_from_file_name(path))
    if has_local_dataset(spec, root):
        transitions, info = load_minari(spec, root)
        return transitions, complete_from_registry(info, None)
    if "/" not in spec:
        task = _task_or_not_found(spec, root)
        dataset_id = task.local_dataset_id
        if not has_local_dataset(dataset_id, root):
            raise DatasetNotFoundError(
                f"task {task.name}'s dataset {dataset_id} is not in the local store "
                f"(looked for {dataset_dir(dataset_id, root) / 'data' / 'metadata.json'}); "
                f"run `hipode collect {task.name}` to build it, "
                "or pass a Minari id or a D4RL .hdf5 file"
            )
        transitions, info = load_minari(dataset_id, root)
        return transitions, complete_from_registry(info, task)
    if not is_dataset_id(spec):
        raise DatasetNotFoundError(
            f"'{spec}' is not a Minari id (namespace/env/name-vN), a registered task or a .hdf5 "
            f"path; local datasets live in {root}"
        )
    # not in the store: load_minari says where it looked and what to do
    return load_minari(spec, root)


def complete_from_registry(info: SourceInfo, task: Task | None) -> SourceInfo:
    """Fill missing ref scores (and env id) from the registry: by env id first, else by `task`.

    metadata["ref_scores_from"] is "dataset", "registry" or None.
    """
    notes = list(info.metadata.get("notes", []))
    if info.ref_min_score is not None and info.ref_max_score is not None:
        return dataclasses.replace(info, metadata={**info.metadata, "ref_scores_from": "dataset"})
    match = task_for_env(info.env_id) if info.env_id else None
    if (
        match is None
        and task is not None
        and (info.env_id is None or registry_family(info.env_id) == task.env)
    ):
        match = task
    if match is None:
        notes.append(
            f"no reference scores: none in the data and no registered task for env {info.env_id!r}"
        )
        return dataclasses.replace(
            info, metadata={**info.metadata, "ref_scores_from": None, "notes": notes}
        )
    env_id = info.env_id
    if env_id is None:
        env_id = match.env_id
        notes.append(f"env id {env_id} from the task registry ({match.name})")
    return dataclasses.replace(
        info,
        env_id=env_id,
        ref_min_score=match.ref_min_score,
        ref_max_score=match.ref_max_score,
        metadata={
            **info.metadata,
            "ref_scores_from": "registry",
            "registry_task": match.name,
            "notes": notes,
        },
    )


def registry_family(env_id: str) -> str:
    """The env family of a gymnasium or D4RL id: Hopper-v5 and hopper-medium-v2 -> hopper."""
    name = re.sub(r"-v\d+$", "", env_id.strip()).lower()
    name = name.split("-")[0]
    for prefix in ENV_FAMILY_PREFIXES:
        name = name.removeprefix(prefix)
    return name


def task_for_env(env_id: str) -> Task | None:
    """The first registered task whose env id is `env_id`, else of the same family (Hopper-v2)."""
    tasks = list(all_tasks().values())
    exact = [t for t in tasks if t.env_id == env_id]
    if exact:
        return exact[0]
    family = registry_family(env_id)
    return next((t for t in tasks if t.env == family), None)


def task_from_file_name(path: str | Path) -> Task | None:
    """The task a D4RL file name stands for: hopper_medium_replay-v0.hdf5 -> hopper-m-r."""
    stem = Path(path).name
    for suffix in HDF5_SUFFIXES:
        stem = stem.removesuffix(suffix).removesuffix(suffix.upper())
    name = re.sub(r"-v\d+$", "", stem.replace("_", "-"))
    try:
        return get_task(name)
    except UnknownTaskError:
        return None


def describe_source(spec: str, root: Path | None = None) -> dict[str, Any]:
    """Load a source and summarize it: size, dims, env, refs, checksum, episodes, flags, returns."""
    transitions, info = load_source(spec, root)
    episode_returns = transitions.episode_returns()
    return {
        "id": info.id,
        "format": info.format,
        "env_id": info.env_id,
        "n": info.n,
        "obs_dim": transitions.obs_dim,
        "act_dim": transitions.act_dim,
        "episodes": int(episode_returns.size),
        "terminals": int(transitions.terminals.sum()),
        "timeouts": int(transitions.timeouts.sum()),
        "ref_min_score": info.ref_min_score,
        "ref_max_score": info.ref_max_score,
        "ref_scores_from": info.metadata.get("ref_scores_from"),
        "mean_episode_return": float(episode_returns.mean()),
        "sha256": info.sha256,
        "notes": info.metadata.get("notes", []),
    }


def _find_file(spec: str, root: Path) -> Path:
    """The file as given (relative to the working directory), else relative to the dataset root."""
    for candidate in (Path(spec).expanduser(), root / spec):
        if candidate.is_file():
            return candidate
    raise DatasetNotFoundError(
        f"no file {spec} (looked in the working directory and in {root}); "
        "give the path of a D4RL-format .hdf5 file that exists here"
    )


def _task_or_not_found(spec: str, root: Path) -> Task:
    try:
        return get_task(spec)
    except UnknownTaskError as error:
        raise DatasetNotFoundError(
            f"no dataset '{spec}': not a .hdf5 file, not a Minari dataset in {root}, and {error}"
        ) from None
