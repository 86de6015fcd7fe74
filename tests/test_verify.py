"""`hipode verify` end to end on a tiny real artifact, its measures, and the CLI."""

import json
import sys
from pathlib import Path

import gymnasium as gym
import h5py
import numpy as np
import pytest
import torch
import typer
from builders import make_minari_dataset
from test_simulator import real_rollout
from typer.testing import CliRunner

from hipode_pipeline import console
from hipode_pipeline.artifact import MANIFEST_ATTR, read_artifact, seal_manifest
from hipode_pipeline.augment import run_augment
from hipode_pipeline.commands.verify import register
from hipode_pipeline.data.load import load_source
from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import DataFormatError, OverwriteError
from hipode_pipeline.simulator import make_env_safely, set_state_from_observation
from hipode_pipeline.verify import BehaviourCVAEConfig, check_transitions, verify_artifact

TINY_BEHAVIOUR = BehaviourCVAEConfig(steps=40, hidden=32, eval_every=20, heldout_eval_rows=256)


def real_episodes(count: int, seed: int) -> list[dict[str, np.ndarray]]:
    """Minari-style Hopper-v5 episodes from seeded random actions (short: they fall quickly)."""
    env = gym.make("Hopper-v5", max_episode_steps=60)
    rng = np.random.default_rng(seed)
    episodes = []
    for episode in range(count):
        observation, _ = env.reset(seed=seed + episode)
        columns = {"observations": [observation], "actions": [], "rewards": []}
        terminated = truncated = False
        while not (terminated or truncated):
            action = rng.uniform(-1, 1, 3).astype(np.float32)
            observation, reward, terminated, truncated, _ = env.step(action)
            columns["observations"].append(observation)
            columns["actions"].append(action)
            columns["rewards"].append(reward)
        steps = len(columns["rewards"])
        episodes.append(
            {
                **{name: np.array(values) for name, values in columns.items()},
                "terminations": np.eye(1, steps, steps - 1, dtype=bool)[0] & terminated,
                "truncations": np.eye(1, steps, steps - 1, dtype=bool)[0] & truncated,
            }
        )
    env.close()
    return episodes


@pytest.fixture(scope="module")
def tiny_artifact(tmp_path_factory):
    """A real stage-one run (quick profile) on a tiny dataset of real Hopper rollouts."""
    root = tmp_path_factory.mktemp("verify") / "datasets"
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(root))
        make_minari_dataset("local/hopper/tiny-real-v0", real_episodes(25, seed=0))
        summary = run_augment(
            "hopper-m-r",
            source="local/hopper/tiny-real-v0",
            profile="quick",
            root=root,
            show_progress=False,
        )
    return root, summary


