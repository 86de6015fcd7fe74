"""What is in the local dataset root: Minari datasets, synthetic artifacts and loose D4RL files.

Only metadata is read (metadata.json, file sizes, HDF5 attributes and shapes), never arrays, so
listing stays fast however large the datasets are.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import h5py

from hipode_pipeline.data.d4rl_source import MANIFEST_ATTR, float_or_none
from hipode_pipeline.data.load import HDF5_SUFFIXES, task_for_env, task_from_file_name
from hipode_pipeline.data.minari_source import METADATA_FILE, env_id_of, ref_scores_of
from hipode_pipeline.envs import canonical_env_id
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.paths import datasets_root
from hipode_pipeline.tasks import Task
from hipode_pipeline.validation import path_problem

ARTIFACTS_DIR = "artifacts"
# Folders of the root that hold no source datasets (generator caches, run outputs)
SKIPPED_DIRS = {"cache", "runs"}
# Minari ids have at most namespace/env/name; deeper folders are not datasets
MAX_ID_DEPTH = 3
# what reading a foreign HDF5 file's header can raise (h5py maps damage to several types);
# one such file gets a note and never stops the listing
UNREADABLE = (
    OSError,
    DataFormatError,
    ValueError,
    TypeError,
    KeyError,
    RuntimeError,
    RecursionError,
)


@dataclass(frozen=True)
class LocalDataset:
    """One dataset or artifact found under the dataset root."""

    id: str  # Minari id, or the file's path relative to the root
    kind: str  # "minari" | "artifact" | "d4rl-hdf5"
    env_id: str | None  # gymnasium id when the metadata names one
    transitions: int | None  # N (Minari total_steps, or rows of a file); None when unknown
    episodes: int | None  # Minari total_episodes; None for flat files
    has_ref_scores: bool  # the data itself carries ref_min_score and ref_max_score
    ref_scores_from: str | None  # "dataset" | "registry" | None: where a loader takes the refs from
    size_bytes: int  # bytes on disk (all files of a Minari dataset)
    path: str  # folder or file, relative to the root
    note: str | None = None  # why some fields are unknown (unreadable metadata, ...)
    task: str | None = None  # artifacts: the task named in the manifest
    schema_version: str | None = None  # artifacts: the manifest's schema version

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def list_local_datasets(root: Path | None = None) -> list[LocalDataset]:
    """Every Minari dataset (`<ns>/<env>/<name>-vN/data/metadata.json`), every artifact under
    `<root>/artifacts/` and every other .hdf5/.h5 file under the root, sorted by kind and id."""
    root = (root or datasets_root()).resolve()
    if not root.is_dir():
        return []
    found: list[LocalDataset] = []
    for folder in _minari_dataset_dirs(root):
        found.append(_describe_minari(root, folder))
    for file in _hdf5_files(root):
        is_artifact = file.relative_to(root).parts[0] == ARTIFACTS_DIR
        found.append(_describe_file(root, file, "artifact" if is_artifact else "d4rl-hdf5"))
    order = {"minari": 0, "d4rl-hdf5": 1, "artifact": 2}
    return sorted(found, key=lambda d: (order[d.kind], d.id))


def _minari_dataset_dirs(root: Path) -> list[Path]:
    """Folders up to MAX_ID_DEPTH below the root that hold `data/metadata.json`."""
    dirs, frontier = [], [root]
    for _ in range(MAX_ID_DEPTH):
        children = []
        for parent in frontier:
            try:
                listing = sorted(parent.iterdir())
            except OSError:
                continue  # an unreadable folder holds nothing we can list
            for child in listing:
                if not child.is_dir() or _skipped(root, child):
                    continue
                if (child / "data" / METADATA_FILE).is_file():
                    dirs.append(child)
                else:
                    children.append(child)
        frontier = children
    return dirs


def _hdf5_files(root: Path) -> list[Path]:
    """HDF5 files under the root, not descending into Minari datasets or skipped folders."""
    files = []
    for folder, subdirs, names in os.walk(root):
        here = Path(folder)
        # prune in place so os.walk never enters caches, hidden folders or Minari datasets
        subdirs[:] = sorted(
            d
            for d in subdirs
            if not _skipped(root, here / d) and not (here / d / "data" / METADATA_FILE).is_file()
        )
        # by suffix only: sidecars (*.summary.json, *.verify.json, *.sha256) are never listed
        files += [
            here / name for name in sorted(names) if Path(name).suffix.lower() in HDF5_SUFFIXES
        ]
    return files


def _skipped(root: Path, path: Path) -> bool:
    parts = path.relative_to(root).parts
    return parts[0] in SKIPPED_DIRS or any(part.startswith(".") for part in parts)


def _describe_minari(root: Path, folder: Path) -> LocalDataset:
    dataset_id = folder.relative_to(root).as_posix()
    size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    try:
        metadata = json.loads((folder / "data" / METADATA_FILE).read_text())
        if not isinstance(metadata, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError, RecursionError) as error:
        return LocalDataset(
            dataset_id,
            "minari",
            None,
            None,
            None,
            False,
            None,
            size,
            dataset_id,
            f"unreadable metadata ({error})",
        )
    env_id = _runnable(env_id_of(metadata))
    has_refs = ref_scores_of(metadata) != (None, None)
    return LocalDataset(
        id=dataset_id,
        kind="minari",
        env_id=env_id,
        transitions=_int_or_none(metadata.get("total_steps")),
        episodes=_int_or_none(metadata.get("total_episodes")),
        has_ref_scores=has_refs,
        ref_scores_from=_refs_from(has_refs, task_for_env(env_id) if env_id else None),
        size_bytes=size,
        path=dataset_id,
    )


def _describe_file(root: Path, file: Path, kind: str) -> LocalDataset:
    relative = file.relative_to(root).as_posix()
    problem = path_problem(file)
    if problem is not None:
        # listed but never opened: a FIFO would block the listing, a link loop would fail it
        entry = LocalDataset(relative, kind, None, None, None, False, None, 0, relative)
        return replace(entry, note=f"not read: {problem}")
    size = file.stat().st_size
    if kind == "artifact":
        described = _describe_artifact(file, relative, size)
        if described is not None:
            return described
    try:
        env_id, rows, has_refs = _file_header(file)
        note = None
    except UNREADABLE as error:
        env_id, rows, has_refs, note = None, None, False, f"unreadable ({error})"
    return _file_entry(file, relative, kind, size, env_id, rows, has_refs, note=note)


def _describe_artifact(file: Path, relative: str, size: int) -> LocalDataset | None:
    """From the manifest and the observations' shape only (no arrays are read); None when the
    manifest is not an artifact's, so the entry is described like any other HDF5 file."""
    from hipode_pipeline.artifact import read_manifest

    try:
        manifest = read_manifest(file)
        with h5py.File(file, "r") as f:
            observations = f.get("observations")
            rows = int(observations.shape[0]) if isinstance(observations, h5py.Dataset) else None
    except UNREADABLE:
        return None
    task_name = manifest.get("task") if isinstance(manifest.get("task"), str) else None
    env_id = manifest.get("env_id") if isinstance(manifest.get("env_id"), str) else None
    has_refs = (
        float_or_none(manifest.get("ref_min_score")) is not None
        and float_or_none(manifest.get("ref_max_score")) is not None
    )
    return _file_entry(
        file,
        relative,
        "artifact",
        size,
        env_id,
        rows,
        has_refs,
        task=task_name,
        schema_version=(manifest.get("schema") or {}).get("version"),
    )


