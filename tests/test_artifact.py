"""The synthetic artifact round-trips, refuses overwrites and rejects damaged files clearly."""

import json

import h5py
import numpy as np
import pytest

from hipode_pipeline.artifact import (
    MANIFEST_ATTR,
    manifest_checksum,
    read_artifact,
    read_manifest,
    seal_manifest,
    write_artifact,
)
from hipode_pipeline.contract import default_artifact_path, table_settings
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import DataFormatError, DatasetNotFoundError, OverwriteError
from hipode_pipeline.tasks import get_task

M, OBS_DIM, ACT_DIM = 300, 11, 3


def _synthetic(seed: int = 0) -> tuple[Transitions, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    transitions = Transitions(
        observations=rng.normal(size=(M, OBS_DIM)).astype(np.float32),
        actions=rng.uniform(-1, 1, (M, ACT_DIM)).astype(np.float32),
        rewards=rng.normal(size=M).astype(np.float32),
        next_observations=rng.normal(size=(M, OBS_DIM)).astype(np.float32),
        terminals=rng.random(M) < 0.1,
        timeouts=np.zeros(M, dtype=bool),
    )
    diagnostics = {
        "dynamics_error": rng.random(M).astype(np.float32),
        "value": rng.normal(size=M).astype(np.float32),
        "source_index": rng.integers(0, 1000, M),
    }
    return transitions, diagnostics


@pytest.fixture
def artifact_file(tmp_path):
    transitions, diagnostics = _synthetic()
    path = tmp_path / "out" / "synthetic.hdf5"
    write_artifact(path, transitions, diagnostics, {"task": "hopper-m-r", "counts": {"kept": M}})
    return path


def test_round_trip_keeps_arrays_and_manifest(artifact_file):
    transitions, diagnostics = _synthetic()
    artifact = read_artifact(artifact_file)
    for name, array in transitions.arrays().items():
        assert artifact.transitions.arrays()[name].dtype == array.dtype
        np.testing.assert_array_equal(artifact.transitions.arrays()[name], array)
    for name, array in diagnostics.items():
        np.testing.assert_array_equal(artifact.diagnostics[name], array)
    assert artifact.manifest["schema"] == {"name": "hipode-synthetic", "version": "1.2"}
    assert artifact.manifest["task"] == "hopper-m-r"
    assert artifact.manifest["checksum"].startswith("sha256:")
    assert artifact.manifest["manifest_checksum"] == manifest_checksum(artifact.manifest)
    assert read_manifest(artifact_file) == artifact.manifest
    # plain h5py (a D4RL-style loader) sees the usual keys
    with h5py.File(artifact_file, "r") as f:
        assert {
            "observations",
            "actions",
            "rewards",
            "next_observations",
            "terminals",
            "timeouts",
        } <= set(f)


def test_overwrite_needs_force_and_leaves_no_temp_files(artifact_file):
    transitions, diagnostics = _synthetic(seed=1)
    with pytest.raises(OverwriteError, match="--force"):
        write_artifact(artifact_file, transitions, diagnostics, {})
    np.testing.assert_array_equal(
        read_artifact(artifact_file).transitions.rewards, _synthetic()[0].rewards
    )
    write_artifact(artifact_file, transitions, diagnostics, {}, force=True)
    np.testing.assert_array_equal(
        read_artifact(artifact_file).transitions.rewards, transitions.rewards
    )
    assert [p.name for p in artifact_file.parent.iterdir()] == [artifact_file.name]


def test_flipped_bytes_fail_the_checksum(artifact_file):
    with h5py.File(artifact_file, "r") as f:
        offset = f["rewards"].id.get_offset()
    with open(artifact_file, "r+b") as f:
        f.seek(offset + 10)
        byte = f.read(1)
        f.seek(offset + 10)
        f.write(bytes([byte[0] ^ 0x01]))
    with pytest.raises(DataFormatError, match="checksum") as error:
        read_artifact(artifact_file)
    assert str(artifact_file) in str(error.value)


def test_truncated_file_is_rejected(artifact_file):
    data = artifact_file.read_bytes()
    artifact_file.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataFormatError, match="complete HDF5 file"):
        read_artifact(artifact_file)


def _edit_manifest(path, change):
    with h5py.File(path, "r+") as f:
        manifest = json.loads(f.attrs[MANIFEST_ATTR])
        f.attrs[MANIFEST_ATTR] = change(manifest)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (
            lambda m: json.dumps({**m, "schema": {"name": "hipode-synthetic", "version": "2.0"}}),
            "schema.version",
        ),
        (lambda m: json.dumps({**m, "schema": {"name": "d4rl", "version": "1.0"}}), "schema.name"),
        (lambda m: "{not json", "manifest"),
    ],
)
def test_bad_manifest_is_rejected(artifact_file, change, field):
    _edit_manifest(artifact_file, change)
    with pytest.raises(DataFormatError, match=field):
        read_artifact(artifact_file)


