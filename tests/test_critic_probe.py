"""bench/critic_probe.py: a finished run's critic read back from its checkpoint and valued at
the source's falls (the smaller twin Q, as TD3 bootstraps) and against its own policy's return
in the simulator; a run of another source refused."""

from __future__ import annotations

import json
import os
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
from hipode_pipeline.run_folder import save_checkpoint

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))
import critic_probe  # noqa: E402


def source(n=60, seed=0) -> Transitions:
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, 11)).astype(np.float32)
    terminals = np.zeros(n, bool)
    terminals[[9, 29, 59]] = True
    timeouts = np.zeros(n, bool)
    timeouts[27] = True  # an episode cut by its time limit two rows before the next fall
    return Transitions(
        observations=obs,
        actions=rng.uniform(-1, 1, (n, 3)).astype(np.float32),
        rewards=rng.normal(2.0, 0.5, n).astype(np.float32),
        next_observations=np.roll(obs, -1, 0),
        terminals=terminals,
        timeouts=timeouts,
    )


def finished_run(
    folder: Path, data: Transitions, sha: str, q_first: float, q_second: float, model=None
):
    """A run folder whose twin critics are constants (their output layers zeroed but the bias)."""
    if model is None:
        model = TD3BC(data.obs_dim, data.act_dim, seed=3)
    model.fit_statistics(data)
    with torch.no_grad():
        model.critic.weights[-1].zero_()
        model.critic.biases[-1][:, 0].fill_(q_first)
        model.critic.biases[-1][:, 1].fill_(q_second)
    folder.mkdir(parents=True)
    save_checkpoint(folder / "checkpoint.pt", {"learner": model.seed_state(0)})
    record = {
        "seed": 3,
        "steps": int(model.step),
        "source_id": "local/hopper/medium-replay-v0",
        "source_sha256": sha,
    }
    (folder / "config.json").write_text(json.dumps(record))
    (folder / "scores.json").write_text("{}")
    return record


def test_falls_are_valued_by_the_smaller_twin(tmp_path):
    data = source()
    config = finished_run(
        tmp_path / "hopper-m-r" / "hipode" / "td3bc-seed3", data, "ab" * 32, 7.0, 5.0
    )
    (tmp_path / "hopper-m-r" / "eta0" / "td3bc-seed0").mkdir(parents=True)  # unfinished: skipped
    folders = critic_probe.run_folders(tmp_path)
    assert [f.parent.name for f in folders] == ["hipode"]
    sources = {"local/hopper/medium-replay-v0": (data, SimpleNamespace(sha256="ab" * 32))}
    row = critic_probe.probe(folders[0], config, sources, states=0)
    falls = data.rewards[data.terminals]
    assert (row["arm"], row["seed"], row["rows"], row["falls"]) == ("hipode", 3, 60, 3)
    assert row["q_mean"] == pytest.approx(5.0) and row["q_falls"] == pytest.approx(5.0)
    assert row["reward_falls"] == pytest.approx(float(falls.mean()))
    assert row["fall_overestimate"] == pytest.approx(5.0 - float(falls.mean()))
    # five rows before the falls at 9 and 59, one before 29 (row 27 ended its own episode)
    expected = []
    for fall, before in ((9, 5), (29, 1), (59, 5)):
        for j in range(fall - 1, fall - 1 - before, -1):
            expected.append(
                sum(0.99 ** (m - j) * float(data.rewards[m]) for m in range(j, fall + 1))
            )
    assert row["rows_before_falls"] == len(expected) == 11
    assert row["q_before_falls"] == pytest.approx(5.0)
    assert row["return_to_fall"] == pytest.approx(np.mean(expected), rel=1e-5)
    assert "| hipode | 3 |" in critic_probe.table([row])
    assert "q_policy" not in row and "return of π" not in critic_probe.table([row])


def test_a_source_without_falls_gets_no_fall_values(tmp_path):
    data = source()
    data.terminals[:] = False  # HalfCheetah never falls
    config = finished_run(
        tmp_path / "halfcheetah-m-r" / "eta0" / "td3bc-seed3", data, "ab" * 32, 4.0, 6.0
    )
    sources = {"local/hopper/medium-replay-v0": (data, SimpleNamespace(sha256="ab" * 32))}
    row = critic_probe.probe(
        tmp_path / "halfcheetah-m-r" / "eta0" / "td3bc-seed3", config, sources, states=0
    )
    assert row["falls"] == 0 and row["rows_before_falls"] == 0
    assert all(row[key] is None for key in critic_probe.FALL_KEYS)
    assert row["q_mean"] == pytest.approx(4.0)
    json.dumps(row, allow_nan=False)  # the record stays strict JSON: no NaN for missing falls
    text = critic_probe.table([row])
    assert "No falls" in text and "| eta0 | 3 | 0 | 4.0 |" in text and "nan" not in text


