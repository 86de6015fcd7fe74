"""`hipode export --minari`: the merge as a Minari dataset that Minari itself loads, source
episodes intact, every synthetic row a flagged one-step episode, provenance in the metadata."""

import json

import minari
import numpy as np
import pytest
from builders import make_d4rl_file
from test_sharing import M, _artifact_from
from typer.testing import CliRunner

from hipode_pipeline.artifact import read_artifact
from hipode_pipeline.cli import app
from hipode_pipeline.data.load import load_source
from hipode_pipeline.data.minari_source import load_minari
from hipode_pipeline.minari_export import SYNTHETIC_INFO, source_episode_ends
from hipode_pipeline.paths import DATASETS_ENV_VAR

N, EPISODE = 60, 10
DATASET_ID = "hipode/hopper/mixed-hipode-v0"


@pytest.fixture
def exported(tmp_path, monkeypatch):
    """A 60-row source (episodes of 10, one ending in a terminal), its artifact with a terminal
    row, and the CLI's export of the two into a fresh dataset root."""
    source = tmp_path / "hopper_source.hdf5"
    make_d4rl_file(
        source,
        n=N,
        obs_dim=11,
        act_dim=3,
        seed=0,
        terminal_rows=(24,),
        attrs={"env_id": "Hopper-v5"},
    )
    artifact = _artifact_from(source, tmp_path / "hopper-m-r-td3bc-seed0.hdf5")
    root = tmp_path / "store"
    monkeypatch.setenv(DATASETS_ENV_VAR, str(root))
    args = ["export", str(artifact), "--minari", DATASET_ID, "--source", str(source), "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    return source, artifact, root, json.loads(result.stdout)


def test_minari_loads_the_export_with_every_row_and_flag(exported):
    source, artifact, _, summary = exported
    real, _ = load_source(str(source))
    synthetic = read_artifact(artifact).transitions
    dataset = minari.load_dataset(DATASET_ID)
    n_source = len(source_episode_ends(real))
    assert n_source == 7  # 10,10,5 (terminal at row 24),10,10,10,5
    assert dataset.total_steps == N + M and dataset.total_episodes == n_source + M
    assert summary["synthetic"] == M and summary["real"] == N
    episodes = list(dataset.iterate_episodes())
    flags = [bool(e.infos[SYNTHETIC_INFO].all()) for e in episodes]
    assert flags == [False] * n_source + [True] * M
    assert all(len(e.infos[SYNTHETIC_INFO]) == len(e.observations) for e in episodes)
    # the source comes back row for row, its terminal kept and no timeout invented
    source_rows = episodes[:n_source]
    np.testing.assert_array_equal(
        np.concatenate([e.observations[:-1] for e in source_rows]), real.observations
    )
    np.testing.assert_array_equal(
        np.concatenate([e.observations[1:] for e in source_rows]), real.next_observations
    )
    np.testing.assert_array_equal(np.concatenate([e.rewards for e in source_rows]), real.rewards)
    np.testing.assert_array_equal(
        np.concatenate([e.terminations for e in source_rows]), real.terminals
    )
    # the file's unfinished last episode is cut there, as a time limit would cut it
    cut = real.timeouts.copy()
    cut[-1] = True
    np.testing.assert_array_equal(np.concatenate([e.truncations for e in source_rows]), cut)
    one_step = episodes[n_source:]
    assert {len(e.rewards) for e in one_step} == {1}
    np.testing.assert_array_equal(
        np.stack([e.observations[1] for e in one_step]), synthetic.next_observations
    )
    np.testing.assert_array_equal(np.concatenate([e.actions for e in one_step]), synthetic.actions)
    np.testing.assert_array_equal(
        np.concatenate([e.terminations for e in one_step]), synthetic.terminals
    )
    # a one-step episode is cut, not ended: its last state bootstraps unless it is terminal
    np.testing.assert_array_equal(
        np.concatenate([e.truncations for e in one_step]), ~synthetic.terminals
    )


def test_export_metadata_names_the_synthetic_episodes_and_their_origin(exported):
    _, artifact, root, _ = exported
    record = minari.load_dataset(DATASET_ID).storage.metadata["hipode"]
    manifest = read_artifact(artifact).manifest
    assert record["first_synthetic_episode"] == 7
    assert record["synthetic_transitions"] == M
    assert record["artifact_checksum"] == manifest["checksum"]
    assert record["artifact_manifest"]["source"]["sha256"] == manifest["source"]["sha256"]
    # our own loader flattens it back: source rows first, then synthetic, nothing lost
    transitions, _ = load_minari(DATASET_ID, root)
    assert len(transitions) == N + M
    assert int(transitions.timeouts[N:].sum()) == int(
        (~read_artifact(artifact).transitions.terminals).sum()
    )


def test_export_minari_refuses_bad_ids_existing_datasets_and_out(exported, tmp_path):
    source, artifact, root, _ = exported
    base = ["export", str(artifact), "--source", str(source)]
    again = CliRunner().invoke(app, [*base, "--minari", DATASET_ID])
    assert again.exit_code != 0 and "--force" in again.output
    bad = CliRunner().invoke(app, [*base, "--minari", "no-version"])
    assert bad.exit_code != 0 and "dataset id" in bad.output
    assert not (root / "no-version").exists()
    with_out = CliRunner().invoke(
        app, [*base, "--minari", "hipode/hopper/other-v0", "--out", str(tmp_path / "x.hdf5")]
    )
    assert with_out.exit_code == 2 and "--out" in with_out.output
    forced = CliRunner().invoke(app, [*base, "--minari", DATASET_ID, "--force"])
    assert forced.exit_code == 0, forced.output
    assert minari.load_dataset(DATASET_ID).total_episodes == 7 + M
