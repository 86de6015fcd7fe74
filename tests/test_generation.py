"""Generation keeps exactly round(eta*N) transitions, and they are the lambda fraction with the
smallest dynamics error, checked against a row-by-row reference on stand-in generators."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.envs import terminal_flags
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.generate import (
    GenerationConfig,
    SourceOrder,
    generate,
    keep_count,
    novelty,
    synthetic_count,
)

OBS_DIM, ACT_DIM, N_SOURCE = 11, 3, 500
PARAMS = torch.Generator().manual_seed(123)
OFFSETS = torch.randn(16, OBS_DIM, generator=PARAMS) * 0.5
VALUE_W = torch.randn(OBS_DIM, generator=PARAMS)
ACTION_W = torch.randn(OBS_DIM, ACT_DIM, generator=PARAMS)
DYNAMICS_W = torch.randn(ACT_DIM, OBS_DIM, generator=PARAMS) * 0.3


class StandIn:
    """Generators-like models made of closed-form functions: deterministic when noise is 0, and
    NaN on chosen rows so that dropping can be checked."""

    def __init__(self, normalizer: StateNormalizer, noise: float = 0.0):
        self.noise = noise
        self.normalizer = normalizer
        self.device = torch.device("cpu")
        self.state_transition = SimpleNamespace(sample=self._next_states)
        self.inverse_action = SimpleNamespace(sample=self._actions)
        self.inverse_reward = SimpleNamespace(sample=self._rewards)
        self.dynamics = SimpleNamespace(sample=self._dynamics)

    def _jitter(self, shape, generator):
        return self.noise * torch.randn(shape, generator=generator) if self.noise else 0.0

    def _next_states(self, cond, num_samples, generator=None):
        k = torch.arange(num_samples, dtype=cond.dtype)
        scale = 1 + 0.5 * torch.sin(cond.sum(-1, keepdim=True) + k)  # (B, n)
        out = cond[:, None, :] + OFFSETS[:num_samples] * scale[..., None]
        out = out + self._jitter(out.shape, generator)
        out[cond[:, 0] > 1.2] = torch.nan  # every candidate broken: the row is dropped
        out[cond[:, 1] > 0.8, 0, 3] = torch.inf  # one candidate broken: another one wins
        return out

    def value(self, states):
        return states @ VALUE_W

    def _actions(self, cond, num_samples, generator=None):
        delta = cond[:, OBS_DIM:] - cond[:, :OBS_DIM]
        actions = torch.tanh(delta @ ACTION_W)[:, None, :].expand(-1, num_samples, -1)
        return actions + self._jitter(actions.shape, generator)

    def _rewards(self, cond, num_samples, generator=None):
        return cond[:, OBS_DIM:].sum(-1)[:, None, None].expand(-1, num_samples, 1)

    def _dynamics(self, states, actions, generator=None, use_mean=False):
        next_states = states + torch.tanh(actions @ DYNAMICS_W) + 0.1 * torch.cos(3 * states)
        if not use_mean:
            next_states = next_states + self._jitter(next_states.shape, generator)
        return next_states, torch.zeros(len(states))


def _source(seed: int = 0) -> Transitions:
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(N_SOURCE, OBS_DIM)).astype(np.float32)
    obs[:, 0] = rng.uniform(
        0.6, 1.6, N_SOURCE
    )  # Hopper torso height, so both terminal outcomes occur
    obs[:, 1] = rng.uniform(-0.3, 0.3, N_SOURCE)
    return Transitions(
        observations=obs,
        actions=rng.uniform(-1, 1, (N_SOURCE, ACT_DIM)).astype(np.float32),
        rewards=rng.normal(size=N_SOURCE).astype(np.float32),
        next_observations=obs + 0.1,
        terminals=np.zeros(N_SOURCE, dtype=bool),
        timeouts=np.zeros(N_SOURCE, dtype=bool),
    )


def _reference_row(s: np.ndarray, n: int):
    """One source state by hand: (dynamics error, argmax-V candidate), None if none is finite."""
    s_t = torch.as_tensor(s)[None]
    candidates = StandIn(None)._next_states(s_t, n)[0]
    best, best_value = None, -math.inf
    for i in range(n):
        if torch.isfinite(candidates[i]).all() and float(candidates[i] @ VALUE_W) > best_value:
            best, best_value = i, float(candidates[i] @ VALUE_W)
    if best is None:
        return None
    action = torch.tanh((candidates[best] - s_t[0]) @ ACTION_W)
    dyna = s_t[0] + torch.tanh(action @ DYNAMICS_W) + 0.1 * torch.cos(3 * s_t[0])
    return float(torch.linalg.vector_norm(dyna - candidates[best])), best


def _reference(source, normalizer, config, seed):
    """Brute-force selection: (kept source indices in output order, their errors, dropped)."""
    order = SourceOrder(len(source), seed)
    states_norm = normalizer.normalize(source.observations)
    target = synthetic_count(config.eta, len(source))
    pool_target = math.ceil(target / config.lam - 1e-9) if config.selection == "global" else target
    kept, pool, dropped, collected = [], [], 0, 0
    while collected < pool_target:
        rows = []
        for position, index in enumerate(order.take(min(config.batch_size, len(source)))):
            row = _reference_row(states_norm[index], config.n)
            if row is None:
                dropped += 1
            else:
                rows.append((row[0], position, int(index)))
        if config.selection == "global":
            pool.extend((error, len(pool) + p, index) for error, p, index in rows)
            collected += len(rows)
            continue
        rows.sort()
        keep = min(keep_count(len(rows), config.lam), target - collected)
        kept.extend(rows[:keep])
        collected += keep
    if config.selection == "global":
        kept = sorted(pool)[:target]
    return [index for _, _, index in kept], np.array([error for error, _, _ in kept]), dropped


@pytest.mark.parametrize("selection", ["batch", "global"])
def test_selection_matches_brute_force(selection):
    source = _source()
    normalizer = StateNormalizer.fit(source.observations)
    config = GenerationConfig(eta=0.5, lam=0.2, n=4, batch_size=64, selection=selection)
    result = generate(
        StandIn(normalizer), source, config, env_id="Hopper-v5", seed=7, show_progress=False
    )
    indices, errors, dropped = _reference(source, normalizer, config, seed=7)

    assert len(result.transitions) == synthetic_count(0.5, N_SOURCE) == 250
    assert result.counts["kept"] == 250
    # more than one pass over the source, so repeated passes are exercised too
    assert result.counts["source_states_drawn"] > N_SOURCE
    assert result.diagnostics["source_index"].tolist() == indices
    np.testing.assert_allclose(result.diagnostics["dynamics_error"], errors, rtol=1e-5, atol=1e-6)
    assert result.counts["nonfinite_dropped"] == dropped > 0
    if selection == "batch":
        # every batch keeps about lam of what it ranked; global selection is free to differ
        per_batch = np.bincount(result.diagnostics["batch_index"])
        assert per_batch[:-1].max() <= math.floor(0.2 * 64 + 0.5)


def test_non_finite_candidates_are_dropped_counted_and_skipped_by_argmax():
    source = _source()
    normalizer = StateNormalizer.fit(source.observations)
    config = GenerationConfig(eta=0.4, lam=1.0, n=4, batch_size=100)
    result = generate(
        StandIn(normalizer), source, config, env_id="Hopper-v5", seed=0, show_progress=False
    )
    assert len(result.transitions) == 200
    for array in (*result.transitions.arrays().values(), *result.diagnostics.values()):
        assert np.isfinite(array.astype(np.float64)).all()
    states_norm = normalizer.normalize(source.observations)
    broken_rows = states_norm[:, 0] > 1.2
    assert not broken_rows[result.diagnostics["source_index"]].any()
    # rows with a broken first candidate still produce a transition, from another candidate
    partly_broken = (states_norm[result.diagnostics["source_index"], 1] > 0.8) & ~broken_rows[
        result.diagnostics["source_index"]
    ]
    assert partly_broken.any()
    assert (result.diagnostics["candidate_index"][partly_broken] != 0).all()
    drawn = result.counts["source_states_drawn"]
    assert result.counts["nonfinite_dropped"] == drawn - result.counts["candidates"] > 0
    assert result.counts["nonfinite_next_states"] >= 4 * result.counts["nonfinite_dropped"]


def test_transitions_hold_raw_values_and_env_terminals():
    source = _source()
    normalizer = StateNormalizer.fit(source.observations)
    config = GenerationConfig(eta=0.3, lam=0.5, n=3, batch_size=50)
    result = generate(
        StandIn(normalizer), source, config, env_id="Hopper-v5", seed=1, show_progress=False
    )
    t = result.transitions
    np.testing.assert_array_equal(
        t.observations, source.observations[result.diagnostics["source_index"]]
    )
    np.testing.assert_allclose(
        t.next_observations, normalizer.denormalize(result.next_states_normalized), rtol=1e-6
    )
    np.testing.assert_array_equal(t.terminals, terminal_flags("Hopper-v5", t.next_observations))
    assert 0 < t.terminals.sum() < len(t)
    assert not t.timeouts.any()
    assert t.observations.dtype == t.next_observations.dtype == t.actions.dtype == np.float32


def test_same_seed_gives_identical_arrays_and_another_seed_does_not():
    source = _source()
    normalizer = StateNormalizer.fit(source.observations)
    config = GenerationConfig(eta=0.2, lam=0.2, n=5, batch_size=128)

    def run(seed):
        return generate(
            StandIn(normalizer, noise=0.05),
            source,
            config,
            env_id="Hopper-v5",
            seed=seed,
            show_progress=False,
        )

    first, second, other = run(3), run(3), run(4)
    for name, array in first.transitions.arrays().items():
        np.testing.assert_array_equal(array, second.transitions.arrays()[name])
    for name, array in first.diagnostics.items():
        np.testing.assert_array_equal(array, second.diagnostics[name])
    assert not np.array_equal(first.transitions.actions, other.transitions.actions)


def test_uniform_candidates_stay_in_the_source_box():
    source = _source()
    normalizer = StateNormalizer.fit(source.observations)
    config = GenerationConfig(eta=0.2, lam=0.5, n=6, batch_size=100, candidates="uniform")
    result = generate(
        StandIn(normalizer), source, config, env_id="Hopper-v5", seed=0, show_progress=False
    )
    states_norm = normalizer.normalize(source.observations)
    assert len(result.transitions) == 100
    assert (result.next_states_normalized >= states_norm.min(0) - 1e-5).all()
    assert (result.next_states_normalized <= states_norm.max(0) + 1e-5).all()
    assert result.counts["nonfinite_dropped"] == 0


def test_novelty_is_the_distance_to_the_nearest_source_state():
    rng = np.random.default_rng(0)
    source_norm = torch.as_tensor(rng.normal(size=(700, 5)).astype(np.float32))
    synthetic = rng.normal(size=(50, 5)).astype(np.float32)
    distances = novelty(synthetic, source_norm, sample=50, chunk=64)
    brute = np.sqrt(((synthetic[:, None, :] - source_norm.numpy()[None]) ** 2).sum(-1)).min(1)
    np.testing.assert_allclose(distances, brute, rtol=1e-4)
    assert novelty(synthetic, source_norm, sample=20).shape == (20,)


def test_unknown_env_fails_before_generating():
    source = _source()
    normalizer = StateNormalizer.fit(source.observations)
    with pytest.raises(DataFormatError, match="env_id"):
        generate(StandIn(normalizer), source, GenerationConfig(), env_id=None, show_progress=False)
