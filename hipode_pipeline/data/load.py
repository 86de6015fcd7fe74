"""One entry point for every source: a task name, a local Minari id, or a D4RL-format file.

The loaders report what the data itself says; here an env id is mapped to the env we run
(hopper-medium-replay-v2, Hopper-v2 -> Hopper-v5) or refused, missing reference scores (and a
missing env id) are completed from the task registry, and SourceInfo.metadata records where
they came from.

A spec the user typed may be any path; a spec read from a file (an artifact's `source.id`) is
data: `load_recorded_source` resolves it only inside the dataset root.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

from hipode_pipeline import console
from hipode_pipeline.data.d4rl_source import (
    DEFAULT_MAX_EPISODE_STEPS,
    ENV_ID_KEYS,
    load_d4rl_hdf5,
)
from hipode_pipeline.data.d4rl_source import env_id_entry as file_env_id_entry
from hipode_pipeline.data.minari_source import (
    METADATA_FILE,
    dataset_dir,
    has_local_dataset,
    is_dataset_id,
    load_minari,
)
from hipode_pipeline.data.minari_source import env_id_entry as minari_env_id_entry
from hipode_pipeline.data.transitions import SourceInfo, Transitions
from hipode_pipeline.envs import canonical_env_id
from hipode_pipeline.errors import DataFormatError, DatasetNotFoundError, UnknownTaskError
from hipode_pipeline.paths import datasets_root
from hipode_pipeline.tasks import Task, all_tasks, get_task
from hipode_pipeline.validation import path_problem

HDF5_SUFFIXES = (".hdf5", ".h5")
# Prefixes of gymnasium ids whose family is the rest of the name (AdroitHandPen -> pen)
ENV_FAMILY_PREFIXES = ("adroithand",)
# Notes already printed in this process, so a source loaded again does not repeat them
_ANNOUNCED: set[tuple[str, str]] = set()


def load_source(
    spec: str, root: Path | None = None, *, task: Task | None = None, announce: bool = True
) -> tuple[Transitions, SourceInfo]:
    """Load a source dataset as flat Transitions plus its SourceInfo.

    `spec` is a path to a D4RL-format .hdf5/.h5 file, a Minari id in the local store
    (`root`, default $MINARI_DATASETS_PATH or ./datasets), or a registered task name, which
    stands for the task's collected dataset (`Task.local_dataset_id`).
    The env id is mapped to the env we run (`canonical_env_id`); the original stays in
    metadata["env_id_original"] and a note, printed to stderr once unless not `announce`.
    `task` is the task the data is for (implied by a task name): a source of another env family
    is refused.
    Raises DatasetNotFoundError when nothing local matches and DataFormatError for a bad file,
    an env id we cannot run, or an env family other than `task`'s.
    """
    root = (root or datasets_root()).resolve()
    spec = spec.strip()
    if spec.lower().endswith(HDF5_SUFFIXES):
        path = _find_file(spec, root)
        transitions, info = load_d4rl_hdf5(path, max_episode_steps=DEFAULT_MAX_EPISODE_STEPS)
        info = dataclasses.replace(info, id=spec)
        hint = task or task_from_file_name(path)
        return transitions, _finish(info, path, hint, task, announce)
    if has_local_dataset(spec, root):
        transitions, info = load_minari(spec, root)
        origin = dataset_dir(spec, root) / "data" / METADATA_FILE
        return transitions, _finish(info, origin, task, task, announce)
    if "/" not in spec:
        named = _task_or_not_found(spec, root)
        dataset_id = named.local_dataset_id
        if not has_local_dataset(dataset_id, root):
            build = (
                f"run `hipode collect {named.name}` to build it"
                if named.collectable
                else f"download it where the internet is reachable (`minari download "
                f"{dataset_id}`) and copy its folder into the store"
            )
            raise DatasetNotFoundError(
                f"task {named.name}'s dataset {dataset_id} is not in the local store "
                f"(looked for {dataset_dir(dataset_id, root) / 'data' / 'metadata.json'}); "
                f"{build}, or pass a Minari id or a D4RL .hdf5 file"
            )
        transitions, info = load_minari(dataset_id, root)
        origin = dataset_dir(dataset_id, root) / "data" / METADATA_FILE
        return transitions, _finish(info, origin, named, task or named, announce)
    if not is_dataset_id(spec):
        raise DatasetNotFoundError(
            f"'{spec}' is not a Minari id (namespace/env/name-vN), a registered task or a .hdf5 "
            f"path; local datasets live in {root}"
        )
    # not in the store: load_minari says where it looked and what to do
    return load_minari(spec, root)


def _finish(
    info: SourceInfo,
    origin: Path,
    hint: Task | None,
    task: Task | None,
    announce: bool,
) -> SourceInfo:
    """Map and check the env id, complete from the registry, check the family, print notes."""
    field = env_id_field(info)
    info, note = resolve_env_id(info, origin, field)
    info = complete_from_registry(info, hint)
    if task is not None:
        check_task_family(info, task, origin, field)
    if announce and note and (str(origin), note) not in _ANNOUNCED:
        _ANNOUNCED.add((str(origin), note))
        console.err.print(f"note: {note}", highlight=False)
    return info


def env_id_field(info: SourceInfo) -> str:
    """The field the source's env id was read from: env, env_id, manifest.env_id, env_spec.id."""
    if info.format == "minari":
        entry = minari_env_id_entry(info.metadata)
    else:
        entry = file_env_id_entry(info.metadata.get("file_metadata") or {})
    # no id in the data: a file would name it in one of these attributes
    return entry[0] if entry else " / ".join(ENV_ID_KEYS)


