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
from hipode_pipeline.errors import HipodeError, OverwriteError
from hipode_pipeline.evaluate import evaluate_policy

D3RLPY_VERSION = "2.8.1"


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
    task: str,
    data: str,
    eta: float,
    steps: int,
    seed: int,
    eval_every: int,
    eval_episodes: int,
    env_id: str,
    ref_scores: tuple[float | None, float | None],
    run_dir: Path,
    batch_size: int,
    device: torch.device,
    learner_alpha: float | None = None,
    force: bool = False,
    show_progress: bool = True,
):
    """Train d3rlpy's `algo_name` (e.g. TD3PlusBC) on the merged data, evaluate it like ours and
    write config.json, metrics.jsonl and scores.json (no resume: d3rlpy keeps its own state)."""
    from hipode_pipeline.files import write_json_atomic
    from hipode_pipeline.train import TrainResult, finish_run
    from hipode_pipeline.versions import package_versions

    d3rlpy = require_d3rlpy()
    config_class = getattr(d3rlpy.algos, f"{algo_name}Config", None)
    if config_class is None:
        raise HipodeError(
            f"learner d3rlpy:{algo_name}: expected a d3rlpy algorithm name "
            "such as TD3PlusBC, IQL or CQL"
        )
    if (run_dir / "scores.json").exists() and not force:
        raise OverwriteError(f"{run_dir} already holds a finished run; pass --force to train again")
    run_dir.mkdir(parents=True, exist_ok=True)
    d3rlpy.seed(seed)
    real = merged.real
    # state statistics from the real data only, as our learners do (d3rlpy adds its eps itself)
    scaler = d3rlpy.preprocessing.StandardObservationScaler(
        mean=real.observations.mean(0), std=real.observations.std(0)
    )
    settings: dict[str, Any] = {"batch_size": batch_size, "observation_scaler": scaler}
    if algo_name == "TD3PlusBC" and learner_alpha is not None:
        settings["alpha"] = learner_alpha
    algo = config_class(**settings).create(device="cuda:0" if device.type == "cuda" else "cpu:0")
    real_buffer, buffer = build_d3rlpy_buffer(real, merged.synthetic, eta)
    algo.build_with_dataset(real_buffer)
    ref_min, ref_max = ref_scores
    config = {
        "task": task,
        "learner": f"d3rlpy:{algo_name}",
        "data": data,
        "eta": eta,
        "seed": seed,
        "steps": steps,
        "batch_size": batch_size,
        "env_id": env_id,
        "source_sha256": merged.source["sha256"],
        "artifact_checksum": (merged.artifact_manifest or {}).get("checksum"),
        "artifact_path": None if merged.artifact_path is None else str(merged.artifact_path),
        "versions": {**package_versions(), "d3rlpy": d3rlpy.__version__},
    }
    write_json_atomic(run_dir / "config.json", config)
    evaluations: list[dict[str, Any]] = []
    train_seconds = 0.0
    with (
        console.progress(disable=not show_progress) as prog,
        open(run_dir / "metrics.jsonl", "w") as metrics_file,
    ):
        bar = prog.add_task(f"train d3rlpy:{algo_name} {task}", total=steps, rate="", info="")
        window, done = time.perf_counter(), 0
        for step in range(1, steps + 1):
            losses = algo.update(buffer.sample_transition_batch(batch_size))
            done += 1
            if step % eval_every and step != steps:
                continue
            elapsed = time.perf_counter() - window
            train_seconds += elapsed
            result = evaluate_policy(
                algo.predict,
                env_id,
                episodes=eval_episodes,
                seed=seed,
                ref_min_score=ref_min,
                ref_max_score=ref_max,
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
            task=task,
            learner=f"d3rlpy:{algo_name}",
            data=data,
            eta=eta,
            steps=steps,
            last={},
            best=None,
            updates_per_second=steps / train_seconds if train_seconds else 0.0,
            resumed_from=0,
            evaluations=evaluations,
        ),
        eval_episodes,
    )
