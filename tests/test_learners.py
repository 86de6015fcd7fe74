"""Each learner learns a tiny continuous-control task from data, and checkpoints resume exactly."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.learners import CQL, IQL, TD3BC, CQLConfig, IQLConfig, TD3BCConfig
from hipode_pipeline.replay import MixedReplay

HORIZON = 15


def step(states: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 2-D point that must reach the origin: s' = s + 0.5 a, reward -|s'|."""
    next_states = np.clip(states + 0.5 * actions, -3, 3)
    return next_states, -np.linalg.norm(next_states, axis=1)


def rollout(policy, episodes: int = 64, seed: int = 123) -> float:
    """Mean return of `policy` ((k, 2) -> (k, 2)) over fixed starts."""
    states = np.random.default_rng(seed).uniform(-2, 2, (episodes, 2)).astype(np.float32)
    total = np.zeros(episodes)
    for _ in range(HORIZON):
        states, rewards = step(states, np.clip(policy(states), -1, 1))
        total += rewards
    return float(total.mean())


def point_task_dataset(behaviour, episodes: int, seed: int) -> Transitions:
    """Episodes of the point task under `behaviour(states, rng)` -> raw actions (clipped)."""
    rng = np.random.default_rng(seed)
    states = rng.uniform(-2, 2, (episodes, 2))
    rows = []
    for t in range(HORIZON):
        actions = np.clip(behaviour(states, rng), -1, 1)
        next_states, rewards = step(states, actions)
        rows.append((states, actions, rewards, next_states, np.full(episodes, t == HORIZON - 1)))
        states = next_states
    stack = lambda i: np.concatenate([r[i] for r in rows]).astype(np.float32)  # noqa: E731
    return Transitions(
        stack(0),
        stack(1),
        stack(2),
        stack(3),
        np.zeros(episodes * HORIZON, bool),
        stack(4).astype(bool),
    )


def scripted_dataset(episodes: int = 200, seed: int = 0) -> Transitions:
    """A noisy controller's episodes (noise large enough that the data is far from optimal)."""
    return point_task_dataset(
        lambda states, rng: -1.5 * states + rng.normal(0, 0.6, states.shape), episodes, seed
    )


def random_policy(states: np.ndarray) -> np.ndarray:
    return np.random.default_rng(7).uniform(-1, 1, states.shape)


CASES = {
    "td3bc": (TD3BC, TD3BCConfig(hidden_dim=64, discount=0.9), 500),
    "iql": (IQL, IQLConfig(hidden_dim=64, discount=0.9, max_steps=500), 500),
    "cql": (
        CQL,
        CQLConfig(hidden_dim=64, discount=0.9, policy_lr=1e-3, cql_n_actions=4, cql_alpha=1.0),
        300,
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_learner_beats_random_policy(name):
    cls, config, steps = CASES[name]
    data = scripted_dataset()
    learner = cls(2, 2, config, device="cpu", seed=0)
    learner.fit_statistics(data)
    replay = MixedReplay(data, device="cpu", seed=0)
    for _ in range(steps):
        metrics = learner.update(replay.sample(64))
    # metrics stay on the device (0-dim tensors): the driver reads them at log time
    assert all(isinstance(v, torch.Tensor) and v.dim() == 0 for v in metrics.values())
    assert all(np.isfinite(float(v)) for v in metrics.values())
    random_return = rollout(random_policy)
    data_return = rollout(lambda s: -1.5 * s)  # the controller without its noise: near-optimal
    learned_return = rollout(learner.act)
    # at least 90% of the way from random to the noiseless controller (untrained: about 35%)
    assert learned_return > random_return + 0.9 * (data_return - random_return), (
        random_return,
        learned_return,
        data_return,
    )


def _floats(metrics):
    return {name: float(value) for name, value in metrics.items()}


@pytest.mark.parametrize("name", list(CASES))
def test_state_dict_resumes_bitwise(name):
    cls, config, _ = CASES[name]
    data = scripted_dataset(episodes=20)
    first = cls(2, 2, config, device="cpu", seed=1)
    first.fit_statistics(data)
    replay = MixedReplay(data, device="cpu", seed=1)
    for _ in range(5):
        first.update(replay.sample(32))
    saved, saved_replay = first.state_dict(), replay.state_dict()
    buffer = __import__("io").BytesIO()
    torch.save(saved, buffer)
    buffer.seek(0)
    restored_state = torch.load(buffer, weights_only=True)
    expected = [_floats(first.update(replay.sample(32))) for _ in range(4)]

    second = cls(
        2, 2, config, device="cpu", seed=99
    )  # other init: everything must come from the checkpoint
    second.load_state_dict(restored_state)
    replay.load_state_dict(saved_replay)
    assert second.step == 5
    got = [_floats(second.update(replay.sample(32))) for _ in range(4)]
    assert got == expected
    for key, module in first.modules.items():
        for (n, a), (_, b) in zip(
            module.state_dict().items(), second.modules[key].state_dict().items(), strict=True
        ):
            assert torch.equal(a, b), (key, n)
    for key, opt in first.optimizers.items():
        state_a, state_b = opt.state_dict()["state"], second.optimizers[key].state_dict()["state"]
        for idx in state_a:
            for field, value in state_a[idx].items():
                assert torch.equal(value, state_b[idx][field]), (key, idx, field)


def test_act_is_deterministic_and_bounded():
    learner = CQL(2, 2, CQLConfig(hidden_dim=16), seed=0)
    obs = np.random.default_rng(0).normal(size=(5, 2)).astype(np.float32)
    first, second = learner.act(obs), learner.act(obs)
    assert first.shape == (5, 2) and np.array_equal(first, second)
    assert np.abs(first).max() <= 1.0
    assert learner.act(obs[0]).shape == (2,)


def _weights(learner) -> dict[str, torch.Tensor]:
    return {
        f"{key}.{name}": p.detach().clone()
        for key, module in learner.modules.items()
        for name, p in module.named_parameters()
    }


@pytest.mark.parametrize("name", list(CASES))
def test_seed_alone_decides_the_weights(name):
    cls, config, _ = CASES[name]
    data = scripted_dataset(episodes=20)
    replay = MixedReplay(data, device="cpu", seed=3)
    batches = [replay.sample(32) for _ in range(4)]
    first = cls(2, 2, config, device="cpu", seed=5)
    other = cls(2, 2, config, device="cpu", seed=6)  # built and updated between the twins
    twin = cls(2, 2, config, device="cpu", seed=5)
    for learner in (first, other, twin):
        learner.fit_statistics(data)
    initial, initial_other = _weights(first), _weights(other)
    # the seed reaches the initialization, not only the update's generator
    assert any(not torch.equal(initial[k], initial_other[k]) for k in initial)
    for batch in batches:  # interleaved: an update drawing from the global RNG would diverge
        for learner in (first, other, twin):
            learner.update(batch)
    after, after_twin, after_other = _weights(first), _weights(twin), _weights(other)
    differ = [k for k in after if not torch.equal(after[k], after_twin[k])]
    assert not differ, differ
    same = [k for k in after if torch.equal(after[k], after_other[k])]
    assert not same, same
    # every tensor moved (TD3+BC's actor and targets on its 2nd and 4th updates)
    unchanged = [k for k in after if torch.equal(after[k], initial[k])]
    assert not unchanged, unchanged