def test_verify_artifact_writes_report_and_plot(tiny_artifact, tmp_path):
    root, summary = tiny_artifact
    out = tmp_path / "out"
    report = verify_artifact(
        summary.artifact,
        sample=48,
        root=root,
        out_dir=out,
        behaviour=TINY_BEHAVIOUR,
        show_progress=False,
    )
    json_path = out / f"{summary.artifact.rsplit('/', 1)[-1]}.verify.json"
    png_path = json_path.with_name(json_path.name.replace(".json", ".png"))
    assert report.json_path == str(json_path) and report.png_path == str(png_path)
    written = json.loads(json_path.read_text())
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert written["env_id"] == "Hopper-v5" and written["source_sha256"] == summary.source_sha256
    for name in ("hipode", "baseline"):
        part = written[name]
        assert part["n"] == 48
        assert len(written["per_transition"][name]["next_state_error"]) == 48
        assert 0 <= part["within_tolerance"] <= 1 and 0 <= part["terminal_agreement"] <= 1
        assert part["next_state_error_median"] <= part["next_state_error_p90"]
    details = written["baseline_details"]
    assert details["generators_were_cached"] and details["dynamics_matches_artifact"]
    assert details["behaviour_cvae"]["steps"] == TINY_BEHAVIOUR.steps

    # the sampled rows by hand: the simulator's own answer against the artifact's transitions
    synthetic = read_artifact(summary.artifact).transitions
    source, _ = load_source("local/hopper/tiny-real-v0", root)
    std = source.next_observations.astype(np.float64).std(0) + 1e-6
    env = make_env_safely("Hopper-v5")
    env.reset(seed=0)
    rows = written["per_transition"]["hipode"]["row"]
    reported_errors = written["per_transition"]["hipode"]["next_state_error"]
    assert len(set(rows)) == 48 and max(rows) < len(synthetic)
    for row, reported in zip(rows, reported_errors, strict=True):
        set_state_from_observation(env, synthetic.observations[row])
        next_observation, *_ = env.unwrapped.step(synthetic.actions[row])
        by_hand = (np.abs(synthetic.next_observations[row] - next_observation) / std).mean()
        assert by_hand == pytest.approx(reported, rel=1e-4, abs=1e-9)
    env.close()

    # same seed -> identical arrays; outputs are not overwritten without force
    with pytest.raises(OverwriteError):
        verify_artifact(summary.artifact, sample=48, root=root, out_dir=out, show_progress=False)
    again = verify_artifact(
        summary.artifact,
        sample=48,
        root=root,
        out_dir=out,
        force=True,
        behaviour=TINY_BEHAVIOUR,
        show_progress=False,
    )
    assert again.baseline_details["behaviour_cvae"]["cached"]
    np.testing.assert_array_equal(again.hipode.next_state_error, report.hipode.next_state_error)
    np.testing.assert_array_equal(again.baseline.next_state_error, report.baseline.next_state_error)
    np.testing.assert_array_equal(again.baseline.novelty, report.baseline.novelty)


def test_checks_measure_a_known_perturbation():
    observations, actions, rewards, next_observations, terminated = real_rollout(
        "HalfCheetah-v5", 60, seed=1
    )
    source = Transitions(
        observations=observations.astype(np.float32),
        actions=actions,
        rewards=rewards.astype(np.float32),
        next_observations=next_observations.astype(np.float32),
        terminals=terminated,
        timeouts=np.zeros(60, dtype=bool),
    )
    std = source.next_observations.astype(np.float64).std(0)
    shifted = source.next_observations.copy()
    shifted[:30, 4] += (0.5 * std[4]).astype(np.float32)
    perturbed = Transitions(
        **{**source.arrays(), "next_observations": shifted, "rewards": source.rewards + 0.25}
    )
    normalizer = StateNormalizer.fit(source.observations)
    checks = check_transitions(
        "HalfCheetah-v5",
        perturbed,
        next_state_std=std,
        reward_std=1.0,
        normalizer=normalizer,
        source_norm=torch.as_tensor(normalizer.normalize(source.observations)),
        tolerance=0.3,
        seed=0,
        origin="test",
    )
    expected = np.where(np.arange(60) < 30, 0.5 / 17, 0.0)
    np.testing.assert_allclose(checks.next_state_error, expected, atol=2e-6)
    np.testing.assert_allclose(checks.reward_error, 0.25, atol=1e-5)
    # reward error 0.25 <= 0.3 reward stds and state error 0.029 <= 0.3: all within
    assert checks.within_tolerance.all()
    assert checks.terminal_agrees.all()
    # an unshifted next state is the next row's observation: novelty 0, up to cdist's float32
    # rounding; the shifted ones moved half a std away from every source state
    assert np.all(checks.novelty[30:59] < 5e-3)
    assert np.all(checks.novelty[:30] > 0.05)


