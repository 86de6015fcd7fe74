"""`hipode datasets list|show` and the catalog behind them."""

from __future__ import annotations

import json

import numpy as np
from builders import make_d4rl_file, make_episodes, make_minari_dataset
from typer.testing import CliRunner

from hipode_pipeline.cli import app
from hipode_pipeline.data.catalog import list_local_datasets
from hipode_pipeline.data.load import load_source


def _flat(text: str) -> str:
    """Rich wraps long lines at the terminal width; compare text with whitespace collapsed."""
    return " ".join(text.split())


def _populate(root) -> None:
    episodes = make_episodes(3, 11, 3, seed=0, lengths=[5, 6, 7])
    make_minari_dataset("test/hopper/small-v0", episodes, ref_min_score=0.0, ref_max_score=10.0)
    make_minari_dataset("test/foo/other-v0", episodes[:1], env_id="Foo-v0")
    (root / "artifacts").mkdir()
    manifest = {"env_id": "Hopper-v5", "ref_min_score": -20.0, "ref_max_score": 3000.0}
    make_d4rl_file(
        root / "artifacts" / "hopper-m-r-td3bc-seed0.hdf5",
        n=40,
        obs_dim=11,
        act_dim=3,
        seed=0,
        attrs={"manifest": json.dumps(manifest)},
    )
    (root / "d4rl").mkdir()
    make_d4rl_file(root / "d4rl" / "walker2d_medium-v2.hdf5", n=25, obs_dim=17, act_dim=6, seed=1)
    # generator caches are not datasets, whatever their format
    (root / "cache").mkdir()
    make_d4rl_file(root / "cache" / "scratch.hdf5", n=5, obs_dim=2, act_dim=1, seed=2)


def test_catalog_finds_minari_datasets_artifacts_and_files(dataset_root):
    _populate(dataset_root)

    entries = {entry.id: entry for entry in list_local_datasets()}

    assert set(entries) == {
        "test/hopper/small-v0",
        "test/foo/other-v0",
        "artifacts/hopper-m-r-td3bc-seed0.hdf5",
        "d4rl/walker2d_medium-v2.hdf5",
    }
    small = entries["test/hopper/small-v0"]
    assert (small.kind, small.env_id, small.transitions, small.episodes) == (
        "minari",
        "Hopper-v5",
        18,
        3,
    )
    assert small.has_ref_scores and small.ref_scores_from == "dataset" and small.size_bytes > 0
    other = entries["test/foo/other-v0"]
    assert not other.has_ref_scores and other.ref_scores_from is None
    artifact = entries["artifacts/hopper-m-r-td3bc-seed0.hdf5"]
    assert (artifact.kind, artifact.env_id, artifact.transitions) == ("artifact", "Hopper-v5", 40)
    assert artifact.has_ref_scores
    assert artifact.size_bytes == (dataset_root / artifact.path).stat().st_size
    loose = entries["d4rl/walker2d_medium-v2.hdf5"]
    assert (loose.kind, loose.env_id, loose.ref_scores_from) == (
        "d4rl-hdf5",
        "Walker2d-v5",
        "registry",
    )


def test_catalog_reports_unreadable_entries_instead_of_failing(dataset_root):
    folder = make_minari_dataset("test/hopper/broken-v0", make_episodes(1, 3, 1, seed=0))
    (folder / "data" / "metadata.json").write_text("{")
    (dataset_root / "artifacts").mkdir()
    (dataset_root / "artifacts" / "junk.hdf5").write_text("not hdf5")

    entries = {entry.id: entry for entry in list_local_datasets()}

    assert entries["test/hopper/broken-v0"].note.startswith("unreadable metadata")
    assert entries["artifacts/junk.hdf5"].note.startswith("unreadable")
    assert entries["artifacts/junk.hdf5"].size_bytes == 8


def test_datasets_list_table_and_json(dataset_root):
    _populate(dataset_root)
    runner = CliRunner()

    table = runner.invoke(app, ["datasets", "list"])
    as_json = runner.invoke(app, ["datasets", "list", "--json"])

    assert table.exit_code == 0, table.stderr
    assert "test/hopper/small-v0" in _flat(table.stdout)
    assert as_json.exit_code == 0
    rows = json.loads(as_json.stdout)
    assert {row["kind"] for row in rows} == {"minari", "artifact", "d4rl-hdf5"}
    assert {row["id"]: row["transitions"] for row in rows}["test/hopper/small-v0"] == 18


def test_datasets_list_with_root_option_and_empty_root(tmp_path):
    empty = tmp_path / "elsewhere"
    empty.mkdir()

    result = CliRunner().invoke(app, ["datasets", "list", "--root", str(empty), "--json"])
    table = CliRunner().invoke(app, ["datasets", "list", "--root", str(empty)])

    assert result.exit_code == 0 and json.loads(result.stdout) == []
    assert table.exit_code == 0 and "no datasets" in _flat(table.stderr)


def test_datasets_show_json_matches_the_loader():
    make_minari_dataset(
        "test/hopper/show-v0", make_episodes(2, 11, 3, seed=9, terminate_last=[True, False])
    )

    result = CliRunner().invoke(app, ["datasets", "show", "test/hopper/show-v0", "--json"])

    assert result.exit_code == 0, result.stderr
    summary = json.loads(result.stdout)
    transitions, info = load_source("test/hopper/show-v0")
    assert summary["sha256"] == info.sha256 and summary["n"] == len(transitions)
    assert (summary["episodes"], summary["terminals"], summary["timeouts"]) == (2, 1, 1)
    assert summary["ref_scores_from"] == "registry"


def test_datasets_show_table():
    make_minari_dataset("test/hopper/table-v0", make_episodes(2, 11, 3, seed=9))

    result = CliRunner().invoke(app, ["datasets", "show", "test/hopper/table-v0"])

    assert result.exit_code == 0
    assert "Hopper-v5" in result.stdout and "sha256" in result.stdout


def test_datasets_show_on_a_bad_file_fails_with_the_message_on_stderr(tmp_path):
    path = tmp_path / "bad.hdf5"
    make_d4rl_file(path, n=12, obs_dim=3, act_dim=1, seed=0, terminals=np.full(12, 7))

    result = CliRunner().invoke(app, ["datasets", "show", str(path)])

    assert result.exit_code != 0
    assert result.stdout == ""
    message = _flat(result.stderr)
    assert "error:" in message and "bad.hdf5" in message and "field 'terminals'" in message


def test_datasets_show_on_a_missing_dataset_fails():
    result = CliRunner().invoke(app, ["datasets", "show", "mujoco/hopper/medium-v0"])

    assert result.exit_code != 0
    assert "copy the dataset" in _flat(result.stderr)
