"""The fitting levers of stage one, each an option off by default: plateau stopping with best
weights kept, budgets in passes over the data, ensemble elites, penalty units, the paper
profile. Each test fails when its option is ignored."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_models import train
from torch import nn

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import SettingError
from hipode_pipeline.models import training
from hipode_pipeline.models.dynamics import DynamicsEnsemble
from hipode_pipeline.models.generators import (
    GeneratorConfig,
    elite_members,
    fit_settings,
    train_generators,
)
from hipode_pipeline.models.value import ValueEstimator


def noisy_line(n: int = 4000, seed: int = 0) -> training.TensorData:
    """y = 2x + noise: a linear model reaches the noise floor within a few hundred steps."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 1))
    y = 2 * x + rng.normal(size=(n, 1))
    tensors = {"x": torch.tensor(x, dtype=torch.float32), "y": torch.tensor(y, dtype=torch.float32)}
    return training.TensorData(tensors, 0.2, 4096, seed)


def fit_line(tmp_path, *, patience: int, steps: int = 3000, name: str = "line"):
    with training.seeded_init(0):
        model = nn.Linear(1, 1)

    def loss(batch, generator):
        value = (model(batch["x"]) - batch["y"]).pow(2).mean()
        return value, value

    def heldout(batch):
        return (model(batch["x"]) - batch["y"]).pow(2).mean()

    record = train(
        name,
        model,
        loss,
        heldout,
        data,
        tmp_path,
        steps=steps,
        batch_size=64,
        lr=1e-2,
        eval_every=20,
        keep_best="model",
        plateau_patience=patience,
        plateau_tolerance=1e-3,
    )
    with torch.no_grad():
        final = float(heldout(data.heldout()))
    return record, final


data = noisy_line()


def test_plateau_stopping_ends_early_and_keeps_the_best_weights(tmp_path):
    stopped, stopped_loss = fit_line(tmp_path, patience=5)
    full, _ = fit_line(tmp_path, patience=0, name="full")
    assert full.steps == 3000 and not full.stopped_on_plateau
    assert stopped.stopped_on_plateau and stopped.steps < 1500 and stopped.budget_steps == 3000
    # the weights left loaded are the best ones seen, and as good as the whole budget's
    assert stopped_loss == pytest.approx(stopped.best_heldout_loss, rel=1e-6)
    assert stopped.best_heldout_loss < 1.05 * full.best_heldout_loss


def test_plateau_stopping_needs_kept_weights(tmp_path):
    with pytest.raises(ValueError, match="best weights"):
        train(
            "x",
            nn.Linear(1, 1),
            lambda b, g: (torch.zeros(()), torch.zeros(())),
            lambda b: torch.zeros(()),
            data,
            tmp_path,
            steps=10,
            keep_best="none",
            plateau_patience=2,
        )


def test_epoch_budgets_scale_with_the_dataset():
    paper = GeneratorConfig.profile
    fixed = fit_settings(paper("paper"), train_rows=100_000)
    scaled = fit_settings(paper("paper", budget_epochs=3.0), train_rows=100_000)
    small = fit_settings(paper("paper", budget_epochs=3.0), train_rows=10_000)
    assert fixed["state_transition"]["steps"] == 30_000 and fixed["dynamics"]["steps"] == 30_000
    for name in ("state_transition", "inverse_action", "inverse_reward", "dynamics"):
        assert scaled[name]["steps"] == math.ceil(3.0 * 100_000 / 256)
        assert small[name]["steps"] == math.ceil(3.0 * 10_000 / 256)
    # the value net's TD loss moves with its target: it keeps its fixed budget
    assert scaled["value"]["steps"] == small["value"]["steps"] == 50_000
    stopping = fit_settings(paper("paper", plateau_patience=4), train_rows=10)
    assert stopping["dynamics"]["plateau_patience"] == 4
    assert stopping["inverse_action"]["plateau_patience"] == 4
    assert "plateau_patience" not in stopping["value"]


