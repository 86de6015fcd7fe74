"""Source loaders: exact flattening, terminal vs timeout, D4RL variants, refs and checksums."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from builders import make_d4rl_file, make_episodes, make_minari_dataset

from hipode_pipeline.artifact import write_artifact
from hipode_pipeline.data.d4rl_source import infer_timeouts, load_d4rl_hdf5
from hipode_pipeline.data.load import (
    describe_source,
    load_source,
    registry_family,
    task_for_env,
    task_from_file_name,
)
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.tasks import get_task

OBS_DIM, ACT_DIM = 11, 3


def _flatten_by_hand(episodes):
    """The expected flat arrays, built per episode, to check the vectorized loader against."""
    return {
        "observations": np.concatenate([e["observations"][:-1] for e in episodes]).astype(
            np.float32
        ),
        "next_observations": np.concatenate([e["observations"][1:] for e in episodes]).astype(
            np.float32
        ),
        "actions": np.concatenate([e["actions"] for e in episodes]),
        "rewards": np.concatenate([e["rewards"] for e in episodes]).astype(np.float32),
        "terminals": np.concatenate([e["terminations"] for e in episodes]),
        "timeouts": np.concatenate([e["truncations"] for e in episodes]),
    }


def test_minari_flattening_is_exact_and_keeps_terminal_and_timeout_apart():
    episodes = make_episodes(
        4, OBS_DIM, ACT_DIM, seed=3, lengths=[7, 5, 9, 4], terminate_last=[True, False, True, None]
    )
    make_minari_dataset("test/hopper/mixed-v0", episodes)

    transitions, info = load_source("test/hopper/mixed-v0")

    expected = _flatten_by_hand(episodes)
    for name, array in transitions.arrays().items():
        np.testing.assert_array_equal(array, expected[name], err_msg=name)
    assert transitions.observations.dtype == np.float32 and transitions.terminals.dtype == bool
    # terminal at the end of episodes 0 and 2, timeout at the end of episode 1, nothing after 3
    assert np.flatnonzero(transitions.terminals).tolist() == [6, 20]
    assert np.flatnonzero(transitions.timeouts).tolist() == [11]
    assert (info.id, info.format, info.n, info.env_id) == (
        "test/hopper/mixed-v0",
        "minari",
        25,
        "Hopper-v5",
    )
    assert info.sha256 == transitions.sha256()
    assert info.metadata["episodes"] == 4 and info.metadata["episodes_without_end"] == 1
    assert any("neither a termination nor a truncation" in note for note in info.metadata["notes"])


def test_minari_refs_come_from_the_dataset_when_present_else_from_the_registry():
    episodes = make_episodes(2, OBS_DIM, ACT_DIM, seed=0)
    make_minari_dataset(
        "test/hopper/with-refs-v0", episodes, ref_min_score=-5.0, ref_max_score=50.0
    )
    make_minari_dataset("test/hopper/no-refs-v0", episodes)
    make_minari_dataset("test/hopper/old-env-v0", episodes, env_id="Hopper-v2")
    # a gymnasium env no task runs on (an unregistered id is refused: tests/test_env_ids.py)
    make_minari_dataset("test/foo/unknown-env-v0", episodes, env_id="CartPole-v1")

    _, own = load_source("test/hopper/with-refs-v0")
    _, registry = load_source("test/hopper/no-refs-v0")
    _, old = load_source("test/hopper/old-env-v0")
    _, unknown = load_source("test/foo/unknown-env-v0")

    hopper = get_task("hopper-m-r")
    assert (own.ref_min_score, own.ref_max_score, own.metadata["ref_scores_from"]) == (
        -5.0,
        50.0,
        "dataset",
    )
    assert (registry.ref_min_score, registry.ref_max_score) == (
        hopper.ref_min_score,
        hopper.ref_max_score,
    )
    assert registry.metadata["ref_scores_from"] == "registry"
    assert old.env_id == "Hopper-v5" and old.ref_max_score == hopper.ref_max_score
    assert old.metadata["env_id_original"] == "Hopper-v2"
    assert unknown.ref_min_score is None and unknown.metadata["ref_scores_from"] is None
    assert any("no reference scores" in note for note in unknown.metadata["notes"])


def test_a_task_name_loads_its_collected_dataset_with_its_metadata():
    episodes = make_episodes(3, OBS_DIM, ACT_DIM, seed=1)
    recipe = {"recipe": "ppo", "seed": 7}
    make_minari_dataset(
        "local/hopper/medium-replay-v0",
        episodes,
        ref_min_score=-20.272305,
        ref_max_score=3234.3,
        extra_metadata={"hipode": recipe},
    )

    transitions, info = load_source("hopper-m-r")

    assert info.id == "local/hopper/medium-replay-v0"
    assert info.metadata["hipode"] == recipe
    assert len(transitions) == sum(len(e["rewards"]) for e in episodes)
    json.dumps(info.to_dict())  # the record goes into artifact manifests as JSON


def test_d4rl_file_with_every_field_round_trips(tmp_path):
    path = tmp_path / "source.hdf5"
    truth = make_d4rl_file(
        path, n=57, obs_dim=OBS_DIM, act_dim=ACT_DIM, seed=0, terminal_rows=[4, 30]
    )

    transitions, info = load_source(str(path))

    for name, array in transitions.arrays().items():
        np.testing.assert_array_equal(array, truth[name], err_msg=name)
    assert (info.id, info.format, info.n, info.metadata["dropped_transitions"]) == (
        str(path),
        "d4rl-hdf5",
        57,
        0,
    )
    assert (
        transitions.terminals.sum() == 2
        and transitions.timeouts.sum() == truth["timeouts"].sum() > 0
    )


def test_d4rl_without_next_observations_drops_rows_without_a_known_successor(tmp_path):
    path = tmp_path / "no-next.hdf5"
    truth = make_d4rl_file(
        path,
        n=33,
        obs_dim=OBS_DIM,
        act_dim=ACT_DIM,
        seed=1,
        terminal_rows=[14],
        with_next_observations=False,
    )

    transitions, info = load_d4rl_hdf5(path)

    # timeouts at 9, 24 (the count restarts after the terminal at 14); row 32 has no successor
    assert np.flatnonzero(truth["timeouts"]).tolist() == [9, 24]
    kept = np.setdiff1d(np.arange(33), [9, 24, 32])
    assert info.metadata["dropped_transitions"] == 3 and len(transitions) == kept.size
    np.testing.assert_array_equal(transitions.observations, truth["observations"][kept])
    np.testing.assert_array_equal(transitions.actions, truth["actions"][kept])
    np.testing.assert_array_equal(transitions.next_observations, truth["observations"][kept + 1])
    # inside episodes the shifted successor is the true one
    inside = ~truth["terminals"][kept]
    np.testing.assert_array_equal(
        transitions.next_observations[inside], truth["next_observations"][kept][inside]
    )
    # the dropped timeouts' predecessors (8, 23) now end their episodes; the terminal stays put
    assert kept[transitions.timeouts].tolist() == [8, 23]
    assert kept[transitions.terminals].tolist() == [14]


def test_d4rl_v0_file_gets_timeouts_from_episode_length(tmp_path):
    path = tmp_path / "v0.hdf5"
    truth = make_d4rl_file(
        path,
        n=40,
        obs_dim=OBS_DIM,
        act_dim=ACT_DIM,
        seed=2,
        terminal_rows=[12],
        with_timeouts=False,
    )

    transitions, info = load_d4rl_hdf5(path, max_episode_steps=10)

    np.testing.assert_array_equal(transitions.timeouts, truth["timeouts"])
    np.testing.assert_array_equal(transitions.terminals, truth["terminals"])
    assert info.metadata["timeouts_inferred"] and np.flatnonzero(transitions.timeouts).tolist() == [
        9,
        22,
        32,
    ]


def test_infer_timeouts_restarts_after_terminals():
    terminals = np.zeros(12, dtype=bool)
    terminals[[1, 4]] = True
    # runs: rows 0-1 (terminal), 2-4 (terminal), 5-11: every third step of a run times out
    assert np.flatnonzero(infer_timeouts(terminals, 3)).tolist() == [7, 10]
    assert not infer_timeouts(terminals, 100).any()


def test_d4rl_refs_from_file_attributes_then_file_name_then_none(tmp_path):
    common = dict(n=20, obs_dim=OBS_DIM, act_dim=ACT_DIM, seed=0)
    attrs = {"env_id": "Walker2d-v5", "ref_min_score": 1.5, "ref_max_score": 99.0}
    make_d4rl_file(tmp_path / "walker_run.hdf5", attrs=attrs, **common)
    manifest = {"env_id": "Hopper-v5", "ref_min_score": -1.0, "ref_max_score": 10.0}
    make_d4rl_file(tmp_path / "artifact.hdf5", attrs={"manifest": json.dumps(manifest)}, **common)
    make_d4rl_file(tmp_path / "hopper_medium_replay-v0.hdf5", **common)
    make_d4rl_file(tmp_path / "mystery.hdf5", **common)

    _, from_attrs = load_source(str(tmp_path / "walker_run.hdf5"))
    _, from_manifest = load_source(str(tmp_path / "artifact.hdf5"))
    _, from_name = load_source(str(tmp_path / "hopper_medium_replay-v0.hdf5"))
    _, unknown = load_source(str(tmp_path / "mystery.hdf5"))

    assert (from_attrs.env_id, from_attrs.ref_min_score, from_attrs.ref_max_score) == (
        "Walker2d-v5",
        1.5,
        99.0,
    )
    assert from_attrs.metadata["ref_scores_from"] == "dataset"
    assert (from_manifest.env_id, from_manifest.ref_max_score) == ("Hopper-v5", 10.0)
    hopper = get_task("hopper-m-r")
    assert (from_name.env_id, from_name.ref_max_score) == ("Hopper-v5", hopper.ref_max_score)
    assert from_name.metadata["ref_scores_from"] == "registry"
    assert (unknown.env_id, unknown.ref_min_score, unknown.metadata["ref_scores_from"]) == (
        None,
        None,
        None,
    )


def test_registry_matching_by_env_id_family_and_file_name():
    assert task_for_env("HalfCheetah-v4").env == "halfcheetah"
    assert task_for_env("AdroitHandPen-v1").env == "pen"
    assert registry_family("hopper-medium-v2") == "hopper"
    assert task_for_env("CartPole-v1") is None
    assert task_from_file_name("walker2d_medium_expert-v2.hdf5").name == "walker2d-m-e"
    assert task_from_file_name("notes.hdf5") is None


def test_sha256_is_stable_and_changes_with_one_value(tmp_path):
    first, second, changed = (tmp_path / name for name in ("a.hdf5", "b.hdf5", "c.hdf5"))
    truth = make_d4rl_file(first, n=30, obs_dim=4, act_dim=2, seed=5)
    make_d4rl_file(second, n=30, obs_dim=4, act_dim=2, seed=5)
    rewards = truth["rewards"].copy()
    rewards[17] += 1e-3
    make_d4rl_file(changed, n=30, obs_dim=4, act_dim=2, seed=5, rewards=rewards)

    hashes = [load_source(str(path))[1].sha256 for path in (first, first, second, changed)]

    assert hashes[0] == hashes[1] == hashes[2]
    assert hashes[3] != hashes[0]


def test_files_are_found_relative_to_the_dataset_root(dataset_root):
    (dataset_root / "artifacts").mkdir()
    make_d4rl_file(dataset_root / "artifacts" / "x.hdf5", n=12, obs_dim=3, act_dim=1, seed=0)

    transitions, info = load_source("artifacts/x.hdf5")

    assert len(transitions) == 12 and info.id == "artifacts/x.hdf5"


def test_describe_source_summarizes_counts_and_returns():
    episodes = make_episodes(3, OBS_DIM, ACT_DIM, seed=4, terminate_last=[True, False, False])
    make_minari_dataset("test/hopper/summary-v0", episodes)

    summary = describe_source("test/hopper/summary-v0")

    assert (summary["episodes"], summary["terminals"], summary["timeouts"]) == (3, 1, 2)
    assert (summary["obs_dim"], summary["act_dim"]) == (OBS_DIM, ACT_DIM)
    expected_return = np.mean(
        [e["rewards"].astype(np.float32).astype(np.float64).sum() for e in episodes]
    )
    assert summary["mean_episode_return"] == pytest.approx(expected_return, rel=1e-6)


def test_float64_observations_are_cast_once_to_float32(tmp_path):
    path = tmp_path / "f64.hdf5"
    truth = make_d4rl_file(path, n=10, obs_dim=2, act_dim=1, seed=0)
    with h5py.File(path, "a") as f:
        del f["observations"]
        f["observations"] = truth["observations"].astype(np.float64) + 1e-9

    transitions, _ = load_source(str(path))

    assert transitions.observations.dtype == np.float32
    np.testing.assert_array_equal(
        transitions.observations, (truth["observations"] + 1e-9).astype(np.float32)
    )


def test_synthetic_artifact_rows_are_not_checked_for_episode_continuity(tmp_path):
    rng = np.random.default_rng(1)
    independent = rng.normal(size=(15, 4)).astype(np.float32)
    common = dict(n=15, obs_dim=4, act_dim=2, seed=0, next_observations=independent)
    rows = make_d4rl_file(tmp_path / "episodes.hdf5", **common)
    synthetic = Transitions(
        rows["observations"],
        rows["actions"],
        rows["rewards"],
        independent,
        np.zeros(15, bool),
        np.zeros(15, bool),
    )
    diagnostics = {
        "dynamics_error": rng.random(15).astype(np.float32),
        "value": rng.random(15).astype(np.float32),
        "source_index": np.arange(15),
    }
    write_artifact(tmp_path / "artifact.hdf5", synthetic, diagnostics, {"env_id": "Hopper-v5"})

    transitions, info = load_source(str(tmp_path / "artifact.hdf5"))

    np.testing.assert_array_equal(transitions.next_observations, independent)
    assert any("synthetic artifact" in note for note in info.metadata["notes"])
    with pytest.raises(DataFormatError, match="next_observations"):
        load_source(str(tmp_path / "episodes.hdf5"))


def test_column_shaped_rewards_and_flags_and_metadata_group(tmp_path):
    path = tmp_path / "old_layout.hdf5"
    truth = make_d4rl_file(path, n=16, obs_dim=3, act_dim=1, seed=0, terminal_rows=[6])
    with h5py.File(path, "a") as f:
        for name in ("rewards", "terminals", "timeouts"):
            column = f[name][()].reshape(-1, 1)
            del f[name]
            f[name] = column
        f["metadata/algorithm"] = "SAC"
        f["metadata/policy/fc0/weight"] = np.zeros((64, 64), np.float32)

    transitions, info = load_source(str(path))

    np.testing.assert_array_equal(transitions.rewards, truth["rewards"])
    np.testing.assert_array_equal(transitions.terminals, truth["terminals"])
    assert info.metadata["file_metadata"] == {"metadata/algorithm": "SAC"}
