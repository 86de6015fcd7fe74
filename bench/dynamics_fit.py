"""Benchmark: how well does the dynamics ensemble fit a source, per fitting setting?

Trains only the forward-dynamics ensemble (stage one's own model, data split and training
loop) on a local source under each variant, and measures its one-step error on the held-out
rows it never trained on: per row, the mean over state dimensions of |predicted - recorded
next state| / the source's next-state std (verify's and the per-stage diagnosis's unit), for
the ensemble's mean prediction (its elites where set), plus the reward's mean absolute error
in reward stds. Variants run in interleaved rounds (one per seed) on one torch thread; the
machine's load average is recorded beside each run.

    python bench/dynamics_fit.py --task halfcheetah-m-r --variants paper long fp32-long
    python bench/dynamics_fit.py --report-only

Writes bench/results/dynamics_fit.json (every run, appended and resumable: a finished
(task, variant, seed) is not rerun) and dynamics_fit.md (the table).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import torch
from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hipode_pipeline.data.load import load_source  # noqa: E402
from hipode_pipeline.data.normalizer import StateNormalizer  # noqa: E402
from hipode_pipeline.diagnose import one_step_errors  # noqa: E402
from hipode_pipeline.files import write_json_atomic, write_text_atomic  # noqa: E402
from hipode_pipeline.models import generators, training  # noqa: E402

RESULTS = REPO / "bench" / "results"
# generator overrides against the paper profile
VARIANTS: dict[str, dict] = {
    "paper": {},
    "long": {"dynamics_steps": 120_000},
    "fp32-long": {"dynamics_steps": 120_000, "dynamics_precision": "fp32"},
    "wide-long": {"dynamics_steps": 120_000, "dynamics_hidden": [512, 512]},
    "deep-long": {"dynamics_steps": 120_000, "dynamics_hidden": [200, 200, 200, 200]},
    "60k": {"dynamics_steps": 60_000},
    "cosine-60k": {"dynamics_steps": 60_000, "dynamics_lr_schedule": "cosine"},
    "cosine-long": {"dynamics_steps": 120_000, "dynamics_lr_schedule": "cosine"},
    "batch1024": {"dynamics_batch_size": 1024},
    "batch1024-60k": {"dynamics_steps": 60_000, "dynamics_batch_size": 1024},
    "no-decay-long": {"dynamics_steps": 120_000, "dynamics_weight_decay": 0.0},
    "lr3e-4-long": {"dynamics_steps": 120_000, "dynamics_lr": 3e-4},
}


def run_one(task: str, variant: str, seed: int, root: Path | None) -> dict:
    torch.set_num_threads(1)
    transitions, info = load_source(task, root, announce=False)
    config = generators.GeneratorConfig.profile(
        "paper", **_as_fields(VARIANTS[variant]), eval_every=1000
    )
    device = torch.device("cpu")
    models = generators.build_models(transitions.obs_dim, transitions.act_dim, config, seed)
    generators.set_data_scales(models, transitions, config)
    normalizer = StateNormalizer.fit(transitions.observations, eps=config.normalizer_eps)
    data = generators.transition_tensors(transitions, normalizer, config, seed, device)
    train_rows = len(transitions) - training.heldout_count(
        len(transitions), config.heldout_fraction
    )
    settings = generators.fit_settings(config, train_rows)["dynamics"]
    train_loss, heldout_loss = generators.model_losses(models)["dynamics"]
    load_before = load_average()
    with tempfile.TemporaryDirectory() as tmp:
        record = training.fit(
            "dynamics",
            models["dynamics"],
            train_loss,
            heldout_loss,
            data,
            seed=seed,
            eval_every=config.eval_every,
            checkpoint_every=settings["steps"] + 1,
            checkpoint_path=Path(tmp) / "never.pt",
            **settings,
        )
    dynamics = models["dynamics"].eval()
    dynamics.set_elites(generators.elite_members(record.member_best_heldout_losses, config))
    _, heldout = training.split_rows(len(transitions), config.heldout_fraction, seed)
    rows = np.sort(heldout.numpy())
    states = transitions.observations[rows]
    with torch.no_grad():
        next_norm, rewards = dynamics.sample(
            normalizer.normalize(torch.as_tensor(states)),
            torch.as_tensor(transitions.actions[rows]),
            use_mean=True,
        )
    predicted = normalizer.denormalize(next_norm.float().numpy())
    recorded = transitions.next_observations[rows]
    errors = one_step_errors(predicted, recorded, transitions.next_observations.std(axis=0))
    per_dim = errors.pop("per_dimension")
    reward_std = float(transitions.rewards.std())
    reward_error = np.abs(rewards.float().numpy() - transitions.rewards[rows]).mean()
    return {
        "task": task,
        "variant": variant,
        "seed": seed,
        "overrides": VARIANTS[variant],
        "source": info.id,
        "source_rows": len(transitions),
        "heldout_rows": int(len(rows)),
        "steps": settings["steps"],
        "seconds": round(record.seconds, 1),
        "one_step": errors,
        "per_dimension": per_dim,
        "reward_error_in_stds": float(reward_error / (reward_std + 1e-6)),
        "best_heldout_loss": record.best_heldout_loss,
        "load_before": load_before,
        "load_after": load_average(),
        "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
        "machine": cpu_name(),
    }


def _as_fields(overrides: dict) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}


def write_report(runs: list[dict]) -> None:
    lines = [
        "# Dynamics ensemble fit per setting",
        "",
        "`python bench/dynamics_fit.py` (the commands are in dynamics_fit.json). One-step error: "
        "per held-out row (rows the ensemble never trained on), the mean over state dimensions "
        "of |ensemble mean next state - recorded| / the source's next-state std; median and "
        "mean over rows. Reward: mean absolute error in reward stds. Each variant changes the "
        "paper profile's ensemble (5 members of 2 x 256, 30k steps of 256, bf16 matmuls, "
        "lr 1e-3, weight decay 1e-4, best weights kept per member) as listed. One torch "
        "thread; sources are the Gymnasium v5 datasets built here, not D4RL's files.",
        "",
        "| task | variant | overrides | seed | steps | one-step median / mean | reward | "
        "train (s) | date | load before → after |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(runs, key=lambda r: (r["task"], list(VARIANTS).index(r["variant"]), r["seed"])):
        lines.append(
            f"| {r['task']} | {r['variant']} | {json.dumps(r['overrides']) or '-'} | {r['seed']} "
            f"| {r['steps']:,} | {r['one_step']['median']:.4f} / {r['one_step']['mean']:.4f} "
            f"| {r['reward_error_in_stds']:.4f} | {r['seconds']:.0f} | {r['date']} "
            f"| {r['load_before']} → {r['load_after']} |"
        )
    write_text_atomic(RESULTS / "dynamics_fit.md", "\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", nargs="+", default=["halfcheetah-m-r"])
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=["paper"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--root", type=Path, default=None)
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args()
    path = RESULTS / "dynamics_fit.json"
    runs = json.loads(path.read_text()) if path.exists() else []
    done = {(r["task"], r["variant"], r["seed"]) for r in runs}
    command = "python bench/dynamics_fit.py " + " ".join(sys.argv[1:])
    if not args.report_only:
        for seed in args.seeds:  # interleaved rounds: every variant once per seed
            for task in args.task:
                for variant in args.variants:
                    if (task, variant, seed) in done:
                        continue
                    t0 = time.perf_counter()
                    run = {**run_one(task, variant, seed, args.root), "command": command}
                    runs.append(run)
                    write_json_atomic(path, runs)
                    print(
                        f"{task} {variant} seed {seed}: one-step median "
                        f"{run['one_step']['median']:.4f} mean {run['one_step']['mean']:.4f}, "
                        f"reward {run['reward_error_in_stds']:.4f}, "
                        f"{time.perf_counter() - t0:.0f} s",
                        flush=True,
                    )
    write_report(runs)


if __name__ == "__main__":
    main()
