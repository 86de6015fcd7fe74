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
from hipode_pipeline.data.d4rl_source import stored_here
from hipode_pipeline.data.load import load_source
from hipode_pipeline.data.transitions import FIELDS, SourceInfo, Transitions, validate_transitions
from hipode_pipeline.envs import canonical_env_id
from hipode_pipeline.errors import DataFormatError, OverwriteError
from hipode_pipeline.files import atomic_path
from hipode_pipeline.validation import (
    MANIFEST_CHECKSUM_KEY,
    ManifestSyntaxError,
    manifest_checksum,
    nonfinite_to_null,
    parse_manifest_text,
    require_regular_file,
)

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
    if isinstance(env_id, str):
        env_id = canonical_env_id(env_id)[0]  # an artifact of a Hopper-v2 source runs as v5
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
    source_spec: str,
    artifact_path: Path | None,
    *,
    root: Path | None = None,
    loaded: tuple[Transitions, SourceInfo] | None = None,
) -> MergedData:
    """Load a source (task name, Minari id or D4RL file; or take it `loaded` already) and, if
    given, its artifact, checked against it."""
    real, info = loaded if loaded is not None else load_source(source_spec, root)
    source = _compact_source(info)
    if artifact_path is None:
        return MergedData(real, None, source, None, None)
    artifact_path = require_regular_file(artifact_path)
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
    with atomic_path(out, replace=force) as temp, h5py.File(temp, "w") as f:
        for name, array in all_rows.arrays().items():
            f.create_dataset(name, data=array)
        f.create_dataset("is_synthetic", data=merged.is_synthetic())
        for key in ("env_id", "ref_min_score", "ref_max_score"):
            if merged.source.get(key) is not None:
                f.attrs[key] = merged.source[key]
        # strict JSON, as read_merged reads it: a non-finite number becomes null
        as_json = json.loads(json.dumps(provenance, sort_keys=True, default=str))
        f.attrs[PROVENANCE_ATTR] = json.dumps(
            nonfinite_to_null(as_json), sort_keys=True, allow_nan=False
        )
    return out


def read_merged(path: Path) -> MergedData:
    """Read a file `write_merged` wrote, split back into real and synthetic rows. The provenance
    is strict JSON of the merged schema (an embedded artifact manifest must match its digest
    when it carries one), and only datasets stored in the file are read."""
    path = require_regular_file(path, "merged file")
    try:
        with h5py.File(path, "r") as f:
            provenance = _read_provenance(path, f.attrs.get(PROVENANCE_ATTR))
            if "is_synthetic" not in f:
                raise DataFormatError(
                    path, "is_synthetic", "a boolean mask, one per row", "nothing (missing)"
                )
            arrays = {name: _dataset(f, name, path)[()] for name in FIELDS if name in f}
            mask = np.asarray(_dataset(f, "is_synthetic", path)[()], dtype=bool)
    except (OSError, RuntimeError, ValueError, TypeError) as error:
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


def _dataset(f: h5py.File, name: str, path: Path) -> h5py.Dataset:
    node = stored_here(f, name, path)
    if not isinstance(node, h5py.Dataset) or node.dtype.kind not in "fiub":
        raise DataFormatError(path, name, "a numeric dataset stored in this file", node)
    return node


def _read_provenance(path: Path, raw: object) -> dict[str, Any]:
    """The `provenance` attribute: strict JSON, an object of the merged schema, its source an
    object, its artifact manifest an object (or null) whose digest matches when it has one."""
    expected = f"a JSON object of schema {MERGED_SCHEMA['name']}"
    if raw is None:
        raise DataFormatError(path, PROVENANCE_ATTR, expected, "nothing")
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8", errors="replace")
    if not isinstance(raw, str):
        raise DataFormatError(path, PROVENANCE_ATTR, expected, f"a {type(raw).__name__} value")
    try:
        provenance = parse_manifest_text(raw)
    except ManifestSyntaxError as error:
        raise DataFormatError(path, PROVENANCE_ATTR, f"{expected} (strict JSON)", error) from None
    except ValueError as error:
        raise DataFormatError(path, PROVENANCE_ATTR, expected, f"not JSON ({error})") from None
    if not isinstance(provenance, dict):
        raise DataFormatError(path, PROVENANCE_ATTR, expected, type(provenance).__name__)
    schema = provenance.get("schema")
    if not isinstance(schema, dict) or schema.get("name") != MERGED_SCHEMA["name"]:
        raise DataFormatError(path, "provenance.schema", MERGED_SCHEMA, repr(schema)[:80])
    if not isinstance(provenance.get("source"), dict):
        raise DataFormatError(
            path,
            "provenance.source",
            "an object (the source record)",
            repr(provenance.get("source"))[:80],
        )
    artifact = provenance.get("artifact")
    if artifact is not None and not isinstance(artifact, dict):
        raise DataFormatError(
            path,
            "provenance.artifact",
            "an object (the artifact's manifest) or null",
            repr(artifact)[:80],
        )
    stored = (artifact or {}).get(MANIFEST_CHECKSUM_KEY)
    if stored is not None and stored != manifest_checksum(artifact):
        raise DataFormatError(
            path,
            f"provenance.artifact.{MANIFEST_CHECKSUM_KEY}",
            f"{manifest_checksum(artifact)} (the digest of the embedded manifest)",
            f"{stored!r:.80}: the artifact's manifest was edited after merging",
        )
    return provenance


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
