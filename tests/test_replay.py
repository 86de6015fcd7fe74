"""η-mixed batches hold exactly the requested synthetic fraction; sampling is seeded."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import HipodeError
from hipode_pipeline.replay import MixedReplay


def marked(n: int, value: float, obs_dim: int = 3) -> Transitions:
    """Transitions whose every number is `value`, so a sampled row shows where it came from."""
    full = lambda *shape: np.full(shape, value, np.float32)  # noqa: E731
    return Transitions(
        full(n, obs_dim),
        full(n, 2),
        full(n),
        full(n, obs_dim),
        np.zeros(n, bool),
        np.zeros(n, bool),
    )


@pytest.mark.parametrize(("eta", "batch"), [(0.2, 256), (0.5, 256), (0.05, 100), (0.7, 33)])
def test_mixed_batches_hold_round_eta_b_synthetic_rows(eta, batch):
    replay = MixedReplay(marked(1000, 1.0), marked(50, -1.0), eta=eta, seed=0)
    for _ in range(5):
        b = replay.sample(batch)
        synthetic = (b.observations[0, :, 0] == -1.0).sum().item()
        assert synthetic == round(eta * batch)
        assert torch.equal(b.rewards[0] == -1.0, b.observations[0, :, 0] == -1.0)  # rows stay whole


def test_eta_zero_never_touches_synthetic_data():
    replay = MixedReplay(marked(100, 1.0), marked(100, -1.0), eta=0.0, seed=0)
    assert replay.n_synthetic == 0 and replay.data.shape[0] == 100
    assert (replay.sample(512).observations == 1.0).all()


def test_union_sampling_is_uniform_over_all_rows():
    replay = MixedReplay(marked(300, 1.0), marked(100, -1.0), eta=0.0, mixing="union", seed=0)
    fractions = [
        (replay.sample(1000).observations[0, :, 0] == -1.0).float().mean().item() for _ in range(20)
    ]
    assert abs(np.mean(fractions) - 0.25) < 0.02
    assert np.std(fractions) > 0  # the count varies per batch, unlike mixed batches


def test_same_seed_same_batches_and_state_restores():
    data = Transitions(
        *(
            np.random.default_rng(0).normal(size=s).astype(np.float32)
            for s in [(50, 3), (50, 2), (50,), (50, 3)]
        ),
        np.zeros(50, bool),
        np.zeros(50, bool),
    )
    a, b = MixedReplay(data, seed=3), MixedReplay(data, seed=3)
    assert torch.equal(a.sample(16).actions, b.sample(16).actions)
    state = a.state_dict()
    expected = a.sample(16).observations
    a.load_state_dict(state)
    assert torch.equal(a.sample(16).observations, expected)


def test_dones_are_terminals_not_timeouts():
    n = 10
    t = Transitions(
        np.zeros((n, 1), np.float32),
        np.zeros((n, 1), np.float32),
        np.zeros(n, np.float32),
        np.zeros((n, 1), np.float32),
        np.arange(n) == 3,
        np.arange(n) == 5,
    )
    replay = MixedReplay(t, seed=0)
    assert replay.data[:, -1].tolist() == [float(i == 3) for i in range(n)]


def test_bad_settings_fail_clearly():
    with pytest.raises(HipodeError, match="no synthetic"):
        MixedReplay(marked(10, 1.0), None, eta=0.5)
    with pytest.raises(HipodeError, match=r"\[0, 1\]"):
        MixedReplay(marked(10, 1.0), marked(10, 1.0), eta=1.5)
    with pytest.raises(HipodeError, match="obs/act dims"):
        MixedReplay(marked(10, 1.0), marked(10, 1.0, obs_dim=4), eta=0.5)


def test_each_seed_draws_the_rows_a_run_of_that_seed_alone_draws():
    data = marked(500, 1.0)
    data = Transitions(
        np.arange(500, dtype=np.float32)[:, None].repeat(3, 1),
        data.actions,
        data.rewards,
        data.next_observations,
        data.terminals,
        data.timeouts,
    )
    stacked = MixedReplay(data, marked(40, -1.0), eta=0.25, seed=[5, 1, 8])
    alone = [MixedReplay(data, marked(40, -1.0), eta=0.25, seed=s) for s in (5, 1, 8)]
    for _ in range(3):
        batch = stacked.sample(20)
        assert batch.observations.shape == (3, 20, 3) and batch.rewards.shape == (3, 20)
        for k, replay in enumerate(alone):
            assert torch.equal(batch.observations[k], replay.sample(20).observations[0])
    assert not torch.equal(batch.observations[0], batch.observations[1])
