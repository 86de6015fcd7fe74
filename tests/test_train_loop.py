"""Stage two's loop: metrics are window means over each log interval, read at log time."""

from __future__ import annotations

import json

import torch

from hipode_pipeline import train as train_module


class CountingLearner:
    """Reports its own step number as a loss, and a second metric every other step."""

    def __init__(self):
        self.step = 0

    def update(self, batch):
        self.step += 1
        metrics = {"loss": torch.tensor(float(self.step))}
        if self.step % 2 == 0:
            metrics["actor_loss"] = torch.tensor(10.0 * self.step)
        return metrics

    def act(self, observations):
        return observations

    def state_dict(self):
        return {"step": self.step}


class NoReplay:
    def sample(self, batch_size):
        return None

    def state_dict(self):
        return {}


def test_metrics_lines_hold_window_means(tmp_path, monkeypatch):
    class Evaluation:
        def summary(self):
            return {"return_mean": 0.0, "return_std": 0.0, "score_mean": 1.0, "score_std": 0.0}

    monkeypatch.setattr(train_module, "make_evaluator", lambda policy, config: Evaluation)
    monkeypatch.setattr(train_module, "save_checkpoint", lambda path, state: None)
    config = {
        "steps": 8,
        "eval_every": 12,
        "log_every": 4,
        "batch_size": 1,
        "learner": "fake",
        "task": "hopper-m-r",
    }
    evaluations = []
    train_module._train_loop(
        CountingLearner(), NoReplay(), config, tmp_path, evaluations, show_progress=False
    )
    lines = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [line["step"] for line in lines] == [4, 8]
    # steps 1-4 and 5-8: means of 1..4 and 5..8; the every-other metric over its own steps
    assert [line["loss"] for line in lines] == [2.5, 6.5]
    assert [line["actor_loss"] for line in lines] == [30.0, 70.0]
    assert all(line["wall_s"] >= 0 for line in lines)
    assert [e["step"] for e in evaluations] == [8] and lines[1]["eval_score_mean"] == 1.0
