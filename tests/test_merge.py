"""Merging a source and its artifact: one D4RL-layout file that plain h5py reads, with an
is_synthetic mask and provenance; pairs that do not belong together are refused clearly."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from hipode_pipeline.artifact import write_artifact
from hipode_pipeline.cli import app
from hipode_pipeline.data.load import load_source
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import DataFormatError, OverwriteError
from hipode_pipeline.merge import load_merged, merge_files, read_merged


def write_source(path, n_episodes=4, length=25, obs_dim=11, act_dim=3, seed=0, env_id="Hopper-v5"):
    """A D4RL-format file of continuous episodes (s' of a step is the s of the next)."""
    rng = np.random.default_rng(seed)
    obs, next_obs, actions, timeouts = [], [], [], []
    for _ in range(n_episodes):
        states = rng.normal(size=(length + 1, obs_dim)).astype(np.float32)
        obs.append(states[:-1])
        next_obs.append(states[1:])
        actions.append(rng.uniform(-1, 1, (length, act_dim)).astype(np.float32))
        timeouts.append(np.arange(length) == length - 1)
    n = n_episodes * length
    with h5py.File(path, "w") as f:
        f["observations"] = np.concatenate(obs)
        f["next_observations"] = np.concatenate(next_obs)
        f["actions"] = np.concatenate(actions)
        f["rewards"] = rng.normal(size=n).astype(np.float32)
        f["terminals"] = np.zeros(n, bool)
        f["timeouts"] = np.concatenate(timeouts)
        f.attrs["env_id"] = env_id
    return path


def write_synthetic(path, source_spec, m=20, seed=1, **manifest_changes):
    """An artifact claiming to come from `source_spec` (its real sha256 unless overridden)."""
    real, info = load_source(str(source_spec))
    rng = np.random.default_rng(seed)
    transitions = Transitions(
        rng.normal(size=(m, real.obs_dim)).astype(np.float32),
        rng.uniform(-1, 1, (m, real.act_dim)).astype(np.float32),
        rng.normal(size=m).astype(np.float32),
        rng.normal(size=(m, real.obs_dim)).astype(np.float32),
        rng.random(m) < 0.2,
        np.zeros(m, bool),
    )
    diagnostics = {
        "dynamics_error": rng.random(m).astype(np.float32),
        "value": rng.random(m).astype(np.float32),
        "source_index": rng.integers(0, len(real), m),
    }
    source = {k: v for k, v in info.to_dict().items() if k != "metadata"}
    manifest = {
        "source": source,
        "env_id": info.env_id,
        "ref_min_score": info.ref_min_score,
        "ref_max_score": info.ref_max_score,
        "task": "hopper-m-r",
        "counts": {"kept": m},
    }
    for key, value in manifest_changes.items():
        if key == "source_sha256":
            manifest["source"] = {**source, "sha256": value}
        else:
            manifest[key] = value
    write_artifact(path, transitions, diagnostics, manifest)
    return transitions


def test_merge_round_trip(tmp_path):
    source = write_source(tmp_path / "source.hdf5")
    synthetic = write_synthetic(tmp_path / "art.hdf5", source)
    summary = merge_files(str(source), tmp_path / "art.hdf5", tmp_path / "merged.hdf5")
    assert (summary["real"], summary["synthetic"]) == (100, 20)
    real, info = load_source(str(source))
    with h5py.File(tmp_path / "merged.hdf5", "r") as f:  # plain h5py, D4RL key names
        assert f["observations"].shape == (120, 11) and f["observations"].dtype == np.float32
        np.testing.assert_array_equal(f["observations"][100:], synthetic.observations)
        np.testing.assert_array_equal(f["terminals"][:100], real.terminals)
        assert f["is_synthetic"][()].sum() == 20 and not f["is_synthetic"][:100].any()
        assert f.attrs["env_id"] == "Hopper-v5"
        provenance = json.loads(f.attrs["provenance"])
    assert provenance["source"]["sha256"] == info.sha256
    assert provenance["artifact"]["checksum"].startswith("sha256:")
    back = read_merged(tmp_path / "merged.hdf5")
    assert back.real.sha256() == real.sha256() and back.synthetic.sha256() == synthetic.sha256()


def test_merged_file_is_a_readable_source(tmp_path):
    source = write_source(tmp_path / "source.hdf5")
    write_synthetic(tmp_path / "art.hdf5", source)
    merge_files(str(source), tmp_path / "art.hdf5", tmp_path / "merged.hdf5")
    merged, info = load_source(str(tmp_path / "merged.hdf5"))
    assert len(merged) == 120 and info.env_id == "Hopper-v5"


@pytest.mark.parametrize(
    ("change", "field"),
    [({"env_id": "Walker2d-v5"}, "env_id"), ({"source_sha256": "0" * 64}, "sha256")],
)
def test_mismatched_manifest_is_refused(tmp_path, change, field):
    source = write_source(tmp_path / "source.hdf5")
    write_synthetic(tmp_path / "art.hdf5", source, **change)
    with pytest.raises(DataFormatError, match=field) as error:
        load_merged(str(source), tmp_path / "art.hdf5")
    assert "art.hdf5" in str(error.value) and "expected" in str(error.value)


def test_artifact_of_other_dims_is_refused(tmp_path):
    small = write_source(tmp_path / "small.hdf5", obs_dim=5, env_id="Hopper-v5")
    write_synthetic(tmp_path / "art.hdf5", small)
    source = write_source(tmp_path / "source.hdf5")
    with pytest.raises(DataFormatError, match="observations.*11 columns"):
        load_merged(str(source), tmp_path / "art.hdf5")


def test_merge_cli_refuses_to_overwrite_and_prints_json(tmp_path):
    source = write_source(tmp_path / "source.hdf5")
    write_synthetic(tmp_path / "art.hdf5", source)
    runner = CliRunner()
    args = ["merge", str(source), str(tmp_path / "art.hdf5"), "--out", str(tmp_path / "m.hdf5")]
    first = runner.invoke(app, [*args, "--json"])
    assert first.exit_code == 0, first.output
    assert json.loads(first.stdout)["synthetic"] == 20
    second = runner.invoke(app, args)
    assert second.exit_code == OverwriteError.exit_code and "--force" in second.output
    assert runner.invoke(app, [*args, "--force"]).exit_code == 0
