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
    assert judged["excess"] == pytest.approx(float(gap.mean() - source_gap.mean()), abs=1e-4)
    lift = next_values - source_next[index]  # against the next state of its own source row
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