def test_the_ensemble_can_keep_its_own_budget_and_stopping():
    cvaes_only = GeneratorConfig(
        budget_epochs=3.0,
        plateau_patience=4,
        dynamics_steps=70_000,
        dynamics_budget_epochs=0.0,
        dynamics_plateau_patience=0,
    )
    settings = fit_settings(cvaes_only, train_rows=100_000)
    assert settings["inverse_action"]["steps"] == math.ceil(3.0 * 100_000 / 256)
    assert settings["inverse_action"]["plateau_patience"] == 4
    assert settings["dynamics"]["steps"] == 70_000
    assert settings["dynamics"]["plateau_patience"] == 0
    own = fit_settings(
        GeneratorConfig(
            budget_epochs=3.0, dynamics_budget_epochs=9.0, dynamics_plateau_patience=20
        ),
        train_rows=100_000,
    )
    assert own["dynamics"]["steps"] == math.ceil(9.0 * 100_000 / 256)
    assert own["dynamics"]["plateau_patience"] == 20
    # the CVAEs' cache keys ignore the ensemble's own settings; the ensemble's follows them
    base = GeneratorConfig(budget_epochs=3.0, plateau_patience=4)
    assert cvaes_only.model_key("inverse_action") == base.model_key("inverse_action")
    assert cvaes_only.model_key("dynamics") != base.model_key("dynamics")
    for bad in ({"dynamics_plateau_patience": -2}, {"dynamics_budget_epochs": -0.5}):
        with pytest.raises(SettingError, match=next(iter(bad))):
            GeneratorConfig(**bad)


def ensemble_with_member_offsets(offsets: list[float]) -> DynamicsEnsemble:
    """Members that predict delta s = offset (constant per member) with tiny noise."""
    model = DynamicsEnsemble(2, 1, members=len(offsets), hidden=(4,))
    with torch.no_grad():
        for p in model.parameters():
            p.zero_()
        model.mean_head.bias.copy_(torch.tensor(offsets).view(-1, 1, 1).expand(-1, 1, 3))
        model.log_std_head.bias.fill_(-9.0)
        model.min_log_std.fill_(-10.0)
    return model.eval()


def test_elites_alone_are_sampled():
    model = ensemble_with_member_offsets([0.0, 1.0, 2.0, 3.0])
    states, actions = torch.zeros(500, 2), torch.zeros(500, 1)
    generator = torch.Generator().manual_seed(0)
    everyone, _ = model.sample(states, actions, generator=generator)
    assert set(np.round(everyone[:, 0].numpy()).tolist()) == {0.0, 1.0, 2.0, 3.0}
    model.set_elites([1, 3])
    elites, _ = model.sample(states, actions, generator=generator)
    assert set(np.round(elites[:, 0].numpy()).tolist()) == {1.0, 3.0}
    mean, _ = model.sample(states, actions, use_mean=True)
    assert torch.allclose(mean[:, 0], torch.full((500,), 2.0), atol=1e-3)


def test_elites_are_the_lowest_heldout_members():
    config = GeneratorConfig(dynamics_members=7, dynamics_elites=5)
    losses = [0.9, 0.1, 0.5, 0.3, 0.8, 0.2, 0.4]
    assert elite_members(losses, config) == [1, 2, 3, 5, 6]
    assert elite_members(losses, GeneratorConfig(dynamics_members=7)) is None
    with pytest.raises(SettingError, match="dynamics_elites"):
        GeneratorConfig(dynamics_members=5, dynamics_elites=6)


def test_trained_ensemble_uses_its_elites(tmp_path):
    rng = np.random.default_rng(0)
    n = 1500
    s = rng.normal(size=(n, 3)).astype(np.float32)
    a = rng.uniform(-1, 1, size=(n, 2)).astype(np.float32)
    transitions = Transitions(
        s, a, s[:, 0].copy(), s + 0.1 * a[:, :1], np.zeros(n, bool), np.zeros(n, bool)
    )
    config = GeneratorConfig.profile(
        "quick",
        cvae_hidden=16,
        value_hidden=16,
        dynamics_hidden=(16,),
        dynamics_members=4,
        dynamics_elites=2,
    )
    gen = train_generators(
        transitions, "ab" * 32, config, cache_root=tmp_path, seed=0, show_progress=False
    )
    losses = gen.training_report["dynamics"]["member_best_heldout_losses"]
    assert len(losses) == 4
    assert gen.dynamics.elites == sorted(np.argsort(losses, kind="stable")[:2].tolist())
    # loaded from the cache, the same elites
    again = train_generators(
        transitions, "ab" * 32, config, cache_root=tmp_path, seed=0, show_progress=False
    )
    assert again.dynamics.elites == gen.dynamics.elites