def expected_env_ids() -> str:
    """What an env id in data may be, for error messages."""
    registered = ", ".join(dict.fromkeys(t.env_id for t in all_tasks().values()))
    return (
        f"an env we can run: one of {registered}, another env registered by gymnasium itself, "
        "an older Hopper/Walker2d/HalfCheetah version (-v2..-v4) "
        "or a D4RL dataset name such as hopper-medium-replay-v2 or pen-human-v1"
    )


def resolve_env_id(
    info: SourceInfo, origin: str | Path, field: str
) -> tuple[SourceInfo, str | None]:
    """`info` with its env id mapped to the env we run, and the note saying so (None: unchanged).

    The original id is kept in metadata["env_id_original"], the note in metadata["notes"]. An id
    that is neither mappable nor a registered gymnasium env raises DataFormatError naming
    `origin` and `field`.
    """
    if info.env_id is None:
        return info, None
    env_id, note = canonical_env_id(info.env_id)
    if env_id not in {t.env_id for t in all_tasks().values()}:
        # lazily: the simulator module imports mujoco, which loading data does not need
        from hipode_pipeline.simulator import check_env_id

        try:
            check_env_id(env_id, origin)
        except DataFormatError as error:
            raise DataFormatError(origin, field, expected_env_ids(), error.found) from None
    if note is None:
        return info, None
    notes = [*info.metadata.get("notes", []), note]
    metadata = {**info.metadata, "env_id_original": info.env_id, "notes": notes}
    return dataclasses.replace(info, env_id=env_id, metadata=metadata), note


def check_task_family(info: SourceInfo, task: Task, origin: str | Path, field: str) -> None:
    """Refuse a source whose env is of another family than `task`'s (walker2d data for hopper)."""
    if info.env_id is None or registry_family(info.env_id) == task.env:
        return
    original = info.metadata.get("env_id_original")
    found = info.env_id if original is None else f"{original!r} (read as {info.env_id})"
    raise DataFormatError(
        origin, field, f"an env of task {task.name}'s family {task.env} ({task.env_id})", found
    )


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
    # the caller prints the notes, the env id's among them
    transitions, info = load_source(spec, root, announce=False)
    episode_returns = transitions.episode_returns()
    return {
        "id": info.id,
        "format": info.format,
        "env_id": info.env_id,
        "env_id_original": info.metadata.get("env_id_original"),
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


def load_recorded_source(
    spec: object,
    root: Path,
    *,
    origin: str | Path,
    field: str,
    task: Task | None = None,
    announce: bool = True,
) -> tuple[Transitions, SourceInfo]:
    """Load a source named by a file's content (e.g. a manifest's `source.id`): a Minari id, a
    task name or a .hdf5 path, resolved only inside `root` (never the working directory).
    Anything else, or anything that resolves outside the root (an absolute path elsewhere,
    `../`, a symlink out of the root), is a DataFormatError naming `origin` and `field`."""
    root = Path(root).resolve()
    expected = (
        f"a source inside the dataset root {root}: a Minari id, a task name or a .hdf5 path "
        "relative to the root (put the source there, or rebuild the artifact from one there)"
    )
    if not isinstance(spec, str) or not spec.strip():
        raise DataFormatError(origin, field, expected, repr(spec))
    spec = spec.strip()
    if spec.lower().endswith(HDF5_SUFFIXES):
        candidate = Path(spec) if Path(spec).is_absolute() else root / spec
        inside = _inside(candidate, root)
        if inside is None:
            raise DataFormatError(origin, field, expected, f"{spec!r}, outside the root")
        transitions, info = load_source(str(inside), root, task=task, announce=announce)
        return transitions, dataclasses.replace(info, id=spec)
    if "/" not in spec and not has_local_dataset(spec, root):
        try:
            dataset_id = get_task(spec).local_dataset_id
        except UnknownTaskError:
            raise DataFormatError(origin, field, expected, repr(spec)) from None
    else:
        dataset_id = spec
    if not is_dataset_id(dataset_id) or _inside(dataset_dir(dataset_id, root), root) is None:
        raise DataFormatError(origin, field, expected, f"{spec!r}, outside the root")
    return load_source(spec, root, task=task, announce=announce)


def _inside(path: Path, root: Path) -> Path | None:
    """`path` with every symlink resolved, when that stays inside `root`; else None."""
    try:
        resolved = path.resolve()
    except (OSError, RuntimeError):
        # a symlink loop cannot be resolved: whatever it is, it is not a file inside the root
        return None
    return resolved if resolved.is_relative_to(root) else None


def _find_file(spec: str, root: Path) -> Path:
    """The file as given (relative to the working directory), else relative to the dataset root.
    A directory, FIFO or symlink loop there is named as such."""
    for candidate in (Path(spec).expanduser(), root / spec):
        problem = path_problem(candidate)
        if problem is None:
            return candidate
        if problem != "nothing at that path":
            raise DataFormatError(
                candidate, "file", "a D4RL-format .hdf5 file (a regular file)", problem
            )
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
