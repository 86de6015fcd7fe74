"""The artifact layout is a contract: a committed reference file and schema description pin it.

A failure here means the schema changed. If that was intended: bump SCHEMA_VERSION (major for
changed or removed fields, minor for additions), update docs/schema.md, and rebuild the
reference with `python tests/data/make_reference_artifact.py`.
"""

import importlib.util
import json
from pathlib import Path

import h5py
import numpy as np

from hipode_pipeline.artifact import (
    MANIFEST_ATTR,
    content_checksum,
    read_artifact,
    write_artifact,
)
from hipode_pipeline.files import file_sha256
from hipode_pipeline.validation import schema_description, validate_artifact

DATA = Path(__file__).parent / "data"
SCHEMA = json.loads((DATA / "artifact_schema.json").read_text())
REFERENCE = DATA / SCHEMA["reference_file"]["name"]
BUMP = "the artifact schema changed: bump SCHEMA_VERSION and update docs/schema.md"


def _reference_builder():
    spec = importlib.util.spec_from_file_location("reference", DATA / "make_reference_artifact.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _layout(path: Path) -> dict:
    """Dataset names, dtypes, ranks and attributes, plus the manifest's key set."""
    with h5py.File(path, "r") as f:
        datasets = {name: (f[name].dtype.str, f[name].ndim) for name in f}
        attrs = sorted(f.attrs)
        manifest = json.loads(f.attrs[MANIFEST_ATTR])
    return {"datasets": datasets, "attrs": attrs, "manifest_keys": sorted(manifest)}


def _layout_from_schema() -> dict:
    datasets = {d["name"]: (np.dtype(d["dtype"]).str, len(d["shape"])) for d in SCHEMA["datasets"]}
    manifest = set(SCHEMA["manifest"]["required"]) | set(SCHEMA["manifest"]["recommended"])
    return {
        "datasets": datasets,
        "attrs": [SCHEMA["manifest_attribute"]],
        "manifest_keys": sorted(manifest),
    }


def test_committed_reference_reads_and_validates():
    artifact = read_artifact(REFERENCE)
    report = validate_artifact(REFERENCE)
    assert report.valid and report.violations == [], report.to_dict()
    assert artifact.manifest["schema"] == SCHEMA["schema"]
    assert len(artifact) == artifact.manifest["counts"]["kept"]


def test_rules_in_code_match_the_committed_description():
    described = {key: value for key, value in SCHEMA.items() if key != "reference_file"}
    assert schema_description() == described, BUMP


def test_fresh_write_has_the_committed_layout(tmp_path):
    transitions, diagnostics, manifest = _reference_builder().reference_content()
    fresh = tmp_path / "fresh.hdf5"
    write_artifact(fresh, transitions, diagnostics, manifest)
    assert _layout(fresh) == _layout(REFERENCE), BUMP
    assert _layout(fresh) == _layout_from_schema(), BUMP
    # same content, same writer: the same content checksum as the committed file
    fresh_checksum = read_artifact(fresh).manifest["checksum"]
    assert fresh_checksum == read_artifact(REFERENCE).manifest["checksum"], BUMP


def test_committed_reference_is_unchanged():
    assert file_sha256(REFERENCE) == SCHEMA["reference_file"]["sha256"], (
        f"{REFERENCE.name} changed; rebuild it only with tests/data/make_reference_artifact.py"
    )
    artifact = read_artifact(REFERENCE)
    arrays = {**artifact.transitions.arrays(), **artifact.diagnostics}
    assert content_checksum(arrays) == artifact.manifest["checksum"]
