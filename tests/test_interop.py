"""A merged file read by D4RL's qlearning_dataset rule and by d3rlpy's episode rule: the raw
layout loses the synthetic rows to both, the interop loaders keep every one of them."""

from __future__ import annotations

import h5py
import numpy as np
from test_merge import write_source, write_synthetic

from hipode_pipeline.data.load import load_source
from hipode_pipeline.interop import d3rlpy_arrays, qlearning_dataset
from hipode_pipeline.merge import merge_files


def d4rl_rule(observations, actions, rewards, terminals, timeouts):
    """D4RL's qlearning_dataset (use_timeouts): s' of row i is observations[i + 1]; a row at a
    timeout ends its episode and is dropped; the last row has no successor."""
    rows = [i for i in range(len(observations) - 1) if not timeouts[i]]
    return {
        "observations": observations[rows],
        "actions": actions[rows],
        "next_observations": observations[np.array(rows) + 1],
        "rewards": rewards[rows],
        "terminals": terminals[rows],
    }


def d3rlpy_rule(observations, actions, rewards, terminals, timeouts):
    """d3rlpy's MDPDataset: episodes end at a terminal or a timeout; an episode of T steps gives
    T transitions when it terminated (the last one's s' is zeros) and T - 1 when it timed out."""
    out = {k: [] for k in ("observations", "actions", "rewards", "next_observations", "terminals")}
    start = 0
    for end in np.flatnonzero(terminals | timeouts):
        length, terminated = end - start + 1, bool(terminals[end])
        for t in range(length if terminated else length - 1):
            row = start + t
            last = t == length - 1
            out["observations"].append(observations[row])
            out["actions"].append(actions[row])
            out["rewards"].append(rewards[row])
            out["next_observations"].append(
                np.zeros_like(observations[row]) if last else observations[row + 1]
            )
            out["terminals"].append(terminated and last)
        start = end + 1
    return {k: np.array(v) for k, v in out.items()}


def merged_file(tmp_path):
    source = write_source(tmp_path / "source.hdf5")
    synthetic = write_synthetic(tmp_path / "art.hdf5", source, m=30)
    merge_files(str(source), tmp_path / "art.hdf5", tmp_path / "merged.hdf5")
    real, _ = load_source(str(source))
    return tmp_path / "merged.hdf5", real, synthetic


def rows_of(arrays, keys=("observations", "actions", "rewards", "next_observations")):
    return {
        tuple(np.round(np.concatenate([np.ravel(arrays[k][i]) for k in keys]), 5))
        for i in range(len(arrays["observations"]))
    }


def test_the_raw_layout_loses_synthetic_rows_to_both_rules(tmp_path):
    path, real, synthetic = merged_file(tmp_path)
    with h5py.File(path, "r") as f:
        raw = {k: f[k][()] for k in ("observations", "actions", "rewards", "terminals", "timeouts")}
    wanted = rows_of(synthetic.arrays())
    assert len(rows_of(d4rl_rule(**raw)) & wanted) == 0
    d3 = d3rlpy_rule(**raw)
    # only terminal synthetic rows survive d3rlpy's rule, and with a zero next state
    assert len(rows_of(d3) & wanted) == 0


def test_qlearning_dataset_keeps_every_synthetic_transition(tmp_path):
    path, real, synthetic = merged_file(tmp_path)
    data = qlearning_dataset(path)
    mask = data["is_synthetic"]
    assert mask.sum() == len(synthetic) == 30
    assert rows_of({k: v[mask] for k, v in data.items()}) == rows_of(synthetic.arrays())
    np.testing.assert_array_equal(data["terminals"][mask], synthetic.terminals)
    # the real rows are exactly what D4RL's own rule keeps of the source
    expected = d4rl_rule(
        real.observations, real.actions, real.rewards, real.terminals, real.timeouts
    )
    got = {k: v[~mask] for k, v in data.items()}
    assert rows_of(got) == rows_of(expected)
    assert len(got["observations"]) == len(expected["observations"]) + (
        0 if real.timeouts[-1] else 1
    )


def test_d3rlpy_arrays_survive_d3rlpys_episode_rule(tmp_path):
    path, real, synthetic = merged_file(tmp_path)
    recovered = d3rlpy_rule(**d3rlpy_arrays(path))
    open_ended = synthetic.arrays()
    keep = ~synthetic.terminals
    wanted = rows_of({k: v[keep] for k, v in open_ended.items()})
    assert wanted <= rows_of(recovered)
    # terminal synthetic transitions are kept as terminal ones (s' unused, zeros)
    terminal = rows_of(
        {k: open_ended[k][~keep] for k in ("observations", "actions", "rewards")},
        keys=("observations", "actions", "rewards"),
    )
    ends = recovered["terminals"]
    assert terminal <= rows_of(
        {k: recovered[k][ends] for k in ("observations", "actions", "rewards")},
        keys=("observations", "actions", "rewards"),
    )
    # and nothing else synthetic: real transitions plus exactly the synthetic ones
    real_rows = d3rlpy_rule(
        real.observations, real.actions, real.rewards, real.terminals, real.timeouts
    )
    assert len(recovered["observations"]) == len(real_rows["observations"]) + len(synthetic)
