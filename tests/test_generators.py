"""train_generators: the contract generation uses, caching by (source, config, seed), resume."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import DataFormatError, SettingError
from hipode_pipeline.files import file_sha256
from hipode_pipeline.models import training
from hipode_pipeline.models.generators import (
    FIELD_OWNERS,
    MODEL_NAMES,
    GeneratorConfig,
    cache_dir_for,
    train_generators,
)
from hipode_pipeline.versions import GENERATOR_CODE, code_digest

DS, DA = 5, 2
TINY = dict(cvae_hidden=48, value_hidden=32, dynamics_hidden=(32, 32), dynamics_members=3)


def tiny_config(**overrides) -> GeneratorConfig:
    return GeneratorConfig.profile("quick", **{**TINY, **overrides})


@pytest.fixture(scope="module")
def transitions() -> Transitions:
    rng = np.random.default_rng(0)
    n = 2000
    s = rng.normal(2.0, 3.0, size=(n, DS)).astype(np.float32)
    a = rng.uniform(-1, 1, size=(n, DA)).astype(np.float32)
    s_next = (s + a @ rng.normal(size=(DA, DS)) + 0.01 * rng.normal(size=(n, DS))).astype(
        np.float32
    )
    r = (s[:, 0] + a[:, 1]).astype(np.float32)
    terminals = rng.random(n) < 0.01
    return Transitions(s, a, r, s_next, terminals, np.zeros(n, bool))


def sample_everything(gen) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(123)
    s = torch.randn(7, DS, generator=g)
    pair = torch.cat([s, s + 0.1], -1)
    return [
        gen.state_transition.sample(s, 3, g),
        gen.value(s),
        gen.inverse_action.sample(pair, 3, g),
        gen.inverse_reward.sample(pair, 3, g),
        *gen.dynamics.sample(s, torch.zeros(7, DA), g),
        *gen.dynamics.sample(s, torch.zeros(7, DA), use_mean=True),
    ]


def weights(gen) -> dict[str, torch.Tensor]:
    return {f"{name}.{k}": v for name, m in gen.models().items() for k, v in m.state_dict().items()}


def test_profiles_hash_and_validation():
    full, quick = GeneratorConfig.profile("full"), GeneratorConfig.profile("quick")
    assert full == GeneratorConfig()
    assert quick.state_transition_steps < full.state_transition_steps
    assert full.cvae_hidden == 750 and full.value_hidden == 256 and full.latent_clip == 0.5
    assert full.penalty == "target" and full.dynamics_members == 5
    assert full.hash() == GeneratorConfig().hash() and len(full.hash()) == 64
    assert full.hash() != GeneratorConfig(alpha=2.0).hash()
    assert GeneratorConfig.from_dict(json.loads(json.dumps(quick.to_dict()))) == quick
    with pytest.raises(SettingError, match="quick"):
        GeneratorConfig.profile("fast")
    with pytest.raises(SettingError, match="'penalty'.*target"):
        GeneratorConfig(penalty="huber")
    with pytest.raises(SettingError, match="alpah"):
        GeneratorConfig.profile("full", alpah=1.0)
    with pytest.raises(SettingError, match="value_steps"):
        GeneratorConfig(value_steps=-1)


def test_train_generators_contract_and_cache(transitions, tmp_path):
    config = tiny_config()
    sha = transitions.sha256()
    gen = train_generators(
        transitions, sha, config, cache_root=tmp_path, seed=3, show_progress=False
    )
    folder = cache_dir_for(tmp_path, sha, config, 3)
    code = code_digest(GENERATOR_CODE)[:12]
    assert folder.name == f"{sha[:16]}-{code}-{config.hash()[:12]}-seed3"
    names = {p.name for p in folder.iterdir()}
    assert {"config.json", "normalizer.json"} <= names
    assert {f"{m}.pt" for m in MODEL_NAMES} | {f"{m}.json" for m in MODEL_NAMES} <= names
    assert not any(n.endswith(".ckpt.pt") for n in names)
    assert gen.device.type == "cpu"
    np.testing.assert_allclose(
        gen.normalizer.mean, transitions.observations.mean(0), rtol=1e-4, atol=1e-4
    )

    outputs = sample_everything(gen)
    shapes = [(7, 3, DS), (7,), (7, 3, DA), (7, 3, 1), (7, DS), (7,), (7, DS), (7,)]
    assert [tuple(o.shape) for o in outputs] == shapes
    low, high = transitions.actions.min(0), transitions.actions.max(0)
    assert np.all(outputs[2].numpy() >= low) and np.all(outputs[2].numpy() <= high)
    for name, record in gen.training_report.items():
        assert record["steps"] == getattr(config, f"{name}_steps") and not record["cached"]
        assert set(record) == {
            "steps",
            "seconds",
            "initial_heldout_loss",
            "best_heldout_loss",
            "final_heldout_loss",
            "cached",
            "budget_steps",
            "stopped_on_plateau",
            "member_best_heldout_losses",
        }
    for name in ("state_transition", "inverse_action", "inverse_reward"):
        assert (
            gen.training_report[name]["best_heldout_loss"]
            < 0.5 * gen.training_report[name]["initial_heldout_loss"]
        )
    assert (
        gen.training_report["dynamics"]["best_heldout_loss"]
        < gen.training_report["dynamics"]["initial_heldout_loss"] - 1
    )

    started = time.perf_counter()
    again = train_generators(
        transitions, sha, config, cache_root=tmp_path, seed=3, show_progress=False
    )
    assert time.perf_counter() - started < 5.0
    assert all(r["cached"] for r in again.training_report.values())
    assert again.checkpoint_hashes == gen.checkpoint_hashes
    assert again.checkpoint_hashes["value"] == file_sha256(folder / "value.pt")
    for one, two in zip(outputs, sample_everything(again), strict=True):
        assert torch.equal(one, two)


class Interrupted(Exception):
    pass


def test_interrupted_training_resumes_to_the_same_weights(transitions, tmp_path, monkeypatch):
    config = tiny_config()
    sha = transitions.sha256()

    def interrupt(name, step):
        if name == "inverse_action" and step == 200:
            raise Interrupted

    monkeypatch.setattr(training, "checkpoint_written", interrupt)
    with pytest.raises(Interrupted):
        train_generators(
            transitions, sha, config, cache_root=tmp_path / "a", seed=0, show_progress=False
        )
    folder = cache_dir_for(tmp_path / "a", sha, config, 0)
    assert (folder / "inverse_action.ckpt.pt").exists() and not (
        folder / "inverse_action.pt"
    ).exists()
    assert (folder / "value.pt").exists()
    monkeypatch.undo()

    resumed = train_generators(
        transitions, sha, config, cache_root=tmp_path / "a", seed=0, show_progress=False
    )
    report = resumed.training_report
    assert report["state_transition"]["cached"] and report["value"]["cached"]
    assert (
        not report["inverse_action"]["cached"]
        and report["inverse_action"]["steps"] == config.inverse_action_steps
    )
    assert not (folder / "inverse_action.ckpt.pt").exists()

    straight = train_generators(
        transitions, sha, config, cache_root=tmp_path / "b", seed=0, show_progress=False
    )
    assert resumed.checkpoint_hashes == straight.checkpoint_hashes
    a, b = weights(resumed), weights(straight)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (
        report["inverse_action"]["best_heldout_loss"]
        == straight.training_report["inverse_action"]["best_heldout_loss"]
    )

    other = train_generators(
        transitions, sha, config, cache_root=tmp_path / "c", seed=1, show_progress=False
    )
    assert not torch.equal(
        weights(other)["dynamics.hidden_layers.0.weight"], b["dynamics.hidden_layers.0.weight"]
    )


def test_damaged_weights_file_is_reported(transitions, tmp_path):
    config = tiny_config(
        state_transition_steps=20,
        value_steps=20,
        inverse_action_steps=20,
        inverse_reward_steps=20,
        dynamics_steps=20,
    )
    sha = transitions.sha256()
    train_generators(transitions, sha, config, cache_root=tmp_path, seed=0, show_progress=False)
    path = cache_dir_for(tmp_path, sha, config, 0) / "value.pt"
    path.write_bytes(b"not a weights file")
    with pytest.raises(DataFormatError, match="value.pt"):
        train_generators(transitions, sha, config, cache_root=tmp_path, seed=0, show_progress=False)


def test_field_owners_name_real_fields_and_models():
    fields = set(GeneratorConfig().to_dict())
    assert set(FIELD_OWNERS) <= fields
    assert all(set(owners) <= set(MODEL_NAMES) for owners in FIELD_OWNERS.values())
    config = tiny_config()
    changed = tiny_config(alpha=config.alpha + 1.0)
    assert changed.model_key("value") != config.model_key("value")
    assert all(changed.model_key(m) == config.model_key(m) for m in MODEL_NAMES if m != "value")


def test_an_alpha_change_retrains_only_the_value_net_and_matches_training_from_scratch(
    transitions, tmp_path
):
    sha = transitions.sha256()
    shared = tmp_path / "shared"
    train_generators(
        transitions, sha, tiny_config(), cache_root=shared, seed=0, show_progress=False
    )
    ablation = tiny_config(alpha=4.0)
    reused = train_generators(
        transitions, sha, ablation, cache_root=shared, seed=0, show_progress=False
    )
    scratch = train_generators(
        transitions, sha, ablation, cache_root=tmp_path / "scratch", seed=0, show_progress=False
    )
    for name in MODEL_NAMES:
        assert ("reused_from" in reused.training_report[name]) == (name != "value"), name
    # same settings and per-model seeds give the same weights, reused or trained afresh
    assert reused.checkpoint_hashes == scratch.checkpoint_hashes
