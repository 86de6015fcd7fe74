"""--set KEY=VALUE and --config FILE.toml: parsed as TOML values, checked against the config
dataclasses' fields and types before any work, and recorded in what the command writes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from test_train_cli import TINY
from typer.testing import CliRunner

from hipode_pipeline.artifact import read_artifact
from hipode_pipeline.cli import app
from hipode_pipeline.errors import SettingError
from hipode_pipeline.learners import TD3BCConfig
from hipode_pipeline.models import generators
from hipode_pipeline.models.generators import GeneratorConfig
from hipode_pipeline.overrides import check_fields, read_overrides


def test_values_read_as_toml_and_set_wins_over_the_file(tmp_path):
    file = tmp_path / "settings.toml"
    file.write_text('actor_lr = 1e-3\nalpha = 2.0\ncvae_precision = "fp32"\n')
    values = read_overrides(
        ["alpha=4", "bf16=true", "dynamics_hidden=[64, 64]", "cvae_precision=bf16"], file
    )
    assert values == {
        "actor_lr": 1e-3,
        "alpha": 4,
        "bf16": True,
        "dynamics_hidden": [64, 64],
        "cvae_precision": "bf16",  # a bare word is a string
    }


@pytest.mark.parametrize("item", ["no_equals", "=3", "Actor-LR=3", "a b=1"])
def test_malformed_set_items_are_refused(item):
    with pytest.raises(SettingError, match="expected KEY=VALUE"):
        read_overrides([item], None)


def test_a_config_file_with_tables_or_bad_toml_is_refused(tmp_path):
    nested = tmp_path / "nested.toml"
    nested.write_text("[td3bc]\nalpha = 1\n")
    with pytest.raises(SettingError, match="flat KEY = VALUE"):
        read_overrides(None, nested)
    broken = tmp_path / "broken.toml"
    broken.write_text("alpha = \n")
    with pytest.raises(SettingError, match="expected TOML"):
        read_overrides(None, broken)
    with pytest.raises(SettingError, match="cannot read"):
        read_overrides(None, tmp_path / "missing.toml")


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"actor_lr": "fast"}, "actor_lr: expected float, found 'fast'"),
        ({"policy_freq": 2.5}, "policy_freq: expected int"),
        ({"policy_freq": True}, "policy_freq: expected int"),
        ({"bf16": 1}, "bf16: expected bool | None"),
        ({"nonsense": 1}, "unknown setting"),
    ],
)
def test_fields_are_checked_by_name_and_type(values, message):
    with pytest.raises(SettingError, match=message.replace("|", "\\|")):
        check_fields(TD3BCConfig, values, "test")
    assert check_fields(GeneratorConfig, {"dynamics_hidden": [64, 64]}, "t")
    assert check_fields(TD3BCConfig, {"actor_lr": 1, "bf16": None}, "t")  # int for a float


def test_train_records_the_settings_and_refuses_bad_ones_before_any_folder(tmp_path, tiny_pair):
    source, artifact = tiny_pair
    base = ["train", "hopper-m-r", "--source", source, "--artifact", str(artifact), *TINY]
    file = tmp_path / "learner.toml"
    file.write_text("actor_lr = 1e-4\ncritic_lr = 1e-4\n")
    out = tmp_path / "runs"
    runner = CliRunner()
    bad = runner.invoke(app, [*base, "--set", "actor_lr=abc", "--out", str(out)])
    assert bad.exit_code != 0 and "actor_lr: expected float, found 'abc'" in bad.output
    assert not out.exists()
    ran = runner.invoke(
        app,
        [*base, "--config", str(file), "--set", "critic_lr=5e-4", "--set", "bf16=true"]
        + ["--out", str(out), "--json"],
    )
    assert ran.exit_code == 0, ran.output
    config = json.loads((Path(json.loads(ran.stdout)["run_dir"]) / "config.json").read_text())
    learner = config["learner_config"]
    assert learner["actor_lr"] == 1e-4 and learner["critic_lr"] == 5e-4 and learner["bf16"]
    assert config["precision"] == "bf16"
    default = runner.invoke(app, [*base, "--out", str(out), "--json"])
    # other settings, another experiment: another folder
    assert json.loads(default.stdout)["run_dir"] != json.loads(ran.stdout)["run_dir"]


@pytest.mark.parametrize("native", [True, False])
def test_generator_bf16_falls_back_to_fp32_only_where_emulated_and_not_asked(monkeypatch, native):
    monkeypatch.setattr(generators, "fast_bf16", lambda device: native)
    config = GeneratorConfig()
    assert config.cvae_precision == config.dynamics_precision == "bf16"
    on_device, moved = config.on_device(torch.device("cpu"), asked={"dynamics_precision"})
    if native:
        assert on_device is config and moved == []
    else:
        assert moved == ["cvae_precision"]
        assert on_device.cvae_precision == "fp32" and on_device.dynamics_precision == "bf16"
        assert on_device.hash() != config.hash()  # the cache key follows the precision trained


def test_augment_takes_generator_settings(tmp_path, tiny_pair, monkeypatch):
    # as on a CPU without native bf16: stage one says so and trains and records fp32, except
    # where a setting asks for bf16
    monkeypatch.setattr(generators, "fast_bf16", lambda device: False)
    source, _ = tiny_pair
    base = ["augment", "hopper-m-r", "--source", source, "--profile", "quick"]
    runner = CliRunner()
    twice = runner.invoke(app, [*base, "--alpha", "2", "--set", "alpha=3"])
    assert twice.exit_code != 0 and "give alpha once" in twice.output
    wrong = runner.invoke(app, [*base, "--set", "dynamics_members=many"])
    assert wrong.exit_code != 0 and "dynamics_members: expected int" in wrong.output
    out = tmp_path / "custom.hdf5"
    settings = ["dynamics_members=3", "value_steps=40", "dynamics_precision=bf16"]
    settings.append("dynamics_steps=30")  # emulated bf16 is slow: a short fit
    built = runner.invoke(
        app, [*base, *(x for s in settings for x in ("--set", s)), "--out", str(out)]
    )
    assert built.exit_code == 0, built.output
    config = read_artifact(out).manifest["hyper_parameters"]["generator_config"]
    assert config["dynamics_members"] == 3 and config["value_steps"] == 40
    assert config["cvae_precision"] == "fp32" and config["dynamics_precision"] == "bf16"
    said = " ".join(built.output.split())
    assert "bf16 matmuls are emulated on cpu" in said and "): cvae_precision set to fp32" in said
    # the plan line names what the settings changed, not what the machine moved
    expected = "dynamics_members=3, dynamics_precision=bf16, dynamics_steps=30, value_steps=40;"
    assert f"profile quick with {expected}" in said


def test_an_artifact_built_where_bf16_is_native_is_kept_where_it_is_emulated(
    tmp_path, tiny_pair, monkeypatch
):
    source, _ = tiny_pair
    short = [f"{name}_steps=20" for name in generators.MODEL_NAMES]
    command = ["augment", "hopper-m-r", "--source", source, "--profile", "quick"]
    command += [*(x for s in short for x in ("--set", s)), "--out", str(tmp_path / "a.hdf5")]
    runner = CliRunner()
    monkeypatch.setattr(generators, "fast_bf16", lambda device: True)
    built = runner.invoke(app, command)
    assert built.exit_code == 0, built.output
    manifest = read_artifact(tmp_path / "a.hdf5").manifest
    assert manifest["hyper_parameters"]["generator_config"]["cvae_precision"] == "bf16"
    monkeypatch.setattr(generators, "fast_bf16", lambda device: False)
    again = runner.invoke(app, command)
    assert again.exit_code == 0, again.output
    assert "is up to date" in " ".join(again.output.split())
    # another setting is still another artifact
    other = runner.invoke(app, [*command, "--set", "value_lr=1e-3"])
    assert other.exit_code != 0 and "built with other settings" in other.output
