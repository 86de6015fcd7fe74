"""The plain model-rollout baseline: its rows are the behaviour model's action and the dynamics
ensemble's next state from drawn source states, exactly η·N of them, every finite one kept."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from hipode_pipeline.augment import HIPODE_ONLY_UNSET, check_method
from hipode_pipeline.contract import ArtifactSettings
from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.envs import termination_rule
from hipode_pipeline.errors import SettingError
from hipode_pipeline.generate import synthetic_count
from hipode_pipeline.rollouts import RolloutConfig, model_rollouts

OBS, ACT = 11, 3
SHIFT, ACTION = 0.1, 0.3


class ShiftDynamics:
    """s'_norm = s_norm + SHIFT (+ the action's first entry), r = the action's sum; rows whose
    first state entry is above `nan_above` come back NaN."""

    def __init__(self, nan_above: float = np.inf):
        self.nan_above = nan_above
        self.calls = 0

    def sample(self, states_norm, actions, generator=None, use_mean=False):
        self.calls += 1
        next_norm = states_norm + SHIFT + actions[:, :1]
        next_norm = torch.where(states_norm[:, :1] > self.nan_above, torch.nan, next_norm)
        return next_norm, actions.sum(1)


class ConstantPolicy:
    def sample(self, states_norm, n, generator=None):
        return torch.full((len(states_norm), n, ACT), ACTION)


@dataclass
class FakeGenerators:
    normalizer: StateNormalizer
    dynamics: ShiftDynamics
    device: torch.device = torch.device("cpu")

    def value(self, states_norm):
        return states_norm.sum(-1)


def source(rows: int = 400, seed: int = 0) -> Transitions:
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(rows, OBS)).astype(np.float32)
    return Transitions(
        observations=obs,
        actions=rng.uniform(-1, 1, size=(rows, ACT)).astype(np.float32),
        rewards=rng.normal(size=rows).astype(np.float32),
        next_observations=obs + 0.01,
        terminals=np.zeros(rows, dtype=np.bool_),
        timeouts=np.zeros(rows, dtype=np.bool_),
    )


def rollouts(data, dynamics, eta=0.5, seed=0, batch_size=64):
    generators = FakeGenerators(StateNormalizer.fit(data.observations), dynamics)
    result = model_rollouts(
        generators,
        ConstantPolicy(),
        data,
        RolloutConfig(eta=eta, batch_size=batch_size),
        env_id="Hopper-v5",
        seed=seed,
        show_progress=False,
    )
    return result, generators.normalizer


def test_rows_are_the_models_step_from_source_states():
    data = source()
    result, normalizer = rollouts(data, ShiftDynamics())
    rows, diagnostics = result.transitions, result.diagnostics
    index = diagnostics["source_index"]
    assert len(rows) == synthetic_count(0.5, len(data)) == 200
    assert len(np.unique(index)) == len(index)  # η ≤ 1: no state drawn twice in one pass
    np.testing.assert_array_equal(rows.observations, data.observations[index])
    np.testing.assert_allclose(rows.actions, ACTION)
    expected_next = normalizer.denormalize(
        normalizer.normalize(data.observations[index]) + SHIFT + ACTION
    )
    np.testing.assert_allclose(rows.next_observations, expected_next, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(rows.rewards, ACT * ACTION, rtol=1e-6)
    np.testing.assert_array_equal(
        rows.terminals, termination_rule("Hopper-v5", OBS)(rows.next_observations)
    )
    assert not rows.timeouts.any()
    # a deterministic ensemble agrees with itself: the consistency check reads zero
    np.testing.assert_allclose(diagnostics["dynamics_error"], 0.0, atol=1e-6)
    np.testing.assert_allclose(
        diagnostics["value"], result.next_states_normalized.sum(1), rtol=1e-5, atol=1e-5
    )
    assert result.counts["kept"] == 200 and result.counts["nonfinite_dropped"] == 0


def test_non_finite_rollouts_are_dropped_and_replaced():
    data = source()
    result, _ = rollouts(data, ShiftDynamics(nan_above=0.5))
    assert len(result.transitions) == 200
    assert np.isfinite(result.transitions.next_observations).all()
    assert result.counts["nonfinite_dropped"] > 0
    assert result.counts["nonfinite_next_states"] == result.counts["nonfinite_dropped"]
    assert (
        result.counts["candidates"]
        == result.counts["source_states_drawn"] - result.counts["nonfinite_dropped"]
    )


def test_same_seed_same_rows_other_seed_other_states():
    data = source()
    first, _ = rollouts(data, ShiftDynamics(), seed=3)
    again, _ = rollouts(data, ShiftDynamics(), seed=3)
    other, _ = rollouts(data, ShiftDynamics(), seed=4)
    for name, array in first.transitions.arrays().items():
        np.testing.assert_array_equal(again.transitions.arrays()[name], array)
    assert not np.array_equal(first.diagnostics["source_index"], other.diagnostics["source_index"])


def test_rate_out_of_range_is_refused():
    with pytest.raises(SettingError, match="eta"):
        RolloutConfig(eta=0.0)


@pytest.mark.parametrize(
    ("given", "flag"),
    [
        ({"lam": 0.5}, "--lam"),
        ({"n": 4}, "--n"),
        ({"selection": "global"}, "--selection"),
        ({"candidates": "uniform"}, "--candidates"),
        ({"uncertainty_check": True}, "--uncertainty-check"),
        ({"project_next_state": True}, "--project-next-state"),
    ],
)
def test_hipode_settings_are_refused_for_rollouts(given, flag):
    unset = HIPODE_ONLY_UNSET
    check_method("hipode", **{**unset, **given})  # HIPODE takes them
    check_method("model-rollouts", **unset)
    with pytest.raises(SettingError, match=flag):
        check_method("model-rollouts", **{**unset, **given})


def test_unknown_method_is_refused():
    with pytest.raises(SettingError, match="--method"):
        check_method("mopo")


def test_rollout_artifacts_are_named_apart():
    hipode = ArtifactSettings(eta=0.5, lam=0.2, n=10, alpha=1.0, sigma=1.0)
    mb = ArtifactSettings(eta=0.5, lam=1.0, n=1, alpha=1.0, sigma=1.0, method="model-rollouts")
    assert "model-rollouts" in mb.stem("hopper-m-r", 0) and Path(hipode.stem("hopper-m-r", 0))
    assert "model-rollouts" not in hipode.stem("hopper-m-r", 0)
    manifest = {"hyper_parameters": {**mb.to_dict()}}
    assert ArtifactSettings.from_manifest(manifest) == mb
    del manifest["hyper_parameters"]["method"]  # files written before the baseline existed
    assert ArtifactSettings.from_manifest(manifest).method == "hipode"
