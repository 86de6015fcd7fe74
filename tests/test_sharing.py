"""Export with a sha256 sidecar, import into the dataset root, D4RL export of the merge: only
intact, valid artifacts travel, and nothing is overwritten without --force."""

import json

import h5py
import numpy as np
import pytest
from builders import make_d4rl_file
from typer.testing import CliRunner

from hipode_pipeline.artifact import SCHEMA_VERSION, read_artifact, write_artifact
from hipode_pipeline.cli import app
from hipode_pipeline.data.load import load_source
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import DataFormatError, OverwriteError
from hipode_pipeline.files import file_sha256
from hipode_pipeline.sharing import export_artifact, import_artifact, sidecar_path

M = 24


def _artifact_from(source_path, out):
    """A small artifact whose manifest names `source_path` (sha256, env), as augment writes."""
    real, info = load_source(str(source_path))
    rng = np.random.default_rng(3)
    transitions = Transitions(
        observations=rng.normal(size=(M, real.obs_dim)).astype(np.float32),
        actions=rng.uniform(-1, 1, (M, real.act_dim)).astype(np.float32),
        rewards=rng.normal(size=M).astype(np.float32),
        next_observations=rng.normal(size=(M, real.obs_dim)).astype(np.float32),
        terminals=np.zeros(M, bool),
        timeouts=np.zeros(M, bool),
    )
    diagnostics = {
        "dynamics_error": rng.random(M).astype(np.float32),
        "value": rng.random(M).astype(np.float32),
        "source_index": rng.integers(0, len(real), M),
    }
    source = {k: v for k, v in info.to_dict().items() if k != "metadata"}
    manifest = {
        "task": "hopper-m-r",
        "env_id": info.env_id,
        "source": source,
        "counts": {"kept": M},
    }
    write_artifact(out, transitions, diagnostics, manifest)
    return out


@pytest.fixture
def pair(tmp_path):
    source = tmp_path / "hopper_source.hdf5"
    make_d4rl_file(source, n=60, obs_dim=11, act_dim=3, seed=0, attrs={"env_id": "Hopper-v5"})
    return source, _artifact_from(source, tmp_path / "made" / "hopper-m-r-td3bc-seed0.hdf5")


def _tamper(path):
    with h5py.File(path, "r+") as f:
        f["rewards"][0] = f["rewards"][0] + 1.0


def test_export_copies_with_sidecar_and_refuses_overwrite(pair, tmp_path):
    _, artifact = pair
    out = tmp_path / "shared" / "copy.hdf5"
    result = CliRunner().invoke(app, ["export", str(artifact), "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert out.read_bytes() == artifact.read_bytes()
    assert sidecar_path(out).read_text() == f"{file_sha256(out)}  copy.hdf5\n"
    assert summary["sha256"] == file_sha256(artifact)
    with pytest.raises(OverwriteError):
        export_artifact(artifact, out)
    assert CliRunner().invoke(app, ["export", str(artifact), "--out", str(out)]).exit_code == 2
    assert export_artifact(artifact, out, force=True)["out"] == str(out)


def test_export_refuses_an_invalid_artifact(pair, tmp_path):
    _, artifact = pair
    _tamper(artifact)
    out = tmp_path / "copy.hdf5"
    with pytest.raises(DataFormatError, match="checksum"):
        export_artifact(artifact, out)
    assert not out.exists() and not sidecar_path(out).exists()


def test_import_validates_and_copies_into_the_root(pair, tmp_path, dataset_root):
    _, artifact = pair
    exported = tmp_path / "inbox" / artifact.name
    export_artifact(artifact, exported)
    result = CliRunner().invoke(app, ["import", str(exported), "--json"])
    assert result.exit_code == 0, result.output
    target = dataset_root / "artifacts" / artifact.name
    assert json.loads(result.stdout)["sidecar_checked"] is True
    assert target.read_bytes() == artifact.read_bytes()
    assert len(read_artifact(target)) == M
    assert [p.name for p in target.parent.iterdir()] == [target.name]
    # a second import needs --force
    assert CliRunner().invoke(app, ["import", str(exported)]).exit_code == 2
    assert CliRunner().invoke(app, ["import", str(exported), "--force"]).exit_code == 0
    listed = json.loads(CliRunner().invoke(app, ["datasets", "list", "--json"]).stdout)
    entry = next(e for e in listed if e["id"] == f"artifacts/{artifact.name}")
    assert (entry["task"], entry["env_id"], entry["transitions"], entry["schema_version"]) == (
        "hopper-m-r",
        "Hopper-v5",
        M,
        SCHEMA_VERSION,
    )


def test_import_refuses_a_tampered_file_and_copies_nothing(pair, tmp_path, dataset_root):
    _, artifact = pair
    tampered = tmp_path / "tampered" / artifact.name
    tampered.parent.mkdir()
    tampered.write_bytes(artifact.read_bytes())
    _tamper(tampered)
    result = CliRunner().invoke(app, ["import", str(tampered)])
    assert result.exit_code == 2 and "checksum" in result.output
    # not even the folder: it was made only for the import's lock
    assert not (dataset_root / "artifacts").exists()


def test_import_checks_the_sidecar_hash(pair, tmp_path, dataset_root):
    _, artifact = pair
    exported = tmp_path / "inbox" / artifact.name
    export_artifact(artifact, exported)
    sidecar_path(exported).write_text("0" * 64 + f"  {artifact.name}\n")
    with pytest.raises(DataFormatError, match="sha256"):
        import_artifact(exported)
    assert not (dataset_root / "artifacts").exists()


def test_export_d4rl_writes_the_merge(pair, tmp_path):
    source, artifact = pair
    out = tmp_path / "merged.hdf5"
    args = ["export", str(artifact), "--d4rl", "--source", str(source), "--out", str(out), "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    with h5py.File(out, "r") as f:
        assert f["observations"].shape == (60 + M, 11)
        assert int(f["is_synthetic"][()].sum()) == M
        np.testing.assert_array_equal(
            f["rewards"][60:], read_artifact(artifact).transitions.rewards
        )
    assert json.loads(result.stdout)["sha256"] == file_sha256(out)
    assert sidecar_path(out).is_file()
    no_source = CliRunner().invoke(app, ["export", str(artifact), "--d4rl", "--out", str(out)])
    assert no_source.exit_code == 2 and "--source" in no_source.output