def test_value_scaled_penalty_uses_the_spread_of_the_target_values():
    torch.manual_seed(0)
    raw = ValueEstimator(3, hidden=16, penalty="target", alpha=2.0, sigma=1.0)
    scaled = ValueEstimator(3, hidden=16, penalty="target", penalty_scale="value", alpha=2.0)
    scaled.load_state_dict(raw.state_dict())
    with torch.no_grad():
        # values in the hundreds, as on a locomotion task
        for model in (raw, scaled):
            model.net[2].weight.mul_(300.0)
            model.target[2].weight.mul_(300.0)
    s, r = torch.randn(256, 3), torch.randn(256)
    s_next, terminal = torch.randn(256, 3), torch.zeros(256)

    def expected(unit: torch.Tensor) -> torch.Tensor:
        generator = torch.Generator().manual_seed(5)
        offset = (torch.rand(s.shape, generator=generator) * 2 - 1) * 1.0
        with torch.no_grad():
            target_values = raw.target(s).squeeze(-1)
            anchor = target_values - 2.0 * unit * offset.norm(dim=-1)
            td = raw.td_loss(s, r, s_next, terminal)
            return td + (raw(s + offset) - anchor).pow(2).mean()

    spread = raw.target(s).squeeze(-1).std().detach()
    assert spread > 10  # the two units differ on this batch
    total_raw, _ = raw.loss(s, r, s_next, terminal, torch.Generator().manual_seed(5))
    total_scaled, _ = scaled.loss(s, r, s_next, terminal, torch.Generator().manual_seed(5))
    assert torch.allclose(total_raw, expected(torch.ones(())), rtol=1e-5)
    assert torch.allclose(total_scaled, expected(spread), rtol=1e-5)
    assert not torch.allclose(total_raw, total_scaled, rtol=1e-2)


def test_value_scale_needs_the_target_penalty():
    with pytest.raises(SettingError, match="penalty_scale"):
        GeneratorConfig(penalty="l2", penalty_scale="value")


def test_paper_profile_keeps_the_appendix_sizes_whatever_the_defaults():
    paper = GeneratorConfig.profile("paper")
    assert (paper.cvae_hidden, paper.latent_per_state_dim, paper.value_hidden) == (750, 2, 256)
    assert (paper.dynamics_members, paper.dynamics_hidden) == (5, (256, 256))
    assert (paper.dynamics_elites, paper.plateau_patience, paper.budget_epochs) == (0, 0, 0.0)
    assert paper.penalty_scale == "raw"
    assert (paper.dynamics_steps, paper.dynamics_plateau_patience) == (30_000, -1)
    # the defaults: CVAEs on epoch budgets stopped on a plateau, the ensemble on its own steps
    full = fit_settings(GeneratorConfig.profile("full"), train_rows=100_000)
    assert full["inverse_action"]["steps"] == math.ceil(60 * 100_000 / 256)
    assert full["inverse_action"]["plateau_patience"] == 8
    assert (full["dynamics"]["steps"], full["dynamics"]["plateau_patience"]) == (60_000, 0)
    quick = fit_settings(GeneratorConfig.profile("quick"), train_rows=100_000)
    assert quick["inverse_action"]["steps"] == quick["dynamics"]["steps"] == 300
    # overrides still win over the profile
    assert GeneratorConfig.profile("paper", cvae_hidden=64).cvae_hidden == 64


def test_predictive_variance_is_the_members_variance_plus_their_disagreement():
    model = ensemble_with_member_offsets([0.0, 1.0, 2.0, 3.0])
    model.set_reward_scale(10.0, 2.0)
    mean, variance = model.predictive(torch.zeros(3, 2), torch.zeros(3, 1))
    assert torch.allclose(mean[:, :2], torch.full((3, 2), 1.5))
    assert torch.allclose(mean[:, 2], torch.full((3,), 10.0 + 2.0 * 1.5))  # raw reward
    assert torch.allclose(variance, torch.full((3, 3), 1.25), atol=1e-6)
    model.set_elites([0, 1])
    _, variance = model.predictive(torch.zeros(3, 2), torch.zeros(3, 1))
    assert torch.allclose(variance, torch.full((3, 3), 0.25), atol=1e-6)


def test_uncertainty_check_ranks_in_the_ensembles_own_stds():
    from test_generation import DYNAMICS_W, StandIn, _source

    from hipode_pipeline.data.normalizer import StateNormalizer
    from hipode_pipeline.generate import GenerationConfig, generate

    # the ensemble is unsure about dimension 0 only: errors there count a tenth as much
    scale = torch.ones(11)
    scale[0] = 100.0

    class Uncertain(StandIn):
        def __init__(self, normalizer):
            super().__init__(normalizer)
            self.dynamics.predictive = self._predictive

        def _predictive(self, states, actions):
            delta = torch.tanh(actions @ DYNAMICS_W) + 0.1 * torch.cos(3 * states)
            mean = torch.cat([delta, torch.zeros(len(states), 1)], dim=1)
            return mean, torch.cat([scale, torch.ones(1)]).expand(len(states), -1)

    source = _source()
    normalizer = StateNormalizer.fit(source.observations)
    config = GenerationConfig(eta=0.3, lam=0.2, n=4, batch_size=64, uncertainty_check=True)
    result = generate(
        Uncertain(normalizer), source, config, env_id="Hopper-v5", seed=3, show_progress=False
    )
    rows = result.diagnostics["source_index"]
    states = torch.as_tensor(normalizer.normalize(source.observations[rows]))
    candidates = torch.as_tensor(result.next_states_normalized)
    actions = torch.as_tensor(result.transitions.actions)
    predicted = states + torch.tanh(actions @ DYNAMICS_W) + 0.1 * torch.cos(3 * states)
    by_hand = ((predicted - candidates).pow(2) / scale).mean(1).sqrt()
    np.testing.assert_allclose(result.diagnostics["dynamics_error"], by_hand, rtol=1e-4)
    plain = generate(
        Uncertain(normalizer),
        source,
        GenerationConfig(eta=0.3, lam=0.2, n=4, batch_size=64),
        env_id="Hopper-v5",
        seed=3,
        show_progress=False,
    )
    assert set(plain.diagnostics["source_index"]) != set(rows)


