"""bench/artifact_values.py: each artifact's synthetic rows judged by critics trained without
them: the target gap r + γ(1 − d)V(s') − Q(s, a) against the source rows' own, and the value of
each synthetic next state against the source's next state from the same source row."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.learners import IQL, TD3BC
from hipode_pipeline.learners.iql import IQLConfig

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))
import artifact_values  # noqa: E402


def rows(n: int, seed: int, terminal_every: int = 7) -> Transitions:
    rng = np.random.default_rng(seed)
    terminals = np.zeros(n, bool)
    terminals[::terminal_every] = True
    return Transitions(
        observations=rng.normal(size=(n, 11)).astype(np.float32),
        actions=rng.uniform(-1, 1, (n, 3)).astype(np.float32),
        rewards=rng.normal(2.0, 0.5, n).astype(np.float32),
        next_observations=rng.normal(size=(n, 11)).astype(np.float32),
        terminals=terminals,
        timeouts=np.zeros(n, bool),
    )


def trained_looking(model, data: Transitions):
    """Weights moved off their initial values, so that V and Q vary from state to state."""
    model.fit_statistics(data)
    generator = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for net in (model.actor, model.critic, getattr(model, "value", None)):
            if net is not None:
                for parameter in net.parameters():
                    parameter.add_(0.3 * torch.randn(parameter.shape, generator=generator))
    return model


def by_hand(model, data: Transitions, discount: float, value_net: bool):
    """The target gap and V(s') computed here from the networks directly."""
    scale = float(getattr(model, "reward_scale", 1.0))
    with torch.no_grad():
        obs = model.normalize(torch.as_tensor(data.observations)).unsqueeze(0)
        nxt = model.normalize(torch.as_tensor(data.next_observations)).unsqueeze(0)
        if value_net:
            v = model.value(nxt)[0, :, 0]
        else:
            action = (model.config.max_action * model.actor(nxt)).clamp(-1, 1)
            v = model.critic(nxt, action).amin(1)[0]
        q = model.critic(obs, torch.as_tensor(data.actions).unsqueeze(0)).amin(1)[0]
    v, q = v.numpy() / scale, q.numpy() / scale
    return data.rewards + discount * (1 - data.terminals) * v - q, v


@pytest.mark.parametrize("kind", ["iql", "td3bc"])
def test_artifact_rows_are_judged_against_the_source_rows_by_the_referee(kind):
    source = rows(80, seed=0)
    synthetic = rows(30, seed=1, terminal_every=5)
    index = np.random.default_rng(2).integers(0, 80, 30)
    if kind == "iql":  # rewards scaled for the critic: the values come back in the data's units
        model = IQL(11, 3, IQLConfig(normalize_reward=True), seed=3)
    else:
        model = TD3BC(11, 3, seed=3)
    model = trained_looking(model, source)
    assert float(getattr(model, "reward_scale", 1.0)) != 1.0 or kind == "td3bc"
    artifact = SimpleNamespace(transitions=synthetic, diagnostics={"source_index": index})
    row = artifact_values.judge(model, source, {"hipode": artifact}, discount=0.97)

    source_gap, source_next = by_hand(model, source, 0.97, kind == "iql")
    gap, next_values = by_hand(model, synthetic, 0.97, kind == "iql")
    assert np.ptp(next_values) > 0.1  # a referee whose V varies: the lift is not trivially 0
    assert row["source_gap"] == pytest.approx(float(source_gap.mean()), rel=1e-4, abs=1e-4)
    judged = row["arms"]["hipode"]
    assert judged["gap"] == pytest.approx(float(gap.mean()), rel=1e-4, abs=1e-4)
    # each row against the gap of the source row it starts from, not the mean of all of them
    paired = float((gap - source_gap[index]).mean())
    assert abs(paired - (gap.mean() - source_gap.mean())) > 0.05
    assert judged["excess"] == pytest.approx(paired, rel=1e-4, abs=1e-4)
    # against the next state of its own source row, on the rows whose V(s') enters a target
    alive = ~synthetic.terminals
    assert 0 < alive.sum() < len(alive)
    lift = next_values[alive] - source_next[index[alive]]
    assert judged["next_state_lift"] == pytest.approx(float(lift.mean()), rel=1e-4, abs=1e-4)


def test_the_summary_spans_the_referees_and_the_table_reads_it():
    per_referee = [
        {"source_gap": 0.5, "arms": {"a": {"gap": 2.0, "excess": 1.5, "next_state_lift": 1.0}}},
        {"source_gap": 1.5, "arms": {"a": {"gap": 3.0, "excess": 1.5, "next_state_lift": 3.0}}},
    ]
    summary = artifact_values.summary(per_referee, ["a"])
    assert summary[0]["gap"] == {"mean": 2.5, "min": 2.0, "max": 3.0}
    assert summary[0]["next_state_lift"] == {"mean": 2.0, "min": 1.0, "max": 3.0}
    assert summary[1] == {"arm": "source rows", "gap": {"mean": 1.0, "min": 0.5, "max": 1.5}}
    json.dumps(summary, allow_nan=False)
    text = artifact_values.table(summary, {"a": 30, "source rows": 80}, 2)
    assert "| a | 30 | +2.5 [+2.0, +3.0] | +1.5 [+1.5, +1.5] | +2.0 [+1.0, +3.0] |" in text
    assert "| source rows | 80 | +1.0 [+0.5, +1.5] |  |  |" in text


def run(folder: Path, artifact: str | None, checksum: str | None) -> None:
    folder.mkdir(parents=True)
    record = {
        "seed": 0,
        "artifact_path": artifact,
        "artifact_checksum": checksum,
        "source_id": "local/walker2d/medium-replay-v0",
        "source_sha256": "ab" * 32,
    }
    (folder / "config.json").write_text(json.dumps(record))
    (folder / "scores.json").write_text("{}")


def test_each_arm_names_the_artifact_its_runs_trained_on(tmp_path):
    root = tmp_path / "walker2d-m-r"
    run(root / "eta0" / "td3bc-seed0", None, None)  # no artifact: not an artifact arm
    run(root / "hipode" / "td3bc-seed0", "a.hdf5", "sha256:aa")
    run(root / "hipode" / "td3bc-seed1", "a.hdf5", "sha256:aa")
    run(root / "hipode" / "iql-seed0", "b.hdf5", "sha256:bb")  # another learner's artifact
    (root / "model-rollouts" / "td3bc-seed0").mkdir(parents=True)  # unfinished: not read
    arms = artifact_values.artifact_arms(tmp_path, "td3bc")
    assert list(arms) == ["hipode"] and arms["hipode"]["artifact_path"] == "a.hdf5"
    assert artifact_values.artifact_arms(tmp_path, "iql")["hipode"]["artifact_checksum"] == (
        "sha256:bb"
    )
    run(root / "hipode" / "td3bc-seed2", "a.hdf5", "sha256:cc")  # rebuilt between runs
    with pytest.raises(DataFormatError, match="artifact_checksum.*sha256:aa"):
        artifact_values.artifact_arms(tmp_path, "td3bc")


def written_artifact(path: Path, data: Transitions, sha: str, index) -> Path:
    from hipode_pipeline.artifact import write_artifact

    diagnostics = {
        "dynamics_error": np.zeros(len(data), np.float32),
        "value": np.zeros(len(data), np.float32),
        "source_index": np.asarray(index, np.int64),
    }
    write_artifact(path, data, diagnostics, {"source": {"sha256": sha, "env_id": "Walker2d-v5"}})
    return path


def test_an_artifact_or_referee_that_does_not_fit_the_source_is_refused(tmp_path):
    from hipode_pipeline.artifact import read_manifest
    from hipode_pipeline.data.transitions import SourceInfo
    from hipode_pipeline.run_folder import save_checkpoint

    source = rows(40, seed=0)
    sha = source.sha256()
    info = SourceInfo("local/walker2d/medium-replay-v0", "Walker2d-v5", 0, 1, sha, 40, "minari")
    good = written_artifact(tmp_path / "good.hdf5", rows(10, 1), sha, np.arange(10))
    record = {
        "artifact_path": str(good),
        "artifact_checksum": read_manifest(good)["checksum"],
        "source_sha256": sha,
    }
    loaded = artifact_values.load_artifacts({"hipode": record}, source, info)
    assert len(loaded["hipode"]) == 10

    def refused(arms, match):
        with pytest.raises(DataFormatError, match=match):
            artifact_values.load_artifacts(arms, source, info)

    refused({"hipode": record | {"artifact_checksum": "sha256:00"}}, "checksum.*rebuild")
    refused({"hipode": record | {"source_sha256": "cd" * 32}}, "source_sha256")
    other = written_artifact(tmp_path / "other.hdf5", rows(10, 1), "ef" * 32, np.arange(10))
    refused(
        {
            "hipode": record
            | {"artifact_path": str(other), "artifact_checksum": read_manifest(other)["checksum"]}
        },
        "manifest.source.sha256",
    )
    for bad in ([-1] + [0] * 9, [40] + [0] * 9):  # numpy would read a negative index from the end
        wrong = written_artifact(tmp_path / f"index{bad[0]}.hdf5", rows(10, 1), sha, bad)
        arms = {
            "hipode": record
            | {"artifact_path": str(wrong), "artifact_checksum": read_manifest(wrong)["checksum"]}
        }
        refused(arms, "source_index.*0 to 39")

    folder = tmp_path / "eta0" / "iql-seed0"
    folder.mkdir(parents=True)
    model = IQL(11, 3, seed=4)
    model.fit_statistics(source)
    save_checkpoint(folder / "checkpoint.pt", {"learner": model.seed_state(0)})
    (folder / "config.json").write_text(json.dumps({"seed": 4, "source_sha256": sha}))
    referee, discount = artifact_values.load_referee(folder, source, info, "iql")
    assert referee.name == "iql" and referee.seeds == [4] and discount == pytest.approx(0.99)
    with pytest.raises(DataFormatError, match="learner.*'td3bc'"):
        artifact_values.load_referee(folder, source, info, "td3bc")
    (folder / "config.json").write_text(json.dumps({"seed": 4, "source_sha256": "cd" * 32}))
    with pytest.raises(DataFormatError, match="source_sha256"):
        artifact_values.load_referee(folder, source, info, "iql")
