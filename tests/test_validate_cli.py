"""`hipode validate` and `hipode inspect` on the committed reference artifact and broken copies."""

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
from typer.testing import CliRunner

from hipode_pipeline.artifact import MANIFEST_ATTR, read_artifact, seal_manifest
from hipode_pipeline.cli import app

REFERENCE = Path(__file__).parent / "data" / "reference_artifact.hdf5"


def _copy(tmp_path) -> Path:
    path = tmp_path / "copy.hdf5"
    shutil.copyfile(REFERENCE, path)
    return path


def test_validate_accepts_the_reference(tmp_path):
    result = CliRunner().invoke(app, ["validate", str(REFERENCE), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report == {
        "valid": True,
        "path": str(REFERENCE),
        "schema": {"name": "hipode-synthetic", "version": "1.2"},
        "violations": [],
    }


def test_validate_lists_every_violation_in_the_table(tmp_path):
    path = _copy(tmp_path)
    with h5py.File(path, "r+") as f:
        f["rewards"][3] = np.inf
        del f["value"]
        f.attrs[MANIFEST_ATTR] = json.dumps(
            {**json.loads(f.attrs[MANIFEST_ATTR]), "task": ["not", "a", "name"]}
        )
    result = CliRunner().invoke(app, ["validate", str(path)], terminal_width=200)
    assert result.exit_code == 1
    # the table's cells wrap with the path's length: read the fields from the --json listing
    listed = CliRunner().invoke(app, ["validate", str(path), "--json"])
    fields = {v["field"] for v in json.loads(listed.stdout)["violations"]}
    assert {"rewards", "value", "manifest.task", "manifest.manifest_checksum"} <= fields
    assert "rewards" in result.stdout and "Invalid" in result.stdout
    # the task edit is also a manifest the digest no longer matches
    assert "invalid" in result.stderr and "4 error(s)" in result.stderr


def test_warnings_alone_keep_a_file_valid(tmp_path):
    path = _copy(tmp_path)
    with h5py.File(path, "r+") as f:
        manifest = json.loads(f.attrs[MANIFEST_ATTR])
        del manifest["seeds"]
        # re-sealed: an edit the digest does not catch, so only the warning remains
        f.attrs[MANIFEST_ATTR] = json.dumps(seal_manifest(manifest))
    result = CliRunner().invoke(app, ["validate", str(path), "--json"])
    assert result.exit_code == 0, result.output
    violations = json.loads(result.stdout)["violations"]
    assert [(v["field"], v["severity"]) for v in violations] == [("manifest.seeds", "warning")]


def test_validate_of_a_missing_file_fails(tmp_path):
    result = CliRunner().invoke(app, ["validate", str(tmp_path / "absent.hdf5"), "--json"])
    assert result.exit_code == 1
    assert json.loads(result.stdout)["violations"][0]["field"] == "file"


def test_inspect_shows_manifest_and_statistics():
    artifact = read_artifact(REFERENCE)
    result = CliRunner().invoke(app, ["inspect", str(REFERENCE), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["manifest"]["task"] == "hopper-m-r"
    assert summary["manifest"]["schema"] == "hipode-synthetic 1.2"
    assert summary["manifest"]["rows"] == len(artifact)
    rewards = summary["statistics"]["rewards"]
    assert rewards["shape"] == [len(artifact)] and rewards["dtype"] == "float32"
    assert np.isclose(rewards["mean"], artifact.transitions.rewards.astype(np.float64).mean())
    assert np.isclose(rewards["max"], artifact.transitions.rewards.max())
    assert summary["fractions"]["terminals"] == artifact.transitions.terminals.mean()
    table = CliRunner().invoke(app, ["inspect", str(REFERENCE)], terminal_width=200)
    assert table.exit_code == 0
    assert "dynamics_error" in table.stdout and "hyper_parameters.eta" in table.stdout


def test_inspect_refuses_a_broken_file(tmp_path):
    path = _copy(tmp_path)
    with h5py.File(path, "r+") as f:
        del f["actions"]
    result = CliRunner().invoke(app, ["inspect", str(path)])
    assert result.exit_code == 2 and "actions" in result.stderr