def test_projected_next_state_is_the_ensembles_mean_for_the_chosen_action():
    from test_generation import DYNAMICS_W, StandIn, _source

    from hipode_pipeline.data.normalizer import StateNormalizer
    from hipode_pipeline.generate import GenerationConfig, generate

    class WithPredictive(StandIn):
        def __init__(self, normalizer):
            super().__init__(normalizer)
            self.dynamics.predictive = lambda states, actions: (
                torch.cat(
                    [
                        torch.tanh(actions @ DYNAMICS_W) + 0.1 * torch.cos(3 * states),
                        torch.zeros(len(states), 1),
                    ],
                    dim=1,
                ),
                torch.ones(len(states), 12),
            )

    source = _source()
    normalizer = StateNormalizer.fit(source.observations)
    config = GenerationConfig(eta=0.3, lam=0.2, n=4, batch_size=64, project_next_state=True)
    result = generate(
        WithPredictive(normalizer), source, config, env_id="Hopper-v5", seed=3, show_progress=False
    )
    plain = generate(
        WithPredictive(normalizer),
        source,
        GenerationConfig(eta=0.3, lam=0.2, n=4, batch_size=64),
        env_id="Hopper-v5",
        seed=3,
        show_progress=False,
    )
    # the same rows are kept (ranking is unchanged), with the model's next state written
    np.testing.assert_array_equal(
        result.diagnostics["source_index"], plain.diagnostics["source_index"]
    )
    states = torch.as_tensor(
        normalizer.normalize(source.observations[result.diagnostics["source_index"]])
    )
    actions = torch.as_tensor(result.transitions.actions)
    expected = states + torch.tanh(actions @ DYNAMICS_W) + 0.1 * torch.cos(3 * states)
    np.testing.assert_allclose(result.next_states_normalized, expected, rtol=1e-5, atol=1e-6)
    assert not np.allclose(plain.next_states_normalized, expected)


def test_cosine_schedule_decays_the_step_size_to_zero(tmp_path):
    def step_sizes(schedule: str) -> list[float]:
        with training.seeded_init(0):
            model = nn.Linear(1, 1)
        sizes, previous = [], [model.weight.detach().clone()]

        def loss(batch, generator):
            value = (model(batch["x"]) - batch["y"]).pow(2).mean()
            return value, value

        def record_step(step: int) -> None:
            now = model.weight.detach().clone()
            sizes.append(float((now - previous[0]).abs()))
            previous[0] = now

        train(
            f"cosine-{schedule}",
            model,
            loss,
            lambda batch: (model(batch["x"]) - batch["y"]).pow(2).mean(),
            data,
            tmp_path,
            steps=400,
            batch_size=64,
            lr=1e-2,
            after_step=record_step,
            lr_schedule=schedule,
        )
        return sizes

    constant, cosine = step_sizes("constant"), step_sizes("cosine")
    assert len(constant) == len(cosine) == 400
    # the same start; cosine's steps are about half of constant's mid-way and near zero at the end
    assert cosine[0] == pytest.approx(constant[0])
    assert 0.3 < np.mean(cosine[190:210]) / np.mean(constant[190:210]) < 0.8
    assert np.mean(cosine[-20:]) < 0.02 * np.mean(constant[-20:])
    with pytest.raises(ValueError, match="lr_schedule"):
        step_sizes("linear")
    with pytest.raises(SettingError, match="dynamics_lr_schedule"):
        GeneratorConfig(dynamics_lr_schedule="step")
    assert (
        fit_settings(GeneratorConfig(dynamics_lr_schedule="cosine"), 10)["dynamics"]["lr_schedule"]
        == "cosine"
    )