def test_iql_runs_are_probed_apart_in_the_datas_reward_units(tmp_path):
    data = source()
    model = IQL(data.obs_dim, data.act_dim, IQLConfig(normalize_reward=True), seed=3)
    folder = tmp_path / "hopper-m-r" / "hipode" / "iql-seed3"
    config = finished_run(folder, data, "ab" * 32, 8.0, 9.0, model=model)
    finished_run(tmp_path / "hopper-m-r" / "hipode" / "td3bc-seed3", data, "ab" * 32, 1.0, 1.0)
    assert critic_probe.run_folders(tmp_path, "iql") == [folder]
    assert [f.name for f in critic_probe.run_folders(tmp_path)] == ["td3bc-seed3"]
    scale = model.reward_scale
    assert scale != 1.0  # the critic learned rewards times this scale
    sources = {"local/hopper/medium-replay-v0": (data, SimpleNamespace(sha256="ab" * 32))}
    row = critic_probe.probe(folder, config, sources, states=0)
    assert row["q_mean"] == pytest.approx(8.0 / scale, rel=1e-5)
    assert row["fall_overestimate"] == pytest.approx(
        8.0 / scale - float(data.rewards[data.terminals].mean()), rel=1e-5
    )


def test_a_run_of_another_source_is_refused(tmp_path):
    data = source()
    config = finished_run(tmp_path / "run", data, "cd" * 32, 1.0, 1.0)
    sources = {"local/hopper/medium-replay-v0": (data, SimpleNamespace(sha256="ab" * 32))}
    with pytest.raises(DataFormatError, match="source_sha256"):
        critic_probe.probe(tmp_path / "run", config, sources, states=0)


def hopper_source(steps=120, seed=2) -> Transitions:
    """Real Hopper-v5 rows (random actions), so that the simulator can restore their states."""
    import gymnasium as gym

    env = gym.make("Hopper-v5")
    rng = np.random.default_rng(seed)
    observation, _ = env.reset(seed=seed)
    rows = []
    for t in range(steps):
        action = rng.uniform(-1, 1, 3).astype(np.float32)
        next_observation, reward, terminated, truncated, _ = env.step(action)
        rows.append((observation, action, reward, next_observation, terminated, truncated))
        observation = next_observation
        if terminated or truncated:
            observation, _ = env.reset(seed=seed + t + 1)
    env.close()
    obs, act, rew, nxt, term, trunc = (np.array(c) for c in zip(*rows, strict=True))
    return Transitions(
        observations=obs.astype(np.float32),
        actions=act,
        rewards=rew.astype(np.float32),
        next_observations=nxt.astype(np.float32),
        terminals=term,
        timeouts=trunc,
    )


def test_the_critic_is_checked_against_its_policys_return_in_the_simulator(tmp_path):
    from hipode_pipeline.simulator import clipped_velocity_rows, policy_returns

    data = hopper_source()
    # a trained-looking run: actor and critics moved away from their initial weights, so a
    # probe that rebuilt a fresh learner, or valued the data's actions, would be found out
    model = TD3BC(data.obs_dim, data.act_dim, seed=3)
    model.fit_statistics(data)
    generator = torch.Generator().manual_seed(11)
    with torch.no_grad():
        for parameter in [*model.actor.parameters(), *model.critic.parameters()]:
            parameter.add_(0.3 * torch.randn(parameter.shape, generator=generator))
    folder = tmp_path / "eta0" / "td3bc-seed3"
    folder.mkdir(parents=True)
    save_checkpoint(folder / "checkpoint.pt", {"learner": model.seed_state(0)})
    config = {
        "seed": 3,
        "source_id": "local/hopper/medium-replay-v0",
        "source_sha256": "ab" * 32,
        "env_id": "Hopper-v5",
    }
    sources = {"local/hopper/medium-replay-v0": (data, SimpleNamespace(sha256="ab" * 32))}
    row = critic_probe.probe(folder, config, sources, 6, 25)

    starts = critic_probe.start_states(data, "Hopper-v5", 6)
    assert (
        len(starts) == 6 and not clipped_velocity_rows("Hopper-v5", data.observations[starts]).any()
    )
    assert np.array_equal(starts, critic_probe.start_states(data, "Hopper-v5", 6))  # seeded
    observations = data.observations[starts]
    with torch.no_grad():
        obs = model.normalize(torch.as_tensor(observations)).unsqueeze(0)
        on_policy = torch.as_tensor(model.act(observations)).unsqueeze(0)
        q = model.critic(obs, on_policy).amin(1)[0].numpy()
        q_data = model.critic(obs, torch.as_tensor(data.actions[starts]).unsqueeze(0)).amin(1)
    returns, steps = policy_returns("Hopper-v5", observations, model.act, horizon=25, discount=0.99)
    assert (row["states"], row["horizon"]) == (6, 25)
    assert row["q_policy"] == pytest.approx(float(q.mean()), rel=1e-5)
    assert abs(float(q_data.mean()) - float(q.mean())) > 1e-3  # Q(s, π(s)), not Q(s, a)
    assert row["return_policy"] == pytest.approx(float(returns.mean()))
    assert row["q_policy_overestimate"] == pytest.approx(float((q - returns).mean()), rel=1e-5)
    assert row["falls_within_horizon"] == int((steps < 25).sum())
    # the columns a carried row drops when the check settings change are exactly the check's
    unchecked = critic_probe.probe(folder, config, sources, states=0)
    assert set(row) - set(unchecked) == set(critic_probe.POLICY_KEYS)
    assert f"| eta0 | 3 | {row['q_policy']:.1f} |" in critic_probe.table([row])


