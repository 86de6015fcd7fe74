"""Source ⊕ synthetic: check that an artifact belongs to a source, hold both side by side for
training, and write them as one flat D4RL-layout file with an `is_synthetic` mask and both
provenance records, so any library that reads D4RL-style HDF5 can train on it."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hipode_pipeline.artifact import Artifact, read_artifact
from hipode_pipeline.data.load import load_source
from hipode_pipeline.data.transitions import FIELDS, SourceInfo, Transitions, validate_transitions
from hipode_pipeline.errors import DataFormatError, DatasetNotFoundError, OverwriteError
from hipode_pipeline.files import atomic_path

MERGED_SCHEMA = {"name": "hipode-merged", "version": "1.0"}
PROVENANCE_ATTR = "provenance"  # JSON: schema, source record, artifact manifest


@dataclass(frozen=True, eq=False)
class MergedData:
    """Real and synthetic transitions that belong together, plus where each came from."""

    real: Transitions  # the source dataset
    synthetic: Transitions | None  # the artifact's transitions (None: source only)
    source: dict[str, Any]  # SourceInfo.to_dict() of the source
    artifact_manifest: dict[str, Any] | None  # the artifact's manifest
    artifact_path: Path | None  # where the artifact was read from

    @property
    def env_id(self) -> str | None:
        return self.source.get("env_id")

    def ref_scores(self) -> tuple[float | None, float | None]:
        return self.source.get("ref_min_score"), self.source.get("ref_max_score")

    def transitions(self) -> Transitions:
        """All rows, real first."""
        return (
            self.real
            if self.synthetic is None
            else Transitions.concatenate([self.real, self.synthetic])
        )

    def is_synthetic(self) -> np.ndarray:
        n_syn = 0 if self.synthetic is None else len(self.synthetic)
        return np.concatenate([np.zeros(len(self.real), bool), np.ones(n_syn, bool)])


def check_pair(source: Transitions, info: SourceInfo, artifact: Artifact) -> None:
    """Refuse an artifact that was not generated from this source: env id, dims, source sha256."""
    manifest, path = artifact.manifest, artifact.path
    recorded = manifest.get("source") or {}
    env_id = manifest.get("env_id") or recorded.get("env_id")
    if info.env_id and env_id and env_id != info.env_id:
        raise DataFormatError(
            path, "manifest.env_id", f"{info.env_id} (the env of source {info.id})", env_id
        )
    syn = artifact.transitions
    if syn.obs_dim != source.obs_dim:
        raise DataFormatError(
            path, "observations", f"{source.obs_dim} columns like source {info.id}", syn.obs_dim
        )
    if syn.act_dim != source.act_dim:
        raise DataFormatError(
            path, "actions", f"{source.act_dim} columns like source {info.id}", syn.act_dim
        )
    sha = recorded.get("sha256")
    if sha != info.sha256:
        raise DataFormatError(
            path,
            "manifest.source.sha256",
            f"{info.sha256[:16]}… (source {info.id}); this artifact was generated from other data",
            f"{str(sha)[:16]}…",
        )


def load_merged(
    source_spec: str, artifact_path: Path | None, *, root: Path | None = None
) -> MergedData:
    """Load a source (task name, Minari id or D4RL file) and, if given, its artifact, checked."""
    real, info = load_source(source_spec, root)
    source = _compact_source(info)
    if artifact_path is None:
        return MergedData(real, None, source, None, None)
    artifact_path = Path(artifact_path)
    if not artifact_path.is_file():
        raise DatasetNotFoundError(f"{artifact_path}: no such artifact file")
    artifact = read_artifact(artifact_path)
    check_pair(real, info, artifact)
    return MergedData(real, artifact.transitions, source, artifact.manifest, artifact_path)


def _compact_source(info: SourceInfo) -> dict[str, Any]:
    """SourceInfo as a dict, metadata kept only when it is small and JSON-able."""
    record = info.to_dict()
    try:
        text = json.dumps(record["metadata"])
        if len(text) > 64_000:
            record["metadata"] = {"omitted": f"{len(text)} characters"}
    except TypeError:
        record["metadata"] = {"omitted": "not JSON-able"}
    return record


def write_merged(merged: MergedData, out: Path, *, force: bool = False) -> Path:
    """One D4RL-layout HDF5 file: the six fields, `is_synthetic`, env id and reference scores as
    attributes, and a JSON `provenance` attribute (schema, source record, artifact manifest)."""
    out = Path(out)
    if out.exists() and not force:
        raise OverwriteError(f"{out} already exists; pass --force to replace it")
    all_rows = merged.transitions()
    # every synthetic row is a one-step episode, and the source's last row ends one too, so
    # readers that follow episodes (s' of a row = s of the next) never join unrelated rows;
    # a timeout still bootstraps, so learning is unchanged
    timeouts = all_rows.timeouts | (merged.is_synthetic() & ~all_rows.terminals)
    if len(all_rows) > len(merged.real) and not (
        merged.real.terminals[-1] or merged.real.timeouts[-1]
    ):
        timeouts[len(merged.real) - 1] = True
    all_rows = Transitions(**{**all_rows.arrays(), "timeouts": timeouts})
    provenance = {
        "schema": MERGED_SCHEMA,
        "source": merged.source,
        "artifact": merged.artifact_manifest,
        "artifact_path": None if merged.artifact_path is None else merged.artifact_path.name,
        "counts": {"real": len(merged.real), "synthetic": len(all_rows) - len(merged.real)},
        "episode_ends": "synthetic rows (not terminal) carry timeouts = 1: one-step episodes; "
        "read them with next_observations",
    }
    with atomic_path(out) as temp, h5py.File(temp, "w") as f:
        for name, array in all_rows.arrays().items():
            f.create_dataset(name, data=array)
        f.create_dataset("is_synthetic", data=merged.is_synthetic())
        for key in ("env_id", "ref_min_score", "ref_max_score"):
            if merged.source.get(key) is not None:
                f.attrs[key] = merged.source[key]
        f.attrs[PROVENANCE_ATTR] = json.dumps(provenance, sort_keys=True, default=str)
    return out


def read_merged(path: Path) -> MergedData:
    """Read a file `write_merged` wrote, split back into real and synthetic rows."""
    path = Path(path)
    if not path.is_file():
        raise DatasetNotFoundError(f"{path}: no such merged file")
    try:
        with h5py.File(path, "r") as f:
            if PROVENANCE_ATTR not in f.attrs:
                raise DataFormatError(
                    path,
                    PROVENANCE_ATTR,
                    f"a JSON attribute of schema {MERGED_SCHEMA['name']}",
                    "nothing",
                )
            provenance = json.loads(f.attrs[PROVENANCE_ATTR])
            if provenance.get("schema", {}).get("name") != MERGED_SCHEMA["name"]:
                raise DataFormatError(
                    path, "provenance.schema", MERGED_SCHEMA, provenance.get("schema")
                )
            if "is_synthetic" not in f:
                raise DataFormatError(
                    path, "is_synthetic", "a boolean mask, one per row", "nothing (missing)"
                )
            arrays = {name: f[name][()] for name in FIELDS if name in f}
            mask = np.asarray(f["is_synthetic"][()], dtype=bool)
    except OSError as error:
        raise DataFormatError(
            path, "file", "a complete HDF5 file", f"unreadable ({error})"
        ) from None
    everything = validate_transitions(arrays, path)
    if mask.shape != (len(everything),):
        raise DataFormatError(path, "is_synthetic", f"shape ({len(everything)},)", mask.shape)
    real = Transitions(**{k: v[~mask] for k, v in everything.arrays().items()})
    synthetic = None
    if mask.any():
        # undo the one-step-episode marks of write_merged (synthetic rows have no timeouts)
        rows = {k: v[mask] for k, v in everything.arrays().items()}
        synthetic = Transitions(**{**rows, "timeouts": np.zeros(int(mask.sum()), bool)})
    return MergedData(real, synthetic, provenance["source"], provenance.get("artifact"), None)


def merge_files(
    source_spec: str,
    artifact_path: Path,
    out: Path,
    *,
    root: Path | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """`hipode merge`: check the pair, write the merged file, return a summary."""
    out = Path(out)
    if out.exists() and not force:
        raise OverwriteError(f"{out} already exists; pass --force to replace it")
    merged = load_merged(source_spec, artifact_path, root=root)
    write_merged(merged, out, force=force)
    return {
        "out": str(out),
        "env_id": merged.env_id,
        "real": len(merged.real),
        "synthetic": 0 if merged.synthetic is None else len(merged.synthetic),
        "source_sha256": merged.source["sha256"],
        "artifact_checksum": (merged.artifact_manifest or {}).get("checksum"),
    }