def _file_entry(
    file: Path,
    relative: str,
    kind: str,
    size: int,
    env_id: str | None,
    rows: int | None,
    has_refs: bool,
    **extra: Any,
) -> LocalDataset:
    """A flat file's entry; env id and refs fall back to the task its env or name points to."""
    env_id = _runnable(env_id)
    task = task_for_env(env_id) if env_id else task_from_file_name(file)
    return LocalDataset(
        id=relative,
        kind=kind,
        env_id=env_id or (task.env_id if task else None),
        transitions=rows,
        episodes=None,
        has_ref_scores=has_refs,
        ref_scores_from=_refs_from(has_refs, task),
        size_bytes=size,
        path=relative,
        **extra,
    )


def _runnable(env_id: str | None) -> str | None:
    """The env a loader runs for `env_id` (Hopper-v2 -> Hopper-v5), so the list matches `show`."""
    return canonical_env_id(env_id)[0] if env_id else None


def _refs_from(has_refs: bool, task: Task | None) -> str | None:
    """Where a loader takes the reference scores from: the data, the registry, or nowhere."""
    return "dataset" if has_refs else ("registry" if task else None)


def _file_header(file: Path) -> tuple[str | None, int | None, bool]:
    """Env id, row count and whether refs are present, from attributes and shapes only."""
    with h5py.File(file, "r") as f:
        attrs: dict[str, Any] = dict(f.attrs)
        manifest = attrs.get(MANIFEST_ATTR)
        if isinstance(manifest, bytes | str):
            manifest = json.loads(manifest)
        source = manifest if isinstance(manifest, dict) else attrs
        env_id = source.get("env_id") or source.get("env")
        env_id = env_id.decode() if isinstance(env_id, bytes) else env_id
        has_refs = (
            float_or_none(source.get("ref_min_score")) is not None
            and float_or_none(source.get("ref_max_score")) is not None
        )
        observations = f.get("observations")
        rows = (
            int(observations.shape[0])
            if isinstance(observations, h5py.Dataset) and observations.ndim
            else None
        )
    return (env_id if isinstance(env_id, str) else None), rows, has_refs


def _int_or_none(value: Any) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None