def test_minor_version_is_accepted(artifact_file):
    # a later minor's writer seals its manifest the same way
    schema = {"name": "hipode-synthetic", "version": "1.3"}
    _edit_manifest(artifact_file, lambda m: json.dumps(seal_manifest({**m, "schema": schema})))
    assert len(read_artifact(artifact_file)) == M


def test_writer_stores_nonfinite_provenance_as_null(tmp_path):
    transitions, diagnostics = _synthetic()
    path = tmp_path / "nan.hdf5"
    stored = write_artifact(path, transitions, diagnostics, {"summary": {"loss": float("nan")}})
    assert stored["summary"] == {"loss": None}
    assert read_manifest(path) == stored


def test_writer_refuses_zero_rows_and_writes_nothing(tmp_path):
    transitions, diagnostics = _synthetic()
    empty = Transitions(**{k: v[:0] for k, v in transitions.arrays().items()})
    with pytest.raises(DataFormatError, match="at least one synthetic transition"):
        write_artifact(
            tmp_path / "empty.hdf5", empty, {k: v[:0] for k, v in diagnostics.items()}, {}
        )
    assert not (tmp_path / "empty.hdf5").exists() and not list(tmp_path.glob(".empty*"))


@pytest.mark.parametrize(
    ("name", "replacement", "message"),
    [
        ("actions", None, "missing"),
        ("rewards", np.zeros(M, dtype=np.float64), "dtype float32"),
        ("next_observations", np.zeros((M, OBS_DIM + 1), dtype=np.float32), "shape"),
        ("value", np.full(M, np.nan, dtype=np.float32), "finite values"),
        ("source_index", None, "missing"),
    ],
)
def test_damaged_datasets_are_rejected(artifact_file, name, replacement, message):
    with h5py.File(artifact_file, "r+") as f:
        del f[name]
        if replacement is not None:
            f.create_dataset(name, data=replacement)
    with pytest.raises(DataFormatError, match=message) as error:
        read_artifact(artifact_file)
    assert name in str(error.value)


def test_missing_file_and_default_path(tmp_path, dataset_root):
    with pytest.raises(DatasetNotFoundError):
        read_artifact(tmp_path / "absent.hdf5")
    task = get_task("hopper-medium-replay-v0")
    path = default_artifact_path(task, table_settings(task, "iql"), seed=3)
    # named by what it is (IQL's Table 7 row on hopper-m-r), not by who asked for it
    assert (
        path == dataset_root / "artifacts" / "hopper-m-r-eta0.05-lam1-n10-alpha1-sigma1-seed3.hdf5"
    )


# Schema regression: the content checksum (unchanged since 1.0) and the manifest digest (since
# 1.1; its text names the version, 1.2 now) for fixed content. Files already written hold these
# values, so a change in their order, encoding or field set would make them all unreadable.
GOLDEN_CHECKSUM_1_0 = "sha256:3e8a55a4c4f446fd13463971e1e7aefc9ffdb37be0ab8613c6d6e9abacab6186"
# sha256 of the canonical text {"checksum":"<GOLDEN_CHECKSUM_1_0>","schema":{...,"version":"1.2"}}
# (with "1.1" it was sha256:8cb9578d334e265ae5400c5d4b6e2568dcbf47c63c8330b5d1233c2c9da71adf)
GOLDEN_MANIFEST_CHECKSUM_1_2 = (
    "sha256:d138ab25e11bb3ef6964aec408d0738b7a9cf32564299cca07736f6baf07cce4"
)


def test_checksum_of_schema_1_0_is_stable(tmp_path):
    transitions = Transitions(
        observations=np.arange(8, dtype=np.float32).reshape(4, 2),
        actions=np.linspace(-1, 1, 4, dtype=np.float32).reshape(4, 1),
        rewards=np.array([0.5, -1.0, 2.0, 0.0], dtype=np.float32),
        next_observations=np.arange(8, dtype=np.float32).reshape(4, 2) + 0.25,
        terminals=np.array([False, True, False, False]),
        timeouts=np.zeros(4, dtype=bool),
    )
    diagnostics = {
        "value": np.array([1, 2, 3, 4], dtype=np.float32),
        "dynamics_error": np.array([0.1, 0.2, 0.3, 0.4], dtype=np.float32),
        "source_index": np.array([3, 1, 0, 2], dtype=np.int64),
    }
    stored = write_artifact(tmp_path / "golden.hdf5", transitions, diagnostics, {})
    assert stored["checksum"] == GOLDEN_CHECKSUM_1_0
    assert read_artifact(tmp_path / "golden.hdf5").manifest["checksum"] == GOLDEN_CHECKSUM_1_0
    assert stored["manifest_checksum"] == GOLDEN_MANIFEST_CHECKSUM_1_2
