"""Stage two's loop: metrics are window means over each log interval, read at log time."""

from __future__ import annotations

import json

import torch

from hipode_pipeline import train as train_module


class CountingLearner:
    """Two seeds; seed k reports its step number plus 100 k as a loss, and a second metric every
    other step."""

    def __init__(self):
        self.step = 0

    def update(self, batch):
        self.step += 1
        offset = torch.tensor([0.0, 100.0])
        metrics = {"loss": float(self.step) + offset}
        if self.step % 2 == 0:
            metrics["actor_loss"] = 10.0 * self.step + offset
        return metrics

    def act_all(self, observations):
        return observations

    def seed_state(self, k):
        return {"step": self.step, "seed_index": k}


class NoReplay:
    def sample(self, batch_size):
        return None

    def seed_state(self, k):
        return {}


def test_metrics_lines_hold_window_means_per_seed(tmp_path, monkeypatch):
    class Evaluation:
        def __init__(self, score):
            self.score = score
            self.returns = [score]

        def summary(self):
            return {
                "return_mean": 0.0,
                "return_std": 0.0,
                "score_mean": self.score,
                "score_std": 0.0,
            }

    def evaluator(policies, config, seeds):
        return lambda: [Evaluation(float(seed)) for seed in seeds]

    saved = []
    monkeypatch.setattr(train_module, "make_evaluator", evaluator)
    monkeypatch.setattr(train_module, "save_checkpoint", lambda path, state: saved.append(state))
    config = {
        "steps": 8,
        "eval_every": 12,
        "log_every": 4,
        "batch_size": 1,
        "learner": "fake",
        "task": "hopper-m-r",
    }
    group = []
    for seed in (3, 7):
        (tmp_path / str(seed)).mkdir()
        group.append(
            train_module.SeedRun(seed, {**config, "seed": seed}, tmp_path / str(seed), "fresh")
        )
    train_module._train_loop(CountingLearner(), NoReplay(), group, show_progress=False)
    for k, seed in enumerate((3, 7)):
        lines = [
            json.loads(x) for x in (tmp_path / str(seed) / "metrics.jsonl").read_text().splitlines()
        ]
        assert [line["step"] for line in lines] == [4, 8]
        # steps 1-4 and 5-8: means of 1..4 and 5..8; the every-other metric over its own steps
        assert [line["loss"] for line in lines] == [2.5 + 100 * k, 6.5 + 100 * k]
        assert [line["actor_loss"] for line in lines] == [30.0 + 100 * k, 70.0 + 100 * k]
        assert all(line["wall_s"] >= 0 for line in lines)
        evaluations = group[k].evaluations
        assert [e["step"] for e in evaluations] == [8]
        assert lines[1]["eval_score_mean"] == float(seed) and lines[1]["eval_returns"] == [seed]
    # one checkpoint per seed per log line, each with that seed's own state
    assert [state["learner"]["seed_index"] for state in saved] == [0, 1, 0, 1]
