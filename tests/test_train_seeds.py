"""`hipode train --seeds`: K seeds in one process, each in the run folder a run of that seed
alone writes, resumable per seed, matching separate runs."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch
from test_train_cli import TINY
from typer.testing import CliRunner

import hipode_pipeline.train as train_module
from hipode_pipeline.cli import app
from hipode_pipeline.machine import cpu_name
from hipode_pipeline.train import run_training, train_seeds

COMMON = dict(steps=20, eval_every=10, eval_episodes=2, batch_size=32, show_progress=False)


def weights(run_dir: str) -> dict[str, torch.Tensor]:
    state = torch.load(Path(run_dir) / "checkpoint.pt", weights_only=True)["learner"]
    return {
        f"{key}.{name}": tensor
        for key, module in state["modules"].items()
        for name, tensor in module.items()
    }


def test_seeds_write_the_folders_single_runs_write(tmp_path, tiny_pair):
    source, artifact = tiny_pair
    args = ["train", "hopper-m-r", "--source", source, "--artifact", str(artifact), *TINY]
    result = CliRunner().invoke(app, [*args, "--seeds", "0-2", "--out", str(tmp_path / "k")])
    assert result.exit_code == 0, result.output
    assert "over 3 seeds" in result.stdout
    runs = sorted((tmp_path / "k" / "hopper-m-r").iterdir())
    assert [run.name.rsplit("-", 1)[1] for run in runs] == ["seed0", "seed1", "seed2"]
    for run in runs:
        config = json.loads((run / "config.json").read_text())
        assert config["seeds_trained_together"] == [0, 1, 2]
        assert config["seed"] == int(run.name[-1])
        lines = (run / "metrics.jsonl").read_text().splitlines()
        assert [json.loads(line)["step"] for line in lines] == [10, 20]
        assert len(json.loads(lines[-1])["eval_returns"]) == 2

    alone = CliRunner().invoke(
        app, [*args, "--seed", "1", "--out", str(tmp_path / "one"), "--json"]
    )
    assert alone.exit_code == 0, alone.output
    single = json.loads(alone.stdout)
    assert Path(single["run_dir"]).name == runs[1].name
    stacked, own = weights(str(runs[1])), weights(single["run_dir"])
    assert stacked.keys() == own.keys()
    for name, tensor in own.items():
        torch.testing.assert_close(stacked[name], tensor, rtol=1e-4, atol=1e-5, msg=name)
    assert not torch.equal(weights(str(runs[0]))["actor.weights.0"], own["actor.weights.0"])

    # rerun: every seed read back; one more seed: only that one trains
    again = CliRunner().invoke(
        app, [*args, "--seeds", "0-3", "--out", str(tmp_path / "k"), "--json"]
    )
    assert again.exit_code == 0, again.output
    records = json.loads(again.stdout)
    assert [r["seed"] for r in records] == [0, 1, 2, 3]
    assert [r["finished_earlier"] for r in records] == [True, True, True, False]


def test_interrupted_seeds_resume_exactly_and_groups_form_by_step(tmp_path, tiny_pair, monkeypatch):
    source, artifact = tiny_pair
    data = dict(source=source, artifact=artifact, **COMMON)
    reference = train_seeds("hopper-m-r", seeds=[0, 1], out_dir=tmp_path / "a", **data)

    real_evaluate, calls = train_module.evaluate_policies, []

    def interrupt_on_second_evaluation(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_evaluate(*args, **kwargs)

    real_versions = train_module.package_versions
    earlier_code = {"git_commit": "0" * 40, "git_modified": True}
    monkeypatch.setattr(train_module, "evaluate_policies", interrupt_on_second_evaluation)
    monkeypatch.setattr(
        train_module, "package_versions", lambda: {**real_versions(), **earlier_code}
    )
    with pytest.raises(KeyboardInterrupt):
        train_seeds("hopper-m-r", seeds=[0, 1], out_dir=tmp_path / "b", **data)
    monkeypatch.setattr(train_module, "evaluate_policies", real_evaluate)
    monkeypatch.setattr(train_module, "package_versions", real_versions)
    # seed 2 starts fresh beside seeds 0 and 1, which resume from step 10: two groups
    resumed = train_seeds("hopper-m-r", seeds=[0, 1, 2], out_dir=tmp_path / "b", **data)
    assert [r.resumed_from for r in resumed] == [10, 10, 0]
    sessions = json.loads((Path(resumed[0].run_dir) / "config.json").read_text())["sessions"]
    assert [(s["from_step"], s["seeds_trained_together"]) for s in sessions] == [
        (0, [0, 1]),
        (10, [0, 1]),
    ]
    # each session says when and on which CPU it ran; the finish is in scores.json
    iso_utc = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\+00:00"
    assert all(re.fullmatch(iso_utc, s["started_utc"]) for s in sessions)
    assert all(s["cpu"] == cpu_name() for s in sessions)
    # and from which code: the config's versions are the last session's only
    versions = json.loads((Path(resumed[0].run_dir) / "config.json").read_text())["versions"]
    code = [{key: s[key] for key in earlier_code} for s in sessions]
    assert code == [earlier_code, {key: versions[key] for key in earlier_code}]
    assert sessions[0]["started_utc"] <= sessions[1]["started_utc"]
    scores = json.loads((Path(resumed[0].run_dir) / "scores.json").read_text())
    assert scores["finished_utc"] >= sessions[1]["started_utc"]
    assert scores["cpu"] == cpu_name() and len(scores["load_average"]) == 3
    assert all(r.steps == 20 for r in resumed)
    for ref, got in zip(reference, resumed[:2], strict=True):
        assert got.evaluations == ref.evaluations
        for name, tensor in weights(ref.run_dir).items():
            assert torch.equal(tensor, weights(got.run_dir)[name]), name
    fresh = run_training("hopper-m-r", seed=2, out_dir=tmp_path / "c", **data)
    for name, tensor in weights(fresh.run_dir).items():
        torch.testing.assert_close(weights(resumed[2].run_dir)[name], tensor, msg=name)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--seeds", "0-x"], "expected seeds like 0-4"),
        (["--seeds", "1,1"], "each seed once"),
        (["--seeds", "3-1"], "0 <= low <= high"),
        (["--seed", "3", "--seeds", "0-1"], "give one of them"),
    ],
)
def test_bad_seed_lists_are_refused_before_any_work(tmp_path, tiny_pair, flags, message):
    source, artifact = tiny_pair
    out = tmp_path / "runs"
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
            str(out),
            *flags,
        ],
    )
    assert result.exit_code != 0 and message in result.output, result.output
    assert not out.exists()


def test_seed_lists_are_strict(tmp_path):
    from hipode_pipeline.errors import SettingError
    from hipode_pipeline.seeding import parse_seeds

    assert parse_seeds("0-2,7") == [0, 1, 2, 7] and parse_seeds(" 3 ") == [3]
    for text in ("1_000", "+3", "٣", "3-", "0--1", "-1", ""):
        with pytest.raises(SettingError, match="expected seeds like"):
            parse_seeds(text)
    with pytest.raises(SettingError, match="at most 10000 seeds"):
        parse_seeds("0-9999,10000-10001")


def test_too_many_evaluation_envs_and_repeated_folders_are_refused(tmp_path, tiny_pair):
    from hipode_pipeline.errors import SettingError

    source, artifact = tiny_pair
    data = dict(source=source, artifact=artifact, show_progress=False, steps=2)
    with pytest.raises(SettingError, match="evaluation episodes stepped together"):
        train_seeds("hopper-m-r", seeds=list(range(10)), eval_episodes=500, **data)
    with pytest.raises(SettingError, match="one per seed"):
        train_seeds("hopper-m-r", seeds=[0, 1], run_dirs=[tmp_path / "x", tmp_path / "x"], **data)
    assert not (tmp_path / "x").exists()
