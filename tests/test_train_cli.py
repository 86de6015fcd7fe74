"""`hipode train` end to end on tiny data: run folder, scores, resume, clear errors, d3rlpy."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from builders import make_episodes, make_minari_dataset
from test_merge import write_synthetic
from typer.testing import CliRunner

import hipode_pipeline.train as train_module
from hipode_pipeline import run_folder
from hipode_pipeline.cli import app
from hipode_pipeline.contract import default_artifact_path, table_settings
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import OverwriteError
from hipode_pipeline.learners.external import episode_arrays
from hipode_pipeline.tasks import get_task
from hipode_pipeline.train import run_training

TINY = ["--steps", "20", "--eval-every", "10", "--eval-episodes", "2", "--batch-size", "32"]


def test_train_cli_writes_run_folder_and_scores(tmp_path, tiny_pair):
    source, artifact = tiny_pair
    result = CliRunner().invoke(
        app,
        [
            "train",
            "hopper-m-r",
            "--source",
            source,
            "--artifact",
            str(artifact),
            *TINY,
            "--out",
            str(tmp_path / "runs"),
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    scores = json.loads(result.stdout)
    run_dir = Path(scores["run_dir"])
    assert run_dir.parent == tmp_path / "runs" / "hopper-m-r"
    # learner, data and η readable; the identity (source, artifact, settings) keeps sweeps apart
    assert re.fullmatch(r"td3bc-merged-eta0\.5-[0-9a-f]{8}-seed0", run_dir.name), run_dir.name
    assert (
        scores["run_dir"] == str(run_dir) and scores["steps"] == 20 and scores["eta"] == 0.5
    )  # Table 6
    assert [e["step"] for e in scores["evaluations"]] == [10, 20]
    assert scores["last"]["step"] == 20 and "best" in scores["best"]["label"]
    config = json.loads((run_dir / "config.json").read_text())
    assert config["artifact_checksum"].startswith("sha256:") and len(config["source_sha256"]) == 64
    assert config["learner_config"]["alpha"] == 2.5 and config["n_synthetic"] == 20
    lines = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert (
        [x["step"] for x in lines] == [10, 20]
        and "critic_loss" in lines[0]
        and "eval_score_mean" in lines[1]
    )
    assert (run_dir / "checkpoint.pt").is_file() and json.loads(
        (run_dir / "scores.json").read_text()
    )["steps"] == 20


def test_train_task_with_defaults_uses_collected_data_and_augment_artifact(tmp_path):
    """What `make train TASK=hopper-m-r` does after `make collect` and `make augment`."""
    make_minari_dataset("local/hopper/medium-replay-v0", make_episodes(6, 11, 3, seed=0))
    task = get_task("hopper-m-r")
    settings = table_settings(task, "td3bc")
    artifact = default_artifact_path(task, settings)
    artifact.parent.mkdir(parents=True)
    write_synthetic(artifact, "hopper-m-r", hyper_parameters=settings.to_dict(), seeds={"seed": 0})
    result = CliRunner().invoke(
        app, ["train", "hopper-m-r", *TINY, "--out", str(tmp_path), "--json"]
    )
    assert result.exit_code == 0, result.output
    run_dir = Path(json.loads(result.stdout)["run_dir"])
    config = json.loads((run_dir / "config.json").read_text())
    assert config["artifact_choice"] == "table" and config["artifact_seed"] == 0
    assert config["source_id"] == "local/hopper/medium-replay-v0"
    assert config["artifact_path"] == str(artifact) and config["n_synthetic"] == 20


def test_table_output_and_finished_run_is_not_retrained(tmp_path, tiny_pair):
    source, artifact = tiny_pair
    args = [
        "train",
        "hopper-m-r",
        "--learner",
        "iql",
        "--data",
        "source",
        "--source",
        source,
        *TINY,
        "--out",
        str(tmp_path / "r"),
    ]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    assert "D4RL-normalized" in first.stdout and "iql" in first.stdout
    # a finished run again (a `set -e` seed loop): its stored scores, exit 0, nothing retrained
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0, again.output
    assert "already finished 20 updates" in again.stderr
    assert first.stdout == again.stdout


def test_missing_artifact_tells_the_user_to_augment(tiny_pair):
    source, _ = tiny_pair
    result = CliRunner().invoke(app, ["train", "hopper-m-r", "--source", source, *TINY])
    assert result.exit_code == 2
    # a --source of its own: the command builds from that source, not the task's dataset
    assert f"hipode augment hopper-m-r --source {source}" in " ".join(result.output.split())
    # the task's own data: the make target too
    make_minari_dataset("local/hopper/medium-replay-v0", make_episodes(6, 11, 3, seed=0))
    own = CliRunner().invoke(app, ["train", "hopper-m-r", "--artifact-seed", "2", *TINY])
    assert own.exit_code == 2
    text = " ".join(own.output.split())
    assert "hipode augment hopper-m-r --seed 2" in text
    assert 'make augment TASK=hopper-m-r ARGS="--seed 2"' in text


def test_interrupted_run_resumes_exactly(tmp_path, tiny_pair, monkeypatch):
    source, artifact = tiny_pair
    common = dict(
        steps=30,
        eval_every=10,
        eval_episodes=1,
        source=source,
        artifact=artifact,
        batch_size=32,
        show_progress=False,
    )
    reference = run_training("hopper-m-r", out_dir=tmp_path / "a", **common)

    real_evaluate, calls = train_module.evaluate_policies, []

    def interrupt_on_second_evaluation(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_evaluate(*args, **kwargs)

    monkeypatch.setattr(train_module, "evaluate_policies", interrupt_on_second_evaluation)
    with pytest.raises(KeyboardInterrupt):
        run_training("hopper-m-r", out_dir=tmp_path / "b", **common)
    monkeypatch.setattr(train_module, "evaluate_policies", real_evaluate)
    resumed = run_training("hopper-m-r", out_dir=tmp_path / "b", **common)
    assert resumed.resumed_from == 10 and resumed.steps == 30
    assert resumed.evaluations == reference.evaluations
    assert Path(reference.run_dir).name == Path(resumed.run_dir).name
    a = torch.load(Path(reference.run_dir) / "checkpoint.pt", weights_only=True)
    b = torch.load(Path(resumed.run_dir) / "checkpoint.pt", weights_only=True)
    for key in a["learner"]["modules"]:
        for name, tensor in a["learner"]["modules"][key].items():
            assert torch.equal(tensor, b["learner"]["modules"][key][name]), (key, name)
    steps = [
        json.loads(x)["step"]
        for x in (Path(resumed.run_dir) / "metrics.jsonl").read_text().splitlines()
    ]
    assert steps == [10, 20, 30]


def test_rerun_with_other_settings_is_refused(tmp_path, tiny_pair):
    source, artifact = tiny_pair
    common = dict(
        steps=10,
        eval_every=10,
        eval_episodes=1,
        source=source,
        artifact=artifact,
        batch_size=16,
        show_progress=False,
    )
    result = run_training("hopper-m-r", out_dir=tmp_path, name="fixed", **common)
    # one --name, other data settings: refused before anything in the folder changes
    before = {p.name: p.stat().st_mtime_ns for p in Path(result.run_dir).iterdir()}
    with pytest.raises(OverwriteError, match="eta"):
        run_training("hopper-m-r", out_dir=tmp_path, eta=0.1, name="fixed", **common)
    assert {p.name: p.stat().st_mtime_ns for p in Path(result.run_dir).iterdir()} == before
    # the read-only check a sweep uses: finished at this budget, not at a longer one
    run_dir = Path(result.run_dir)
    same = {"eta": result.eta, "seed": 0, "data": "merged"}
    assert run_folder.finished_scores(run_dir, 10, same)["steps"] == 10
    assert run_folder.finished_scores(run_dir, 20, same) is None
    with pytest.raises(OverwriteError, match="seed"):
        run_folder.finished_scores(run_dir, 10, {**same, "seed": 1})


def small_transitions() -> Transitions:
    """Episode A: rows 0-1, ends terminal; episode B: rows 2-4, ends by timeout."""
    obs = np.arange(5, dtype=np.float32)[:, None] * 10
    next_obs = obs + 1
    return Transitions(
        obs,
        obs / 10,
        np.arange(5, dtype=np.float32),
        next_obs,
        np.arange(5) == 1,
        np.arange(5) == 4,
    )


def test_d3rlpy_rows_keep_each_transition_aligned():
    rows = episode_arrays(small_transitions())
    # a terminal episode keeps its rows; a timeout episode gets a closing row with its last s'
    assert rows["observations"][:, 0].tolist() == [0, 10, 20, 30, 40, 41]
    assert rows["terminals"].tolist() == [0, 1, 0, 0, 0, 0]
    assert rows["timeouts"].tolist() == [0, 0, 0, 0, 0, 1]
    assert rows["rewards"].tolist() == [0, 1, 2, 3, 4, 0]
    one_step = episode_arrays(small_transitions(), every_row_is_an_episode=True)
    # terminal row 1 stays one row; the four others each get their s' as a closing row
    assert one_step["observations"][:, 0].tolist() == [0, 1, 10, 20, 21, 30, 31, 40, 41]
    assert one_step["timeouts"].sum() == 4 and one_step["terminals"].tolist()[2] == 1


def test_d3rlpy_learner_trains_a_few_steps(tmp_path, tiny_pair):
    pytest.importorskip("d3rlpy", reason="the d3rlpy extra is not installed")
    from hipode_pipeline.learners.external import build_d3rlpy_buffer

    real_buffer, mixed = build_d3rlpy_buffer(small_transitions(), small_transitions(), 0.5)
    assert real_buffer.transition_count == 5
    picked = [
        real_buffer.transition_picker(ep, i)
        for ep in real_buffer.episodes
        for i in range(ep.transition_count)
    ]
    assert [(t.observation[0], t.next_observation[0], float(t.reward[0])) for t in picked] == [
        (0, 10, 0),
        (10, 0, 1),
        (20, 30, 2),
        (30, 40, 3),
        (40, 41, 4),
    ]  # d3rlpy zeroes a terminal's successor
    assert mixed.sample_transition_batch(8).observations.shape == (8, 1)
    source, artifact = tiny_pair
    result = run_training(
        "hopper-m-r",
        "d3rlpy:TD3PlusBC",
        steps=20,
        eval_every=10,
        eval_episodes=1,
        out_dir=tmp_path,
        source=source,
        artifact=artifact,
        batch_size=32,
        show_progress=False,
    )
    assert result.steps == 20 and result.last["return_mean"] is not None


@pytest.mark.parametrize(
    ("algo", "expected"),
    [
        ("TD3PlusBC", {"alpha": 2.5}),
        ("CQL", {"conservative_weight": 10.0}),
        # hopper-m-r: CORL's IQL normalizes rewards (stages/train.toml), so d3rlpy's does too
        ("IQL", {"reward_scaler": "ReturnBasedRewardScaler"}),
    ],
)
def test_d3rlpy_gets_the_papers_alpha_and_iqls_reward_scaling(tmp_path, tiny_pair, algo, expected):
    pytest.importorskip("d3rlpy", reason="the d3rlpy extra is not installed")
    source, artifact = tiny_pair
    result = run_training(
        "hopper-m-r",
        f"d3rlpy:{algo}",
        steps=4,
        eval_every=4,
        eval_episodes=1,
        out_dir=tmp_path,
        source=source,
        artifact=artifact,
        batch_size=16,
        show_progress=False,
    )
    settings = json.loads((Path(result.run_dir) / "config.json").read_text())["d3rlpy_settings"]
    assert expected.items() <= settings.items(), settings


def _train_with_logger(logger, tmp_path, tiny_pair):
    """A tiny training run with `--logger`; its run folder."""
    source, artifact = tiny_pair
    args = ["train", "hopper-m-r", "--source", source, "--artifact", str(artifact), *TINY]
    args += ["--out", str(tmp_path / "runs"), "--logger", logger, "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    return Path(json.loads(result.stdout)["run_dir"])


def test_tensorboard_logs_appear_when_asked(tmp_path, tiny_pair):
    pytest.importorskip("tensorboard", reason="the tensorboard extra is not installed")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_dir = _train_with_logger("tensorboard", tmp_path, tiny_pair)
    events = EventAccumulator(str(run_dir / "tensorboard"))
    events.Reload()
    tags = events.Tags()["scalars"]
    assert "train/critic_loss" in tags and "eval/score_mean" in tags
    assert [e.step for e in events.Scalars("eval/score_mean")] == [10, 20]


def test_wandb_logs_offline_when_asked(tmp_path, tiny_pair, monkeypatch):
    pytest.importorskip("wandb", reason="the wandb extra is not installed")
    monkeypatch.delenv("WANDB_MODE", raising=False)  # offline is the default, no network needed
    run_dir = _train_with_logger("wandb", tmp_path, tiny_pair)
    # two stacked seeds: two W&B runs open in one process, each whole when training returns
    source, artifact = tiny_pair
    args = ["train", "hopper-m-r", "--source", source, "--artifact", str(artifact), *TINY]
    args += ["--seeds", "0-1", "--out", str(tmp_path / "stacked"), "--logger", "wandb", "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    stacked = [Path(record["run_dir"]) for record in json.loads(result.stdout)]
    for folder in [run_dir, *stacked]:
        offline = list((folder / "wandb").glob("offline-run-*"))
        assert len(offline) == 1, list((folder / "wandb").iterdir())
        history = list(offline[0].glob("*.wandb"))
        assert history and b"eval/score_mean" in history[0].read_bytes()  # the logged scalars


def test_unknown_logger_is_refused_before_any_work(tmp_path, tiny_pair):
    source, artifact = tiny_pair
    args = ["train", "hopper-m-r", "--source", source, "--artifact", str(artifact), *TINY]
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "runs"), "--logger", "mlflow"])
    assert result.exit_code == 2 and "--logger" in result.output
    assert not (tmp_path / "runs").exists()


def test_ctrl_c_checkpoints_and_the_same_command_resumes(tmp_path, tiny_pair):
    import os
    import signal
    import subprocess
    import sys
    import time

    source, artifact = tiny_pair
    args = [sys.executable, "-m", "hipode_pipeline", "train", "hopper-m-r", "--source", source]
    args += ["--artifact", str(artifact), "--steps", "500000", "--eval-every", "250000"]
    args += ["--eval-episodes", "1", "--batch-size", "32", "--out", str(tmp_path / "runs")]
    env = {**os.environ, "HIPODE_PROGRESS_EVERY": "0.5"}

    def run_until(marker: str) -> tuple[str, str, int]:
        process = subprocess.Popen(args, stderr=subprocess.PIPE, text=True, env=env)
        seen, deadline = [], time.time() + 120
        for line in process.stderr:  # wait until updates are running
            seen.append(line)
            if line.startswith(marker) or time.time() > deadline:
                break
        time.sleep(1.0)
        process.send_signal(signal.SIGINT)
        rest = process.stderr.read()
        return "".join(seen), rest, process.wait(timeout=60)

    _, rest, code = run_until("train td3bc")
    assert code == 130, rest
    assert "interrupted after update" in rest and "run the same command again" in rest
    (run_dir,) = (tmp_path / "runs" / "hopper-m-r").iterdir()
    stopped_at = torch.load(run_dir / "checkpoint.pt", weights_only=False)["learner"]["step"]
    assert 0 < stopped_at < 500_000
    assert f"interrupted after update {stopped_at:,}" in rest
    # the same command resumes from that update
    seen, rest, code = run_until("train td3bc")
    assert f"from step {stopped_at}" in seen and code == 130, seen + rest
