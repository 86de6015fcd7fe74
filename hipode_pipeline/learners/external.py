"""Other libraries' learners on the same data: d3rlpy 2.x (`--learner d3rlpy:TD3PlusBC`).

d3rlpy's dataset is built from our arrays, not through its `get_minari`, which misaligns
observations from the second episode on. Its transitions come from consecutive rows of an
episode, so a real episode becomes its observations plus, unless it ended in a terminal, one
closing row holding the last next-observation (flagged timeout); every synthetic transition
becomes its own episode: [s, s'] with a timeout, or [s] with a terminal (d3rlpy gives a
terminal row a zero successor, which a terminal never bootstraps from). Batches mix real and
synthetic rows with d3rlpy's own MixedReplayBuffer at ratio η.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hipode_pipeline import console
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import HipodeError
from hipode_pipeline.evaluate import evaluate_policy
from hipode_pipeline.files import write_json_atomic
from hipode_pipeline.run_folder import TrainResult, data_identity, finish_run, open_run_dir

D3RLPY_VERSION = "2.8.1"
# where each d3rlpy algorithm takes the paper's learner alpha (TD3+BC's alpha, CQL's weight)
ALPHA_FIELDS = {"TD3PlusBC": "alpha", "CQL": "conservative_weight", "CalQL": "conservative_weight"}


def require_d3rlpy():
    """Import d3rlpy or say how to get it."""
    try:
        import d3rlpy
    except ImportError:
        raise HipodeError(
            f"learner d3rlpy:*: expected d3rlpy=={D3RLPY_VERSION} installed (the project's "
            "'d3rlpy' extra); it pins gymnasium 1.0.0, so install it in a separate virtual "
            "environment with torch, then this project with --no-deps"
        ) from None
    return d3rlpy


def episode_arrays(
    transitions: Transitions, *, every_row_is_an_episode: bool = False
) -> dict[str, np.ndarray]:
    """Row arrays for d3rlpy's MDPDataset (observations, actions, rewards, terminals, timeouts).

    A non-terminal episode end gets one closing row [s'_last, 0, 0] flagged timeout; a trailing
    unfinished episode is closed the same way. `every_row_is_an_episode` treats each transition
    as a one-step episode (synthetic data).
    """
    n = len(transitions)
    ends = (
        np.ones(n, bool)
        if every_row_is_an_episode
        else transitions.terminals | transitions.timeouts
    )
    ends[-1] = True
    closing = np.flatnonzero(ends & ~transitions.terminals)
    at = closing + 1  # np.insert puts each closing row right after its episode's last transition
    return {
        "observations": np.insert(
            transitions.observations, at, transitions.next_observations[closing], axis=0
        ),
        "actions": np.insert(transitions.actions, at, 0.0, axis=0),
        "rewards": np.insert(transitions.rewards, at, 0.0),
        "terminals": np.insert(transitions.terminals.astype(np.float32), at, 0.0),
        "timeouts": np.insert(np.zeros(n, np.float32), at, 1.0),
    }


def build_d3rlpy_buffer(merged_real: Transitions, synthetic: Transitions | None, eta: float):
    """d3rlpy replay buffer: real only (η = 0), else MixedReplayBuffer(real, synthetic, η)."""
    d3rlpy = require_d3rlpy()
    real = d3rlpy.dataset.MDPDataset(**episode_arrays(merged_real), action_size=merged_real.act_dim)
    if synthetic is None or len(synthetic) == 0 or eta == 0:
        return real, real
    fake = d3rlpy.dataset.MDPDataset(
        **episode_arrays(synthetic, every_row_is_an_episode=True), action_size=synthetic.act_dim
    )
    return real, d3rlpy.dataset.MixedReplayBuffer(real, fake, secondary_mix_ratio=eta)


def train_d3rlpy(algo_name: str, merged, **settings):
    """Train d3rlpy's `algo_name` (settings: see `_train_d3rlpy`); d3rlpy logs to stdout, which
    is kept for results (--json), so its lines go to stderr."""
    with contextlib.redirect_stdout(sys.stderr):
        return _train_d3rlpy(algo_name, merged, **settings)


def _train_d3rlpy(
    algo_name: str,
    merged,
    *,
    config: dict[str, Any],
    run_dir: Path,
    run_state: str,
    device: torch.device,
    show_progress: bool = True,
) -> TrainResult:
    """Train d3rlpy's `algo_name` (e.g. TD3PlusBC) on the merged data with the run's `config`
    (built and checked by stage two's driver), evaluate it like ours and write config.json,
    metrics.jsonl and scores.json. No resume: d3rlpy keeps its own state, so an unfinished
    folder starts over."""
    d3rlpy = require_d3rlpy()
    config_class = getattr(d3rlpy.algos, f"{algo_name}Config", None)
    if config_class is None:
        raise HipodeError(
            f"learner d3rlpy:{algo_name}: expected a d3rlpy algorithm name "
            "such as TD3PlusBC, IQL or CQL"
        )
    steps, seed, eval_every = config["steps"], config["seed"], config["eval_every"]
    open_run_dir(run_dir, "replace" if run_state == "resume" else run_state)
    d3rlpy.seed(seed)
    real = merged.real
    # state statistics from the real data only, as our learners do (d3rlpy adds its eps itself)
    scaler = d3rlpy.preprocessing.StandardObservationScaler(
        mean=real.observations.mean(0), std=real.observations.std(0)
    )
    settings: dict[str, Any] = {"batch_size": config["batch_size"], "observation_scaler": scaler}
    learner_alpha = config["learner_config"].get("alpha")
    if learner_alpha is not None and algo_name in ALPHA_FIELDS:
        settings[ALPHA_FIELDS[algo_name]] = float(learner_alpha)
    if algo_name == "IQL" and config["learner_config"].get("normalize_reward"):
        # r · 1000 / (max − min episode return), fitted on the real buffer as our IQL does
        totals = real.episode_returns()
        settings["reward_scaler"] = d3rlpy.preprocessing.ReturnBasedRewardScaler(
            return_max=float(totals.max()), return_min=float(totals.min()), multiplier=1000.0
        )
    algo = config_class(**settings).create(device="cuda:0" if device.type == "cuda" else "cpu:0")
    real_buffer, buffer = build_d3rlpy_buffer(real, merged.synthetic, config["eta"])
    algo.build_with_dataset(real_buffer)
    config = {
        **config,
        # what this run passed to d3rlpy beyond its defaults (objects by their class name)
        "d3rlpy_settings": {
            name: value if isinstance(value, int | float) else type(value).__name__
            for name, value in settings.items()
        },
        "versions": {**config["versions"], "d3rlpy": d3rlpy.__version__},
    }
    write_json_atomic(run_dir / "config.json", config)
    evaluations: list[dict[str, Any]] = []
    train_seconds = 0.0
    learner = config["learner"]
    with (
        console.progress(disable=not show_progress) as prog,
        open(run_dir / "metrics.jsonl", "w") as metrics_file,
    ):
        bar = prog.add_task(f"train {learner} {config['task']}", total=steps, rate="", info="")
        window, done = time.perf_counter(), 0
        for step in range(1, steps + 1):
            losses = algo.update(buffer.sample_transition_batch(config["batch_size"]))
            done += 1
            if step % eval_every and step != steps:
                continue
            elapsed = time.perf_counter() - window
            train_seconds += elapsed
            result = evaluate_policy(
                algo.predict,
                config["env_id"],
                episodes=config["eval_episodes"],
                seed=seed,
                ref_min_score=config["ref_min_score"],
                ref_max_score=config["ref_max_score"],
                max_episode_steps=config.get("eval_max_episode_steps"),
            )
            evaluations.append({"step": step, **result.summary()})
            metrics_file.write(
                json.dumps(
                    {
                        "step": step,
                        **{k: float(v) for k, v in losses.items()},
                        "updates_per_s": done / elapsed,
                        **{f"eval_{k}": v for k, v in evaluations[-1].items() if k != "step"},
                    }
                )
                + "\n"
            )
            prog.update(
                bar,
                completed=step,
                rate=f"{done / elapsed:,.0f} upd/s",
                info=f"return {result.return_mean:.0f}",
            )
            window, done = time.perf_counter(), 0
    return finish_run(
        TrainResult(
            run_dir=str(run_dir),
            task=config["task"],
            learner=learner,
            data=config["data"],
            eta=config["eta"],
            steps=steps,
            last={},
            best=None,
            updates_per_second=steps / train_seconds if train_seconds else 0.0,
            resumed_from=0,
            evaluations=evaluations,
            seed=seed,
            env_id=config["env_id"],
            data_identity=data_identity(config),
        ),
        config["eval_episodes"],
    )
