"""Each learner learns a tiny continuous-control task from data, and checkpoints resume exactly."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import HipodeError
from hipode_pipeline.learners import CQL, IQL, TD3BC, CQLConfig, IQLConfig, TD3BCConfig
from hipode_pipeline.replay import Batch, MixedReplay

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
    # metrics stay on the device, one entry per seed: the driver reads them at log time
    assert all(isinstance(v, torch.Tensor) and v.shape == (1,) for v in metrics.values())
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


@pytest.mark.parametrize("name", list(CASES))
def test_stacked_seeds_follow_their_separate_runs(name):
    """K seeds in one stacked learner: each seed's losses and weights after 20 updates are those
    of a run of that seed alone (its own init, batches and draws), up to float rounding."""
    cls, config, _ = CASES[name]
    data = scripted_dataset(episodes=20)
    seeds = [4, 0, 9]
    stacked = cls(2, 2, config, device="cpu", seed=seeds)
    stacked.fit_statistics(data)
    stacked_replay = MixedReplay(data, device="cpu", seed=seeds)
    alone = []
    for seed in seeds:
        learner = cls(2, 2, config, device="cpu", seed=seed)
        learner.fit_statistics(data)
        alone.append((learner, MixedReplay(data, device="cpu", seed=seed)))
    for _ in range(20):
        metrics = stacked.update(stacked_replay.sample(32))
        single = [learner.update(replay.sample(32)) for learner, replay in alone]
        for i, seed_metrics in enumerate(single):
            for key, value in seed_metrics.items():
                torch.testing.assert_close(metrics[key][i : i + 1], value, rtol=1e-4, atol=1e-5)
    for i, (learner, _) in enumerate(alone):
        state, own = stacked.seed_state(i), learner.state_dict()
        assert state["seed"] == seeds[i] and state["step"] == own["step"] == 20
        for key, module_state in own["modules"].items():
            for param, tensor in module_state.items():
                torch.testing.assert_close(
                    state["modules"][key][param], tensor, rtol=1e-4, atol=1e-6, msg=param
                )
    # the seeds did not stay alike: the test compares different networks
    first = stacked.seed_state(0)["modules"]["critic"]["weights.0"]
    assert not torch.allclose(first, stacked.seed_state(1)["modules"]["critic"]["weights.0"])


@pytest.mark.parametrize("name", list(CASES))
def test_a_seed_of_a_stacked_run_resumes_alone_and_back(name):
    """seed_state(k) of a stacked learner is a one-seed checkpoint: loaded alone it continues
    as it would have inside the stack, and stacked again it restores the stack exactly."""
    cls, config, _ = CASES[name]
    data = scripted_dataset(episodes=20)
    seeds = [2, 5]
    stacked = cls(2, 2, config, device="cpu", seed=seeds)
    stacked.fit_statistics(data)
    replay = MixedReplay(data, device="cpu", seed=seeds)
    for _ in range(3):
        stacked.update(replay.sample(16))
    states = [stacked.seed_state(i) for i in range(2)]
    replay_states = [replay.seed_state(i) for i in range(2)]

    again = cls(2, 2, config, device="cpu", seed=[7, 8])
    again.load_seed_states(states)
    again_replay = MixedReplay(data, device="cpu", seed=[7, 8])
    again_replay.load_seed_states(replay_states)
    expected = _floats_per_seed(stacked.update(replay.sample(16)))
    assert _floats_per_seed(again.update(again_replay.sample(16))) == expected

    alone = cls(2, 2, config, device="cpu", seed=99)
    alone.load_state_dict(states[1])
    alone_replay = MixedReplay(data, device="cpu", seed=99)
    alone_replay.load_state_dict(replay_states[1])
    got = _floats_per_seed(alone.update(alone_replay.sample(16)))
    for key, values in got.items():
        assert values[0] == pytest.approx(expected[key][1], rel=1e-4, abs=1e-6), key


def _floats_per_seed(metrics):
    return {name: value.tolist() for name, value in metrics.items()}


def test_stacked_learner_refuses_a_plain_batch_and_duplicate_seeds():
    data = scripted_dataset(episodes=5)
    learner = TD3BC(2, 2, TD3BCConfig(hidden_dim=8), device="cpu", seed=[0, 1])
    plain = MixedReplay(data, device="cpu", seed=0).sample(8)
    with pytest.raises(HipodeError, match="expected a \\(K=2, B"):
        learner.update(Batch(*(field[0] for field in plain)))
    with pytest.raises(HipodeError, match="distinct training seeds"):
        TD3BC(2, 2, TD3BCConfig(hidden_dim=8), device="cpu", seed=[3, 3])


@pytest.mark.parametrize("name", list(CASES))
def test_bf16_runs_hidden_matmuls_only_and_stays_near_fp32(name):
    """bf16 changes the hidden layers' arithmetic (the results differ from fp32) while heads,
    targets and losses come out in fp32, and one update's losses stay near fp32's."""
    cls, config, _ = CASES[name]
    data = scripted_dataset(episodes=20)
    batch = MixedReplay(data, device="cpu", seed=0).sample(64)
    metrics = {}
    for bf16 in (False, True):
        learner = cls(
            2, 2, type(config)(**{**config.to_dict(), "bf16": bf16}), device="cpu", seed=0
        )
        learner.fit_statistics(data)
        assert learner.use_bf16 is bf16
        q = learner.critic(batch.observations, batch.actions)
        assert q.dtype == torch.float32
        metrics[bf16] = {key: float(value) for key, value in learner.update(batch).items()}
    assert metrics[True] != metrics[False]
    for key, value in metrics[False].items():
        assert metrics[True][key] == pytest.approx(value, rel=0.05, abs=0.05), key
