"""Learners do what behaviour cloning cannot, and real-data statistics ignore synthetic rows."""

from __future__ import annotations

import numpy as np
import pytest
import torch

# the 2-D point task of test_learners: s' = s + 0.5 a, reward -|s'|
from test_learners import point_task_dataset, rollout
from test_merge import write_source, write_synthetic
from torch import nn

from hipode_pipeline.data.load import load_source
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.learners import CQL, IQL, TD3BC, CQLConfig, IQLConfig, TD3BCConfig
from hipode_pipeline.replay import MixedReplay
from hipode_pipeline.train import run_training


def good_controller(states: np.ndarray) -> np.ndarray:
    return -1.5 * states


def two_controller_dataset(episodes: int = 200, seed: int = 0) -> Transitions:
    """Each step the behaviour flips a coin between the good controller and its mirror image
    (+1.5 s, pushing away): the mean action is ~0 in every state, so cloning it goes nowhere,
    while the rewards say which half of the actions to keep."""

    def coin_flip(states, rng):
        gain = np.where(rng.random((episodes, 1)) < 0.5, -1.5, 1.5)
        return gain * states + rng.normal(0, 0.2, states.shape)

    return point_task_dataset(coin_flip, episodes, seed)


def behaviour_cloning_return(data: Transitions) -> float:
    """The better of two BC fits (least squares on [s, 1], and an MLP after 300 MSE steps)."""
    features = lambda s: np.c_[s, np.ones(len(s))]  # noqa: E731
    weights, *_ = np.linalg.lstsq(features(data.observations), data.actions, rcond=None)
    linear = rollout(lambda s: features(s) @ weights)
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(2, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(), nn.Linear(64, 2))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    obs, actions = torch.as_tensor(data.observations), torch.as_tensor(data.actions)
    for _ in range(300):
        loss = (net(obs) - actions).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        mlp = rollout(lambda s: net(torch.as_tensor(s, dtype=torch.float32)).numpy())
    return max(linear, mlp)


# small learning-rate bump so 1000 updates suffice; cql_alpha 1 as in test_learners (10 is
# unstable on this task in so few updates)
CASES = {
    "td3bc": (TD3BC, TD3BCConfig(hidden_dim=64, discount=0.9, actor_lr=1e-3, critic_lr=1e-3), 1000),
    "iql": (
        IQL,
        IQLConfig(
            hidden_dim=64,
            discount=0.9,
            actor_lr=1e-3,
            critic_lr=1e-3,
            value_lr=1e-3,
            max_steps=1000,
        ),
        1000,
    ),
    "cql": (
        CQL,
        CQLConfig(
            hidden_dim=64,
            discount=0.9,
            policy_lr=1e-3,
            critic_lr=1e-3,
            cql_n_actions=4,
            cql_alpha=1.0,
        ),
        800,
    ),
}


@pytest.fixture(scope="module")
def two_controllers():
    data = two_controller_dataset()
    return data, behaviour_cloning_return(data), rollout(good_controller)


@pytest.mark.parametrize("name", list(CASES))
def test_learner_beats_behaviour_cloning(name, two_controllers):
    data, bc_return, good_return = two_controllers
    # the task itself: cloning the data's mean action is far from the good controller
    assert bc_return < good_return - 15, (bc_return, good_return)
    cls, config, steps = CASES[name]
    learner = cls(2, 2, config, device="cpu", seed=0)
    learner.fit_statistics(data)
    replay = MixedReplay(data, device="cpu", seed=0)
    for _ in range(steps):
        learner.update(replay.sample(64))
    learned = rollout(learner.act)
    # at least 80% of the way from BC to the good controller (measured: about 88-98%)
    assert learned > bc_return + 0.8 * (good_return - bc_return), (bc_return, learned, good_return)


# ---- statistics from real rows only, with synthetic rows in the replay --------------------------
SHIFT = 1000.0


def shifted(real: Transitions) -> Transitions:
    """Synthetic rows far from the real ones: states and rewards +1000, one long episode."""
    n = len(real)
    return Transitions(
        real.observations[::-1] + SHIFT,
        real.actions[::-1].copy(),
        real.rewards[::-1] + SHIFT,
        real.next_observations[::-1] + SHIFT,
        np.zeros(n, bool),
        np.eye(1, n, n - 1, dtype=bool)[0],
    )


