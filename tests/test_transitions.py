"""The Transitions type: content hash and per-episode returns."""

import numpy as np

from hipode_pipeline.data.transitions import Transitions


def _transitions(rewards, terminals, timeouts) -> Transitions:
    n = len(rewards)
    obs = np.arange(n * 2, dtype=np.float32).reshape(n, 2)
    return Transitions(
        observations=obs,
        actions=np.zeros((n, 1), np.float32),
        rewards=np.asarray(rewards, np.float32),
        next_observations=obs + 1,
        terminals=np.asarray(terminals, bool),
        timeouts=np.asarray(timeouts, bool),
    )


def test_episode_returns_split_on_terminals_and_timeouts_and_keep_a_trailing_episode():
    t = _transitions([1, 2, 3, 4, 5, 6], [0, 1, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0])
    np.testing.assert_allclose(t.episode_returns(), [3.0, 7.0, 11.0])


def test_sha256_changes_with_one_value():
    a = _transitions([1, 2, 3], [0, 0, 1], [0, 0, 0])
    b = _transitions([1, 2, 3.5], [0, 0, 1], [0, 0, 0])
    assert a.sha256() == _transitions([1, 2, 3], [0, 0, 1], [0, 0, 0]).sha256()
    assert a.sha256() != b.sha256()
