"""The synthetic dataset file: schema, checksum, atomic writer and a reader that trusts nothing.

One flat HDF5 file with D4RL key names (observations, actions, rewards, next_observations,
terminals, timeouts), per-transition diagnostics beside them, and a JSON manifest in the root
attribute `manifest` that carries the content checksum and its own digest. Only numeric
datasets: no pickle, nothing in the file is executed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hipode_pipeline.data.transitions import FIELDS, Transitions
from hipode_pipeline.errors import DataFormatError, OverwriteError
from hipode_pipeline.files import atomic_path, file_sha256
from hipode_pipeline.validation import (  # re-exported: the schema's constants live with its rules
    DIAGNOSTIC_DTYPES,
    MANIFEST_ATTR,
    MANIFEST_CHECKSUM_KEY,
    REQUIRED_DIAGNOSTICS,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    TRANSITION_DTYPES,
    Findings,
    check_file,
    content_checksum,
    manifest_checksum,
    nonfinite_to_null,
    require_regular_file,
    seal_manifest,
)

__all__ = [
    "DIAGNOSTIC_DTYPES",
    "MANIFEST_ATTR",
    "MANIFEST_CHECKSUM_KEY",
    "REQUIRED_DIAGNOSTICS",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "TRANSITION_DTYPES",
    "Artifact",
    "content_checksum",
    "manifest_checksum",
    "read_artifact",
    "read_manifest",
    "seal_manifest",
    "write_artifact",
]


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


def write_artifact(
    path: Path,
    transitions: Transitions,
    diagnostics: dict[str, np.ndarray],
    manifest: dict[str, Any],
    *,
    force: bool = False,
) -> dict[str, Any]:
    """Write the artifact atomically and return the manifest as stored (schema, checksum and
    manifest digest added; values as JSON holds them, a non-finite number as null).

    Refuses an existing `path` unless `force`, and zero transitions. The file appears only once
    complete: it is written to a temporary file in the same folder and renamed over `path`.
    """
    path = Path(path)
    if path.exists() and not force:
        raise OverwriteError(f"{path} already exists; pass --force to replace it")
    if len(transitions) == 0:
        raise DataFormatError(
            path, "observations", "at least one synthetic transition to write", "0 rows"
        )
    arrays = {**transitions.arrays(), **_checked_diagnostics(diagnostics, len(transitions), path)}
    stored = {
        **manifest,
        "schema": {"name": SCHEMA_NAME, "version": SCHEMA_VERSION},
        "checksum": content_checksum(arrays),
    }
    # the digest is over what a reader parses back, so numpy scalars, paths and tuples go first
    as_json = json.loads(json.dumps(stored, sort_keys=True, default=_json_default))
    stored = seal_manifest(nonfinite_to_null(as_json))
    text = json.dumps(stored, sort_keys=True, allow_nan=False)
    with atomic_path(path, replace=force) as temp, h5py.File(temp, "w") as f:
        for name, array in arrays.items():
            f.create_dataset(name, data=array)
        f.attrs[MANIFEST_ATTR] = text
    return stored


def read_manifest(path: Path) -> dict[str, Any]:
    """Only the manifest (cheap: no arrays are read), after checking it: strict JSON, schema
    name and version, key types and its digest. The content checksum needs the arrays: only
    `read_artifact` checks it."""
    path = require_regular_file(path)
    manifest, _ = check_file(path, Findings(path, strict=True), read_arrays=False)
    return manifest


def read_artifact(path: Path) -> Artifact:
    """Read and verify an artifact: schema name and major version, the manifest's types and
    digest, every dataset's presence, dtype and shape, at least one row, finiteness, and the
    content checksum. The first failure is a DataFormatError naming the file, the field and
    what was expected (`validate_artifact` in hipode_pipeline.validation runs the same rules
    and lists them all)."""
    path = require_regular_file(path)
    manifest, arrays = check_file(path, Findings(path, strict=True), read_arrays=True)
    transitions = Transitions(**{name: arrays[name] for name in FIELDS})
    diagnostics = {name: array for name, array in arrays.items() if name not in FIELDS}
    return Artifact(path=path, transitions=transitions, diagnostics=diagnostics, manifest=manifest)


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


# manifest entries `hipode inspect` shows first, in this order
HIGHLIGHT_KEYS = ("schema", "task", "env_id", "created_utc", "checksum", "manifest_checksum")


def inspect_artifact(path: Path) -> dict[str, Any]:
    """Read and verify an artifact, then summarize it: manifest highlights (schema, task, env,
    source, hyper-parameters, seeds, versions, counts) and per-dataset statistics."""
    artifact = read_artifact(path)
    manifest = artifact.manifest
    source = manifest.get("source") if isinstance(manifest.get("source"), dict) else {}
    highlights: dict[str, Any] = {key: manifest.get(key) for key in HIGHLIGHT_KEYS}
    highlights["schema"] = "{name} {version}".format(**manifest["schema"])
    highlights.update(
        {
            "rows": len(artifact),
            "source.id": source.get("id"),
            "source.sha256": source.get("sha256"),
            "source.N": source.get("n"),
        }
    )
    for group in ("hyper_parameters", "seeds", "versions", "counts"):
        values = manifest.get(group)
        if isinstance(values, dict):
            # nested configs are in --json; the table keeps scalars
            highlights.update(
                {f"{group}.{k}": v for k, v in values.items() if not isinstance(v, dict | list)}
            )
    arrays = {**artifact.transitions.arrays(), **artifact.diagnostics}
    statistics = {name: _statistics(array) for name, array in arrays.items()}
    return {
        "path": str(artifact.path),
        "file_sha256": file_sha256(artifact.path),
        "manifest": highlights,
        "statistics": statistics,
        "fractions": {
            "terminals": float(artifact.transitions.terminals.mean()) if len(artifact) else 0.0,
            "timeouts": float(artifact.transitions.timeouts.mean()) if len(artifact) else 0.0,
        },
    }


def _statistics(array: np.ndarray) -> dict[str, Any]:
    values = array.astype(np.float64)
    empty = values.size == 0
    return {
        "shape": list(array.shape),
        "dtype": array.dtype.name,
        "mean": None if empty else float(values.mean()),
        "std": None if empty else float(values.std()),
        "min": None if empty else float(values.min()),
        "max": None if empty else float(values.max()),
    }