def real_statistics(real: Transitions) -> tuple[np.ndarray, np.ndarray, float]:
    """Mean, std + 1e-3 and 1000 / (max - min episode return), computed here from the rows."""
    obs = real.observations.astype(np.float64)
    ends = np.flatnonzero(real.terminals | real.timeouts) + 1
    returns = [
        chunk.sum() for chunk in np.split(real.rewards.astype(np.float64), ends) if chunk.size
    ]
    return obs.mean(0), obs.std(0) + 1e-3, 1000.0 / (max(returns) - min(returns))


MAKERS = {
    "td3bc": lambda: TD3BC(2, 2, TD3BCConfig(hidden_dim=16), device="cpu", seed=0),
    "iql": lambda: IQL(
        2, 2, IQLConfig(hidden_dim=16, normalize_reward=True, max_steps=10), device="cpu", seed=0
    ),
    "cql": lambda: CQL(2, 2, CQLConfig(hidden_dim=16, cql_n_actions=3), device="cpu", seed=0),
}


@pytest.mark.parametrize("name", list(MAKERS))
def test_statistics_come_from_real_rows_with_synthetic_rows_present(name):
    real = two_controller_dataset(episodes=20)
    synthetic = shifted(real)
    replay = MixedReplay(real, synthetic, eta=0.5, device="cpu", seed=0)
    learner, alone = MAKERS[name](), MAKERS[name]()
    # as train.py does: statistics from the real part, the replay holding both
    learner.fit_statistics(real)
    alone.fit_statistics(two_controller_dataset(episodes=20))
    mean, std, reward_scale = real_statistics(real)
    union_mean, _, union_scale = real_statistics(Transitions.concatenate([real, synthetic]))
    assert np.abs(union_mean - mean).min() > 400  # the synthetic rows would move them
    np.testing.assert_allclose(learner.state_mean.numpy(), mean, rtol=1e-5)
    np.testing.assert_allclose(learner.state_std.numpy(), std, rtol=1e-5)
    assert torch.equal(learner.state_mean, alone.state_mean)
    assert torch.equal(learner.state_std, alone.state_std)
    normalized = learner.normalize(torch.as_tensor(real.observations))
    np.testing.assert_allclose(normalized.mean(0).numpy(), 0.0, atol=1e-4)
    if name == "iql":
        assert abs(union_scale - reward_scale) > 0.01 * reward_scale
        assert learner.reward_scale == pytest.approx(reward_scale, rel=1e-9)
        assert learner.reward_scale == alone.reward_scale

    batch = replay.sample(64)
    assert int((batch.observations[0, :, 0] > SHIFT / 2).sum()) == 32  # half the rows synthetic
    for _ in range(2):  # TD3+BC's actor moves on its second update
        metrics = learner.update(batch)
    assert all(np.isfinite(float(v)) for v in metrics.values()), metrics
    for module in learner.modules.values():
        assert all(torch.isfinite(p).all() for p in module.parameters())


def test_iql_leaves_rewards_unscaled_by_default():
    learner = IQL(2, 2, IQLConfig(hidden_dim=16), device="cpu", seed=0)
    learner.fit_statistics(two_controller_dataset(episodes=20))
    assert learner.reward_scale == 1.0


def test_training_run_fits_statistics_on_the_source_rows_only(tmp_path, monkeypatch):
    source = write_source(tmp_path / "source.hdf5")
    write_synthetic(tmp_path / "art.hdf5", source)
    seen, fit = [], IQL.fit_statistics

    def recording(self, real):
        seen.append(real)
        fit(self, real)

    monkeypatch.setattr(IQL, "fit_statistics", recording)
    result = run_training(
        "hopper-m-r",
        "iql",
        steps=2,
        eval_every=2,
        eval_episodes=1,
        out_dir=tmp_path / "runs",
        source=str(source),
        artifact=tmp_path / "art.hdf5",
        batch_size=16,
        learner_settings={"normalize_reward": True},
        show_progress=False,
    )
    assert result.steps == 2 and result.eta > 0  # batches held synthetic rows
    real, _ = load_source(str(source), announce=False)
    assert len(seen) == 1 and seen[0].sha256() == real.sha256()
