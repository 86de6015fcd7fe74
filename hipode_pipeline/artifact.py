"""The synthetic dataset file: schema, checksum, atomic writer and a reader that trusts nothing.

One flat HDF5 file with D4RL key names (observations, actions, rewards, next_observations,
terminals, timeouts), per-transition diagnostics beside them, and a JSON manifest in the root
attribute `manifest`. Only numeric datasets: no pickle, nothing in the file is executed.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hipode_pipeline.data.transitions import FIELDS, Transitions
from hipode_pipeline.errors import DataFormatError, DatasetNotFoundError, OverwriteError
from hipode_pipeline.paths import datasets_root
from hipode_pipeline.tasks import get_task

SCHEMA_NAME = "hipode-synthetic"
SCHEMA_VERSION = "1.0"
MANIFEST_ATTR = "manifest"
# diagnostics every artifact carries, with their dtypes; writers may add more (float32 or int64)
REQUIRED_DIAGNOSTICS = {"dynamics_error": np.float32, "value": np.float32, "source_index": np.int64}
DIAGNOSTIC_DTYPES = (np.dtype(np.float32), np.dtype(np.int64))
TRANSITION_DTYPES = {
    "observations": np.float32,
    "actions": np.float32,
    "rewards": np.float32,
    "next_observations": np.float32,
    "terminals": np.bool_,
    "timeouts": np.bool_,
}


@dataclass(frozen=True, eq=False)
class Artifact:
    """A synthetic dataset file read back and verified."""

    path: Path  # the file it was read from
    transitions: Transitions  # the M synthetic transitions, raw (un-normalized) values
    diagnostics: dict[str, np.ndarray]  # per-transition (M,) arrays: dynamics_error, value, ...
    manifest: dict[
        str, Any
    ]  # provenance: schema, source, hyper-parameters, seeds, versions, counts

    def __len__(self) -> int:
        return len(self.transitions)


def default_artifact_path(
    task_name: str, *, learner: str = "td3bc", seed: int = 0, root: Path | None = None
) -> Path:
    """Where `hipode augment TASK` writes by default:
    <dataset root>/artifacts/<task>-<learner>-seed<seed>.hdf5."""
    task = get_task(task_name)
    return (root or datasets_root()) / "artifacts" / f"{task.name}-{learner}-seed{seed}.hdf5"


def content_checksum(arrays: dict[str, np.ndarray]) -> str:
    """sha256 over each dataset's name, dtype, shape and bytes: transition fields in D4RL order,
    then diagnostics by name. The manifest is left out (it holds this checksum)."""
    digest = hashlib.sha256()
    names = [*FIELDS, *sorted(name for name in arrays if name not in FIELDS)]
    for name in names:
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
        digest.update(array.data)
    return "sha256:" + digest.hexdigest()


def file_sha256(path: Path) -> str:
    """sha256 of the file's bytes (what a user compares after copying it)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def write_artifact(
    path: Path,
    transitions: Transitions,
    diagnostics: dict[str, np.ndarray],
    manifest: dict[str, Any],
    *,
    force: bool = False,
) -> dict[str, Any]:
    """Write the artifact atomically and return the manifest as stored (schema and checksum added).

    Refuses an existing `path` unless `force`. The file appears only once complete: it is
    written to a temporary file in the same folder and renamed over `path`.
    """
    path = Path(path)
    if path.exists() and not force:
        raise OverwriteError(f"{path} already exists; pass --force to replace it")
    arrays = {**transitions.arrays(), **_checked_diagnostics(diagnostics, len(transitions), path)}
    stored = {
        **manifest,
        "schema": {"name": SCHEMA_NAME, "version": SCHEMA_VERSION},
        "checksum": content_checksum(arrays),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(handle)
    try:
        with h5py.File(temp_name, "w") as f:
            for name, array in arrays.items():
                f.create_dataset(name, data=array)
            f.attrs[MANIFEST_ATTR] = json.dumps(stored, sort_keys=True, default=_json_default)
        os.replace(temp_name, path)
    except BaseException:
        Path(temp_name).unlink(missing_ok=True)
        raise
    return stored


def read_manifest(path: Path) -> dict[str, Any]:
    """Only the manifest (cheap: no arrays are read), after checking the schema name and version."""
    path = Path(path)
    if not path.is_file():
        raise DatasetNotFoundError(f"{path}: no such artifact file")
    try:
        with h5py.File(path, "r") as f:
            return _parse_manifest(f, path)
    except OSError as error:
        raise DataFormatError(
            path, "file", "a complete HDF5 file", f"unreadable ({error})"
        ) from None


def read_artifact(path: Path) -> Artifact:
    """Read and verify an artifact: schema name and major version, every dataset's presence,
    dtype and shape, finiteness, and the content checksum. Any failure is a DataFormatError
    naming the file, the field and what was expected."""
    path = Path(path)
    if not path.is_file():
        raise DatasetNotFoundError(f"{path}: no such artifact file")
    try:
        with h5py.File(path, "r") as f:
            manifest = _parse_manifest(f, path)
            arrays = {name: _read_dataset(f, name, path) for name in f.keys()}
    except OSError as error:
        # a truncated or overwritten file fails inside HDF5 itself
        raise DataFormatError(
            path, "file", "a complete HDF5 file", f"unreadable ({error})"
        ) from None
    for name in FIELDS:
        if name not in arrays:
            raise DataFormatError(path, name, "a dataset in the file", "nothing (missing)")
    for name in REQUIRED_DIAGNOSTICS:
        if name not in arrays:
            raise DataFormatError(
                path, name, "a diagnostics dataset in the file", "nothing (missing)"
            )
    m, obs_dim = _shape_of(arrays["observations"], path)
    act_dim = arrays["actions"].shape[1] if arrays["actions"].ndim == 2 else None
    expected_shapes = {
        "observations": (m, obs_dim),
        "actions": (m, act_dim),
        "rewards": (m,),
        "next_observations": (m, obs_dim),
        "terminals": (m,),
        "timeouts": (m,),
    }
    for name, array in arrays.items():
        expected_dtype = TRANSITION_DTYPES.get(name) or REQUIRED_DIAGNOSTICS.get(name)
        if expected_dtype is not None and array.dtype != np.dtype(expected_dtype):
            raise DataFormatError(path, name, f"dtype {np.dtype(expected_dtype)}", array.dtype)
        if expected_dtype is None and array.dtype not in DIAGNOSTIC_DTYPES:
            raise DataFormatError(path, name, "a float32 or int64 diagnostics dataset", array.dtype)
        shape = expected_shapes.get(name, (m,))
        if array.shape != shape:
            raise DataFormatError(path, name, f"shape {shape}", array.shape)
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            bad = ~np.isfinite(array)
            first = int(np.argwhere(bad)[0][0])
            raise DataFormatError(
                path, name, "finite values", f"{int(bad.sum())} NaN/inf (first at row {first})"
            )
    checksum = content_checksum(arrays)
    if manifest.get("checksum") != checksum:
        raise DataFormatError(
            path,
            "checksum",
            f"{manifest.get('checksum')} (the manifest's)",
            f"{checksum}: the content was changed or corrupted",
        )
    transitions = Transitions(**{name: arrays[name] for name in FIELDS})
    diagnostics = {name: array for name, array in arrays.items() if name not in FIELDS}
    return Artifact(path=path, transitions=transitions, diagnostics=diagnostics, manifest=manifest)


def _parse_manifest(f: h5py.File, path: Path) -> dict[str, Any]:
    raw = f.attrs.get(MANIFEST_ATTR)
    if raw is None:
        raise DataFormatError(
            path, MANIFEST_ATTR, "a JSON manifest attribute on the file's root", "nothing (missing)"
        )
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8", errors="replace")
    try:
        manifest = json.loads(raw)
    except (TypeError, ValueError) as error:
        raise DataFormatError(
            path, MANIFEST_ATTR, "a JSON object", f"text that is not JSON ({error})"
        ) from None
    if not isinstance(manifest, dict):
        raise DataFormatError(path, MANIFEST_ATTR, "a JSON object", type(manifest).__name__)
    schema = manifest.get("schema") if isinstance(manifest.get("schema"), dict) else {}
    if schema.get("name") != SCHEMA_NAME:
        raise DataFormatError(
            path, "manifest.schema.name", f"'{SCHEMA_NAME}'", repr(schema.get("name"))
        )
    version = str(schema.get("version", ""))
    if version.split(".")[0] != SCHEMA_VERSION.split(".")[0]:
        raise DataFormatError(
            path,
            "manifest.schema.version",
            f"major version {SCHEMA_VERSION.split('.')[0]} (this reader reads {SCHEMA_VERSION}); "
            "rebuild the file with this version's `hipode augment`",
            repr(version),
        )
    return manifest


def _read_dataset(f: h5py.File, name: str, path: Path) -> np.ndarray:
    node = f[name]
    if not isinstance(node, h5py.Dataset):
        raise DataFormatError(path, name, "a dataset", "a group")
    if node.dtype.kind not in "fiub":
        raise DataFormatError(path, name, "a numeric or boolean dataset", node.dtype)
    return node[()]


def _shape_of(observations: np.ndarray, path: Path) -> tuple[int, int]:
    if observations.ndim != 2 or observations.shape[1] == 0:
        raise DataFormatError(path, "observations", "a 2-D array (M, obs_dim)", observations.shape)
    return observations.shape


def _checked_diagnostics(
    diagnostics: dict[str, np.ndarray], m: int, path: Path
) -> dict[str, np.ndarray]:
    """Writer-side check, so a bad diagnostic fails before any file is created."""
    checked = {}
    for name in REQUIRED_DIAGNOSTICS:
        if name not in diagnostics:
            raise ValueError(f"{path}: diagnostics need '{name}'")
    for name, array in diagnostics.items():
        if name in FIELDS or name == MANIFEST_ATTR:
            raise ValueError(f"{path}: diagnostic name '{name}' is reserved")
        array = np.ascontiguousarray(array)
        if array.dtype not in DIAGNOSTIC_DTYPES or array.shape != (m,):
            raise ValueError(
                f"{path}: diagnostic '{name}' must be ({m},) float32 or int64, "
                f"got {array.shape} {array.dtype}"
            )
        checked[name] = array
    return checked


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"manifest value of type {type(value).__name__} is not JSON-able")
