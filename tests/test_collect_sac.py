"""SAC as the behaviour-policy trainer, D4RL-sized medium-replay histories, and a missed target
searched on under a grown budget: real MuJoCo, tiny budgets."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import hipode_pipeline.data.collect as collect_module
from hipode_pipeline.cli import app
from hipode_pipeline.data.collect import collect, load_recipe, subsample_in_order, work_dir
from hipode_pipeline.data.policies import load_policy
from hipode_pipeline.data.ppo import RolloutBlock
from hipode_pipeline.data.sac import SACConfig, SACTrainer, SquashedActor, TanhGaussianPolicy
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.tasks import get_task

TINY = SACConfig(num_envs=2, rollout_steps=8, hidden=16, batch_size=16, start_steps=32)


def _metadata(root, dataset_id: str) -> dict:
    return json.loads((root / dataset_id / "data" / "metadata.json").read_text())


def test_squashed_log_prob_matches_torch_transformed_distribution():
    torch.manual_seed(0)
    low, high = np.array([-2.0, -1.0, 0.0]), np.array([2.0, 1.0, 4.0])
    actor = SquashedActor(5, 3, 8, low, high)
    obs, noise = 0.3 * torch.randn(64, 5), 0.3 * torch.randn(64, 3)
    actions, log_prob = actor(obs, noise)
    mean, log_std = actor.net(obs).chunk(2, -1)
    std = log_std.clamp(-5, 2).exp()
    scale, center = torch.tensor((high - low) / 2), torch.tensor((high + low) / 2)
    reference = torch.distributions.TransformedDistribution(
        torch.distributions.Normal(mean.double(), std.double()),
        [
            torch.distributions.TanhTransform(),
            torch.distributions.AffineTransform(center, scale),
        ],
    )
    expected = reference.log_prob(actions.double()).sum(-1)  # inverts tanh: no saturated rows
    torch.testing.assert_close(log_prob.double(), expected, rtol=1e-3, atol=1e-3)
    assert torch.all(actions > torch.tensor(low)) and torch.all(actions < torch.tensor(high))


def test_numpy_snapshot_acts_as_the_torch_actor():
    trainer = SACTrainer("HalfCheetah-v5", TINY, 0)
    obs = np.random.default_rng(1).standard_normal((7, trainer.envs.obs_dim))
    noise = np.random.default_rng(2).standard_normal((7, trainer.envs.act_dim))
    policy = TanhGaussianPolicy.from_state_dict(trainer.policy().state_dict())
    mean, log_std = policy.mean_log_std(obs)
    torch_actions, _ = trainer.actor(torch.as_tensor(obs).float(), torch.as_tensor(noise).float())
    np.testing.assert_allclose(
        np.tanh(mean + np.exp(log_std) * noise), torch_actions.detach().numpy(), atol=1e-5
    )
    deterministic = policy.sample(obs, np.random.default_rng(3), deterministic=True)
    np.testing.assert_allclose(deterministic, np.tanh(mean))


def test_sac_resumes_bit_for_bit_and_learns_a_q_function():
    straight = SACTrainer("HalfCheetah-v5", TINY, 3)
    for _ in range(8):
        straight.train_iteration()
    assert straight.updates == math.floor((8 * 16 - 32) * TINY.updates_per_step)

    first = SACTrainer("HalfCheetah-v5", TINY, 3)
    for _ in range(5):
        first.train_iteration()
    state = first.state_dict()
    resumed = SACTrainer("HalfCheetah-v5", TINY, 3)
    resumed.load_state_dict(state)
    for _ in range(3):
        resumed.train_iteration()
    assert resumed.steps == straight.steps == 128 and resumed.buffer.size == 128
    for a, b in zip(resumed.actor.parameters(), straight.actor.parameters(), strict=True):
        assert torch.equal(a, b)
    for a, b in zip(resumed.target.parameters(), straight.target.parameters(), strict=True):
        assert torch.equal(a, b)
    np.testing.assert_array_equal(resumed.envs.obs, straight.envs.obs)
    # the critics moved away from their start and the temperature adapts
    assert float(straight.log_temperature.detach()) != 0.0

    other = SACConfig(**{**TINY.to_dict(), "tau": 0.01})
    with pytest.raises(Exception, match="SAC config"):
        SACTrainer("HalfCheetah-v5", other, 3).load_state_dict(state)


def test_halfcheetah_collects_with_sac(dataset_root):
    recipe = load_recipe("halfcheetah", "quick")
    assert recipe.trainer == "sac"
    result = CliRunner().invoke(app, ["collect", "halfcheetah-m-r", "--profile", "quick", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["transitions"] == recipe.medium_max_steps
    meta = _metadata(dataset_root, "local/halfcheetah/medium-replay-v0")
    assert meta["algorithm_name"] == "SAC"
    assert meta["hipode"]["seeds"]["trainer"] == "sac"
    work = work_dir(dataset_root, "halfcheetah", 0)
    assert (work / "sac.pt").exists() and not (work / "ppo.pt").exists()
    policy, info = load_policy(work / "policy-medium.pt")
    assert isinstance(policy, TanhGaussianPolicy) and info["train_steps"] == 1024

    # the medium rollouts act with the SAC policy: actions strictly inside the bounds
    medium = collect(get_task("halfcheetah-m"), profile="quick", show_progress=False)
    assert medium.transitions == recipe.medium_size
    import minari

    actions = np.concatenate(
        [e.actions for e in minari.load_dataset(medium.dataset_ids[0]).iterate_episodes()]
    )
    assert np.abs(actions).max() < 1.0 and actions.std() > 0.05


def _block(lengths_per_env: list[list[int]]) -> RolloutBlock:
    """A (step, env) block whose env streams are episodes of the given lengths; each step's
    reward is its step index, so kept episodes reveal when they started."""
    steps = sum(lengths_per_env[0])
    n = len(lengths_per_env)
    ends = np.zeros((steps, n), bool)
    for env, lengths in enumerate(lengths_per_env):
        assert sum(lengths) == steps
        ends[np.cumsum(lengths) - 1, env] = True
    rewards = np.repeat(np.arange(steps, dtype=float)[:, None], n, axis=1)
    return RolloutBlock(
        observations=np.zeros((steps, n, 2)),
        actions=np.zeros((steps, n, 1), np.float32),
        rewards=rewards,
        next_observations=np.zeros((steps, n, 2)),
        terminations=ends,
        truncations=np.zeros((steps, n), bool),
    )


def test_long_histories_are_subsampled_in_order_to_d4rl_size():
    block = _block([[10] * 100, [20] * 50, [25] * 40])  # 3,000 transitions, 190 episodes
    kept, record = subsample_in_order(block, 600, 1.5)
    total = sum(len(e["rewards"]) for e in kept)
    assert abs(total - 600) <= 25 and record["kept_transitions"] == total
    starts = [e["rewards"][0] for e in kept]
    assert starts == sorted(starts), "kept episodes follow training time"
    # spread over the whole history, not its first fifth
    assert starts[0] < 100 and starts[-1] > 800
    assert all(len(e["rewards"]) in (10, 20, 25) for e in kept), "whole episodes only"
    # at most 1.5x D4RL's size, or no size: the history is kept whole
    assert subsample_in_order(block, 2000, 1.5)[1] is None
    assert len(subsample_in_order(block, 0, 1.5)[0]) == 190


def test_a_missed_medium_target_is_searched_on_under_a_grown_budget(dataset_root, monkeypatch):
    real = collect_module.load_recipe
    budget = {"steps": 512}

    def recipe(env, profile="full", path=None):
        base = real(env, profile, path)
        return dataclasses.replace(
            base, medium_band=(1000.0, 1001.0), medium_max_steps=budget["steps"]
        )

    monkeypatch.setattr(collect_module, "load_recipe", recipe)
    runner = CliRunner()
    first = runner.invoke(app, ["collect", "hopper-m-r", "--profile", "quick"])
    assert first.exit_code == 3 and "training goes on" in " ".join(first.output.split())
    dataset = "local/hopper/medium-replay-v0"
    assert _metadata(dataset_root, dataset)["total_steps"] == 512
    before = np.load(work_dir(dataset_root, "hopper", 0) / "replay" / f"{0:012d}.npz")

    # the same budget: nothing to search on, the off-band dataset is reported again as it is
    again = runner.invoke(app, ["collect", "hopper-m-r", "--profile", "quick"])
    assert again.exit_code == 3 and _metadata(dataset_root, dataset)["total_steps"] == 512

    budget["steps"] = 1024
    grown = runner.invoke(app, ["collect", "hopper-m-r", "--profile", "quick"])
    assert grown.exit_code == 3, grown.output  # still off-band (the band is unreachable)
    meta = _metadata(dataset_root, dataset)
    assert meta["total_steps"] == 1024
    assert meta["hipode"]["training"]["medium"]["train_steps"] == 1024
    work = work_dir(dataset_root, "hopper", 0)
    assert int(torch.load(work / "ppo.pt", weights_only=True)["steps"]) == 1024
    after = np.load(work / "replay" / f"{0:012d}.npz")
    np.testing.assert_array_equal(before["rewards"], after["rewards"][: len(before["rewards"])])


def test_bfloat16_matmuls_train_in_float32_weights_and_outputs():
    with pytest.raises(ValueError, match="matmul_dtype"):
        SACConfig(matmul_dtype="float16")
    with pytest.raises(DataFormatError, match="collect.toml: field 'matmul_dtype'.*'float16'"):
        SACConfig.from_dict({"matmul_dtype": "float16"}, "collect.toml")
    fast = dataclasses.replace(TINY, matmul_dtype="bfloat16")
    plain, mixed = SACTrainer("HalfCheetah-v5", TINY, 5), SACTrainer("HalfCheetah-v5", fast, 5)
    obs, actions = torch.randn(32, plain.envs.obs_dim), torch.rand(32, plain.envs.act_dim)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        q_mixed = mixed.critic(obs, actions)
        _, log_prob = mixed.actor(obs, torch.randn(32, plain.envs.act_dim))
    q_plain = plain.critic(obs, actions)
    # the output layers run in float32, the hidden ones in bfloat16: close, not equal
    assert q_mixed.dtype == log_prob.dtype == torch.float32
    assert not torch.equal(q_mixed, q_plain)
    torch.testing.assert_close(q_mixed, q_plain, rtol=0.05, atol=0.05)
    for _ in range(6):
        plain.train_iteration()
        mixed.train_iteration()
    assert mixed.updates == plain.updates > 0
    assert all(p.dtype == torch.float32 for p in mixed.critic.parameters())
    pairs = zip(mixed.actor.parameters(), plain.actor.parameters(), strict=True)
    moved = [not torch.equal(a, b) for a, b in pairs]
    assert any(moved)  # the same seed and data: only the matmul precision differs
    assert load_recipe("halfcheetah").sac.matmul_dtype == "bfloat16"