def test_rows_of_runs_whose_checkpoints_are_gone_are_carried_with_their_probe_date(tmp_path):
    data = source()
    sha = "ab" * 32
    root = tmp_path / "hopper-m-r"
    arms = ("eta0", "hipode", "lam1", "longer", "retrained", "checked")
    configs = {arm: finished_run(root / arm / "td3bc-seed3", data, sha, 1.0, 1.0) for arm in arms}
    sources = {"local/hopper/medium-replay-v0": (data, SimpleNamespace(sha256=sha))}
    now = critic_probe.probe(root / "hipode" / "td3bc-seed3", configs["hipode"], sources, states=0)
    assert now["source_sha256"] == sha and now["step"] == configs["hipode"]["steps"]
    old = {arm: {**now, "run": str(root / arm / "td3bc-seed3"), "arm": arm} for arm in arms}
    old["deleted"] = {**now, "run": str(root / "deleted" / "td3bc-seed3"), "arm": "deleted"}
    # written relative to the repository by another invocation: still the same run
    old["eta0"]["run"] = os.path.relpath(root / "eta0" / "td3bc-seed3", critic_probe.REPO)
    old["hipode"].update(run=os.path.relpath(now["run"], critic_probe.REPO), q_mean=-1.0)
    old["retrained"]["source_sha256"] = "cd" * 32  # trained on another source since
    old["checked"].update(  # checked at another setting
        q_policy=1.0,
        return_policy=2.0,
        q_policy_overestimate=-1.0,
        falls_within_horizon=0,
        states=6,
        horizon=25,
    )
    for arm in ("eta0", "lam1", "longer", "retrained", "checked"):
        (root / arm / "td3bc-seed3" / "checkpoint.pt").unlink()  # gone with their machine
    (root / "lam1" / "td3bc-seed3" / "scores.json").unlink()  # no longer finished
    config = root / "longer" / "td3bc-seed3" / "config.json"
    config.write_text(json.dumps({**json.loads(config.read_text()), "steps": 10**6}))
    report = tmp_path / "critic_probe.json"
    report.write_text(json.dumps({"date_utc": "2026-12-04 06:18", "runs": list(old.values())}))

    fresh = [{**now, "probed_utc": "2026-12-05 11:40"}]
    previous = critic_probe.previous_report(report)
    kept = critic_probe.carried_rows(previous, fresh, 0, 500)
    # hipode: the fresh row, not the old one
    assert [row["arm"] for row in kept] == ["eta0", "checked"]
    assert kept[0]["probed_utc"] == "2026-12-04 06:18" and kept[0]["q_mean"] == now["q_mean"]
    dates = critic_probe.probe_dates(fresh + kept)
    assert dates == "2026-12-04 06:18 UTC: 2 runs; 2026-12-05 11:40 UTC: 1 run"
    # the falls columns hold under any check; the policy check's only at its own setting
    assert kept[1]["q_mean"] == now["q_mean"] and "q_policy" not in kept[1]
    assert "return of π" not in critic_probe.table(fresh + kept)
    same = critic_probe.carried_rows(previous, fresh, 6, 25)
    assert [r["arm"] for r in same] == ["eta0", "checked"]
    assert "q_policy" not in same[0] and same[1]["q_policy"] == 1.0
    assert "| checked | 3 | 1.0 |" in critic_probe.table(same)
    for states, horizon in ((6, 500), (5, 25)):
        other = critic_probe.carried_rows(previous, fresh, states, horizon)
        assert [r["arm"] for r in other] == ["eta0", "checked"]
        assert not any(key in r for r in other for key in critic_probe.POLICY_KEYS)

    report.write_text(json.dumps({"date_utc": "x", "runs": [{"run": "a", "arm": "eta0"}]}))
    with pytest.raises(DataFormatError, match="runs.*each with run, arm, seed, step"):
        critic_probe.previous_report(report)
    report.write_text(json.dumps({"runs": []}))
    with pytest.raises(DataFormatError, match="date_utc"):
        critic_probe.previous_report(report)
    report.write_text("[not json")
    with pytest.raises(DataFormatError, match="unreadable JSON"):
        critic_probe.previous_report(report)


