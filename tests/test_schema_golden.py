"""The artifact layout is a contract: a committed reference file and schema description pin it.

A failure here means the schema changed. If that was intended: bump SCHEMA_VERSION (major for
changed or removed fields, minor for additions), update docs/schema.md, and rebuild the
reference with `python tests/data/make_reference_artifact.py`. Files of older minor versions
stay committed (never rebuilt): every reader of the same major must keep reading them.
"""

import importlib.util
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from hipode_pipeline.artifact import (
    MANIFEST_ATTR,
    MANIFEST_CHECKSUM_KEY,
    content_checksum,
    manifest_checksum,
    read_artifact,
    read_manifest,
    write_artifact,
)
from hipode_pipeline.files import file_sha256
from hipode_pipeline.validation import schema_description, validate_artifact

DATA = Path(__file__).parent / "data"
SCHEMA = json.loads((DATA / "artifact_schema.json").read_text())
REFERENCE = DATA / SCHEMA["reference_file"]["name"]
LEGACY = {
    version: DATA / entry["name"] for version, entry in SCHEMA["legacy_reference_files"].items()
}
# keys of the committed description that name files rather than rules
FILE_KEYS = ("reference_file", "legacy_reference_files")
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
    described = {key: value for key, value in SCHEMA.items() if key not in FILE_KEYS}
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


def test_committed_reference_carries_a_matching_manifest_digest():
    manifest = read_manifest(REFERENCE)
    assert manifest[MANIFEST_CHECKSUM_KEY] == manifest_checksum(manifest)


@pytest.mark.parametrize("version", sorted(LEGACY))
def test_older_minor_references_stay_readable(version):
    path = LEGACY[version]
    assert file_sha256(path) == SCHEMA["legacy_reference_files"][version]["sha256"], (
        f"{path.name} changed; older references are kept as they were written"
    )
    old, current = read_artifact(path), read_artifact(REFERENCE)
    assert old.manifest["schema"] == {"name": "hipode-synthetic", "version": version}
    # same rows, same content checksum: the checksum's definition did not change within 1.x
    assert old.manifest["checksum"] == current.manifest["checksum"]
    report = validate_artifact(path)
    assert report.valid, report.to_dict()
    if version != "1.0":
        # from 1.1 on the manifest carries its digest: nothing to warn about
        assert report.violations == [], report.to_dict()
        return
    # 1.0 predates the manifest digest: valid, with a warning that names the version
    assert [(v.field, v.severity) for v in report.violations] == [
        ("manifest.manifest_checksum", "warning")
    ]
    assert version in report.violations[0].found
