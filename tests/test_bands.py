"""Off-band sources: a dataset whose behaviour policy missed the band of its kind makes
`collect` fail (written, marked), and `augment` / `train` refuse it unless --allow-off-band,
which the outputs then record."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

import hipode_pipeline.data.collect as collect_module
from hipode_pipeline.cli import app
from hipode_pipeline.data.bands import OffBandError, band_record, dataset_band

QUICK = ["--profile", "quick"]
TINY_TRAIN = ["--steps", "4", "--eval-every", "4", "--eval-episodes", "1", "--batch-size", "16"]


@pytest.fixture
def unreachable_band(monkeypatch):
    """The quick recipe with a medium band no quick policy reaches."""
    real = collect_module.load_recipe

    def with_band(env, profile="full", path=None):
        return dataclasses.replace(real(env, profile, path), medium_band=(1000.0, 1001.0))

    monkeypatch.setattr(collect_module, "load_recipe", with_band)


def metadata(root: Path) -> dict:
    path = root / "local" / "hopper" / "medium-replay-v0" / "data" / "metadata.json"
    return json.loads(path.read_text())


def test_off_band_collection_fails_is_marked_and_refused_downstream(
    dataset_root, unreachable_band, tmp_path
):
    runner = CliRunner()
    collected = runner.invoke(app, ["collect", "hopper-m-r", *QUICK])
    assert collected.exit_code == OffBandError.exit_code, collected.output
    message = " ".join(collected.output.split())
    assert "outside its band [1000, 1001]" in message and "--allow-off-band" in message
    band = metadata(dataset_root)["hipode"]["band"]
    assert band["in_band"] is False and band["policies"]["medium"]["band"] == [1000.0, 1001.0]
    # the dataset stays off-band: asking again fails again, the flag lets it through
    assert runner.invoke(app, ["collect", "hopper-m-r", *QUICK]).exit_code == 3
    accepted = runner.invoke(app, ["collect", "hopper-m-r", *QUICK, "--allow-off-band", "--json"])
    assert accepted.exit_code == 0, accepted.output
    assert json.loads(accepted.stdout)["band"]["in_band"] is False

    refused = runner.invoke(app, ["augment", "hopper-m-r", *QUICK])
    assert refused.exit_code == 3 and "--allow-off-band" in refused.output
    assert not (dataset_root / "artifacts").exists() and not (dataset_root / "cache").exists()
    built = runner.invoke(app, ["augment", "hopper-m-r", *QUICK, "--allow-off-band", "--json"])
    assert built.exit_code == 0, built.output
    summary = json.loads(built.stdout)
    assert summary["allowed_off_band"] is True
    assert summary["source_band"]["in_band"] is False

    artifact = summary["artifact"]
    sweep = ["sweep", "--tasks", "hopper-m-r", "--seeds", "0", "--steps", "2", "--eval-every"]
    sweep += ["2", "--eval-episodes", "1", "--artifact", artifact, "--out", str(tmp_path / "sw")]
    refused_sweep = runner.invoke(app, sweep)
    assert refused_sweep.exit_code == 3 and "--allow-off-band" in refused_sweep.output
    swept = runner.invoke(app, [*sweep, "--allow-off-band", "--json"])
    assert swept.exit_code == 0, swept.output

    out = tmp_path / "runs"
    train = ["train", "hopper-m-r", "--data", "source", *TINY_TRAIN, "--out", str(out)]
    assert runner.invoke(app, train).exit_code == 3 and not out.exists()
    trained = runner.invoke(app, [*train, "--allow-off-band", "--json"])
    assert trained.exit_code == 0, trained.output
    config = json.loads((Path(json.loads(trained.stdout)["run_dir"]) / "config.json").read_text())
    assert config["allowed_off_band"] is True and config["source_band"]["in_band"] is False


def test_in_band_and_bandless_sources_pass(dataset_root):
    result = CliRunner().invoke(app, ["collect", "hopper-m-r", *QUICK, "--json"])
    assert result.exit_code == 0, result.output
    # the quick profile records no band: nothing to check, nothing refused
    assert json.loads(result.stdout)["band"]["in_band"] is None


def test_band_of_data_collected_before_bands_were_recorded():
    """The halfcheetah case: a medium policy at 15.7 normalized under the full recipe."""
    legacy = {
        "hipode": {
            "kind": "medium-replay",
            "recipe": {"env": "halfcheetah", "profile": "full", "medium_range": [38.0, 46.0]},
            "behaviour_policy": {"medium": {"normalized": 15.7}},
        }
    }
    record = dataset_band(legacy)
    assert record["in_band"] is False and record["policies"]["medium"]["band"] == [29.0, 53.0]
    assert dataset_band({"some": "minari metadata"}) is None
    both = band_record(
        "medium-expert",
        {"medium": (30.0, 50.0), "expert": None},
        {"medium": {"normalized": 40.0}, "expert": {"normalized": 90.0}},
    )
    assert both["in_band"] is None  # the expert half has no band recorded: unknown, not in