def iql_with_known_advantage(data: Transitions, q: float) -> IQL:
    """An IQL learner whose target critics are the constant `q` and whose value is
    relu(first normalized state dimension): its advantage at each row is known in closed form."""
    model = IQL(data.obs_dim, data.act_dim, IQLConfig(), seed=3)
    model.fit_statistics(data)
    with torch.no_grad():
        model.critic_target.weights[-1].zero_()
        model.critic_target.biases[-1].fill_(q)
        for weight, bias in zip(model.value.weights, model.value.biases, strict=True):
            weight.zero_()
            bias.zero_()
            weight[:, 0, 0] = 1.0  # feature 0 of the state passes through every layer
    return model


def write_synthetic(path: Path, synthetic: Transitions) -> dict:
    """`synthetic` as an artifact file, with the diagnostics the contract asks for."""
    from hipode_pipeline.artifact import write_artifact

    n = len(synthetic)
    diagnostics = {
        "dynamics_error": np.zeros(n, np.float32),
        "value": np.zeros(n, np.float32),
        "source_index": np.arange(n),
    }
    return write_artifact(path, synthetic, diagnostics, {})


def test_iql_actor_weights_are_the_capped_advantage_and_the_synthetic_share_reweights_the_batch(
    tmp_path,
):
    data = source()
    synthetic = source(seed=1)
    synthetic.observations[:, 0] = -50.0  # normalized far below zero: V = 0 on every synthetic row
    model = iql_with_known_advantage(data, q=2.0)
    folder = tmp_path / "walker2d-m-r" / "hipode" / "iql-seed3"
    config = finished_run(folder, data, "ab" * 32, 2.0, 2.0, model=model)
    # finished_run set the online critic; the actor weights read the target critic
    assert float(model.critic_target.biases[-1].min()) == 2.0
    artifact = tmp_path / "synthetic.hdf5"
    stored = write_synthetic(artifact, synthetic)
    config |= {
        "artifact_path": str(artifact),
        "artifact_checksum": stored["checksum"],
        "n_real": len(data),
        "n_synthetic": len(synthetic),
        "eta": 0.2,
        "batch_size": 256,
        "mixing": "mixed",
    }
    (folder / "config.json").write_text(json.dumps(config))
    artifacts = critic_probe.run_artifacts({folder: config})
    sources = {"local/hopper/medium-replay-v0": (data, SimpleNamespace(sha256="ab" * 32))}
    row = critic_probe.probe(folder, config, sources, states=0, artifacts=artifacts)

    normalized = model.normalize(torch.as_tensor(data.observations)).numpy()
    expected = np.minimum(np.exp(3.0 * (2.0 - np.maximum(normalized[:, 0], 0.0))), 100.0)
    assert 0 < (expected >= 100.0).mean() < 1  # some source rows at the cap, some below
    assert row["weight_source"] == pytest.approx(expected.mean(), rel=1e-5)
    assert row["capped_source"] == pytest.approx((expected >= 100.0).mean())
    assert row["weight_synthetic"] == pytest.approx(100.0)  # exp(3 · 2) is past the cap
    assert row["capped_synthetic"] == 1.0
    share = 51 / 256  # round(0.2 · 256) synthetic rows per batch
    assert row["synthetic_batch_share"] == share
    pulled = share * 100.0
    assert row["synthetic_actor_share"] == pytest.approx(
        pulled / (pulled + (1 - share) * expected.mean()), rel=1e-5
    )
    assert critic_probe.actor_table([row]) in critic_probe.table([row])
    assert "| hipode | 3 |" in critic_probe.actor_table([row])

    union = config | {"mixing": "union"}
    assert critic_probe.synthetic_batch_share(union) == 60 / 120
    eta0 = config | {"eta": 0.0, "n_synthetic": 0}
    assert "synthetic_actor_share" not in critic_probe.probe(
        folder, eta0, sources, states=0, artifacts=artifacts
    )


def test_an_artifact_other_than_the_runs_own_is_refused(tmp_path):
    artifact = tmp_path / "synthetic.hdf5"
    write_synthetic(artifact, source(seed=1))
    config = {
        "artifact_path": str(artifact),
        "artifact_checksum": "sha256:" + "0" * 64,
        "n_synthetic": 60,
        "eta": 0.2,
    }
    with pytest.raises(DataFormatError, match="checksum"):
        critic_probe.run_artifacts({tmp_path / "iql-seed0": config})