def test_foreign_env_id_in_artifact_is_refused_without_import(tiny_artifact, tmp_path):
    root, summary = tiny_artifact
    tampered = tmp_path / "tampered.hdf5"
    tampered.write_bytes(open(summary.artifact, "rb").read())
    with h5py.File(tampered, "r+") as f:
        manifest = json.loads(f.attrs[MANIFEST_ATTR])
        manifest["env_id"] = "hipode_never_imported_probe:Env"
        # re-sealed: a forger who recomputes the digest still meets the env-id check
        f.attrs[MANIFEST_ATTR] = json.dumps(seal_manifest(manifest))
    with pytest.raises(DataFormatError) as caught:
        verify_artifact(tampered, sample=8, root=root, baseline=False, show_progress=False)
    assert caught.value.path == str(tampered) and caught.value.field == "env_id"
    assert "hipode_never_imported_probe" not in sys.modules


def cli_app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """Test group."""

    register(app)
    return app


def test_cli_prints_table_and_json(tiny_artifact, tmp_path, monkeypatch):
    root, summary = tiny_artifact
    # rich folds cells on a narrow terminal
    monkeypatch.setattr(console.out, "width", 250)
    runner = CliRunner()
    common = ["verify", summary.artifact, "--sample", "16", "--no-baseline", "--root", str(root)]
    table = runner.invoke(cli_app(), [*common, "--out-dir", str(tmp_path / "a")])
    assert table.exit_code == 0, table.output
    assert "HIPODE" in table.stdout and "plain model rollout" not in table.stdout
    assert "terminal agree" in table.stdout
    result = runner.invoke(cli_app(), [*common, "--out-dir", str(tmp_path / "b"), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["hipode"]["n"] == 16 and data["baseline"] is None
    assert "per_transition" not in data
    again = runner.invoke(cli_app(), [*common, "--out-dir", str(tmp_path / "b")])
    assert again.exit_code == 2 and "--force" in again.stderr
    missing = runner.invoke(cli_app(), ["verify", str(tmp_path / "none.hdf5")])
    assert missing.exit_code == 2 and "no such artifact" in missing.stderr


def test_verify_diagnoses_each_stage_on_held_out_real_rows(tiny_artifact, tmp_path):
    root, summary = tiny_artifact
    report = verify_artifact(
        summary.artifact,
        sample=48,
        root=root,
        out_dir=tmp_path,
        behaviour=TINY_BEHAVIOUR,
        show_progress=False,
    )
    stages = report.analysis["stages"]
    # the simulator replays the recorded actions of real held-out rows to their recorded next
    # states: the rows, their order and the state restore line up
    assert stages["recorded_action_on_real"]["median"] < 1e-4
    assert stages["heldout_rows"] > 0 and 0 <= stages["heldout_clipped_share"] <= 1
    assert stages["kept"]["total"]["median"] == pytest.approx(
        float(np.median(report.hipode.next_state_error))
    )
    one_step = stages["ensemble_one_step_on_real"]
    assert len(one_step["per_dimension"]) == 11 and one_step["median"] > 0
    tolerance = report.analysis["model_tolerance"]
    assert tolerance["value"] == one_step["median"] and 0 <= tolerance["hipode_within"] <= 1
    matched = report.analysis["matched_novelty_exact_rows"]
    assert sum(b["hipode_n"] for b in matched["bins"]) == int((~report.hipode.clipped_input).sum())
    assert report.hipode.summary()["exact_ground_truth_share"] == pytest.approx(
        float((~report.hipode.clipped_input).mean())
    )


def test_heldout_rows_are_the_generators_own_split():
    from hipode_pipeline.models.training import TensorData, split_rows

    data = TensorData({"x": torch.zeros(1000, 1)}, 0.05, 4096, seed=7)
    train, heldout = split_rows(1000, 0.05, 7)
    assert torch.equal(heldout, data.heldout_rows) and torch.equal(train, data.train_rows)
    assert len(heldout) == 50 and not torch.equal(split_rows(1000, 0.05, 8)[1], heldout)


def test_matched_novelty_compares_like_with_like():
    from hipode_pipeline.diagnose import matched_novelty

    rng = np.random.default_rng(0)
    # error grows with novelty for both; the baseline is twice as wrong at any novelty but sits
    # mostly at high novelty, so unmatched medians would overstate HIPODE's advantage
    mine = rng.uniform(0, 1, 4000)
    theirs = rng.uniform(0.5, 3, 4000)
    result = matched_novelty(mine, 0.01 * (1 + mine), theirs, 0.02 * (1 + theirs), bins=5)
    assert result["median_ratio"] == pytest.approx(0.5, rel=0.05)
    unmatched = np.median(0.01 * (1 + mine)) / np.median(0.02 * (1 + theirs))
    assert unmatched < 0.3


def test_cli_summarizes_several_artifacts(tiny_artifact, tmp_path, monkeypatch):
    import shutil

    root, summary = tiny_artifact
    monkeypatch.setattr(console.out, "width", 300)
    copy = tmp_path / "copy.hdf5"
    shutil.copyfile(summary.artifact, copy)
    out = tmp_path / "out"
    args = ["verify", summary.artifact, str(copy), "--sample", "16", "--no-baseline"]
    args += ["--root", str(root), "--out-dir", str(out)]
    result = CliRunner().invoke(cli_app(), args)
    assert result.exit_code == 0, result.output
    assert "across artifacts" in result.stdout
    written = json.loads((out / "verify-summary.json").read_text())
    assert [row["artifact"] for row in written["rows"]] == [
        Path(summary.artifact).name,
        "copy.hdf5",
    ]
    assert (out / "verify-summary.png").read_bytes()[:4] == b"\x89PNG"
    # a second run without --force is refused before any artifact is verified again
    (out / "copy.hdf5.verify.json").unlink()
    again = CliRunner().invoke(cli_app(), args)
    assert again.exit_code == 2 and "verify-summary" in again.stderr
    assert not (out / "copy.hdf5.verify.json").exists()


def test_cli_refuses_two_artifacts_of_one_name_into_one_folder(tiny_artifact, tmp_path):
    import shutil

    root, summary = tiny_artifact
    twins = []
    for arm in ("hipode", "model-rollouts"):
        (tmp_path / arm).mkdir()
        twins.append(str(shutil.copyfile(summary.artifact, tmp_path / arm / "artifact.hdf5")))
    out = tmp_path / "out"
    args = ["verify", *twins, "--sample", "16", "--no-baseline", "--root", str(root)]
    # even --force may not let the second report replace the first's: refused before any work
    result = CliRunner().invoke(cli_app(), [*args, "--out-dir", str(out), "--force"])
    assert result.exit_code == 2 and "both would write" in result.stderr
    assert not out.exists() or not any(out.iterdir())
    apart = CliRunner().invoke(cli_app(), args)  # each beside its own artifact
    assert apart.exit_code == 0, apart.output
    assert all(Path(t + ".verify.json").is_file() for t in twins)


def test_a_model_rollout_artifact_is_named_as_such(tiny_artifact, tmp_path, monkeypatch):
    root, _ = tiny_artifact
    with monkeypatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(root))
        rollouts = run_augment(
            "hopper-m-r",
            source="local/hopper/tiny-real-v0",
            profile="quick",
            method="model-rollouts",
            out=tmp_path / "rollouts.hdf5",
            root=root,
            show_progress=False,
        )
    monkeypatch.setattr(console.out, "width", 250)
    args = ["verify", rollouts.artifact, "--sample", "16", "--no-baseline", "--root", str(root)]
    table = CliRunner().invoke(cli_app(), [*args, "--out-dir", str(tmp_path / "a")])
    assert table.exit_code == 0, table.output
    assert "model-rollout artifact" in table.stdout and "HIPODE" not in table.stdout
    written = json.loads((tmp_path / "a" / "rollouts.hdf5.verify.json").read_text())
    assert written["method"] == "model-rollouts"


def test_every_method_an_artifact_can_record_has_a_label():
    from hipode_pipeline.contract import METHODS
    from hipode_pipeline.verify import METHOD_LABELS

    assert set(METHOD_LABELS) == set(METHODS)
