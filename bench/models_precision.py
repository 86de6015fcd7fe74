"""Benchmark: steps/s and held-out loss of the generators in fp32 vs bf16 autocast, 1 and 2 threads.

Data: random-action rollouts of Hopper-v5 (11-dim states, 3-dim actions), collected here.
Each run trains one model from the same seeded init for a fixed number of steps through the
project's own training loop and reports wall-clock steps/s (held-out evaluations included)
and the final held-out loss evaluated in fp32. The machine is shared: the load average
before and after is printed with the results.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/models_precision.py [--write]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from machine import cpu_name, load_average

from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.models import generators, training
from hipode_pipeline.models.generators import MODEL_NAMES, GeneratorConfig

RESULTS = Path(__file__).resolve().parent / "results" / "models_precision.md"


def hopper_random_rollouts(n: int, seed: int) -> Transitions:
    """n transitions of Hopper-v5 under uniform random actions (episodes reset on termination)."""
    env = gym.make("Hopper-v5")
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    rows = {
        k: []
        for k in (
            "observations",
            "actions",
            "rewards",
            "next_observations",
            "terminals",
            "timeouts",
        )
    }
    for _ in range(n):
        action = rng.uniform(-1, 1, size=3).astype(np.float32)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for key, value in zip(
            rows, (obs, action, reward, next_obs, terminated, truncated), strict=True
        ):
            rows[key].append(value)
        obs = env.reset()[0] if terminated or truncated else next_obs
    env.close()
    arrays = {k: np.asarray(v) for k, v in rows.items()}
    for key in ("observations", "actions", "rewards", "next_observations"):
        arrays[key] = arrays[key].astype(np.float32)
    return Transitions(
        **{k: (v.astype(bool) if k in ("terminals", "timeouts") else v) for k, v in arrays.items()}
    )


def at_precision(precision: str, **overrides) -> GeneratorConfig:
    """Default config with every model family trained at `precision`."""
    families = ("cvae_precision", "value_precision", "dynamics_precision")
    return GeneratorConfig(**{f: precision for f in families}, **overrides)


def run_one(
    name: str,
    transitions: Transitions,
    config: GeneratorConfig,
    steps: int,
    threads: int,
    seed: int,
    evaluations: int = 10,
) -> dict:
    """Train one model for `steps` steps (`evaluations` held-out evaluations among them);
    return steps/s and held-out losses."""
    torch.set_num_threads(threads)
    device = torch.device("cpu")
    models = generators.build_models(transitions.obs_dim, transitions.act_dim, config, seed)
    generators.set_data_scales(models, transitions, config)
    normalizer = StateNormalizer.fit(transitions.observations)
    data = generators.transition_tensors(transitions, normalizer, config, seed, device)
    train_loss, heldout_loss = generators.model_losses(models)[name]
    settings = {**generators.fit_settings(config, len(transitions))[name], "steps": steps}
    with tempfile.TemporaryDirectory() as tmp:
        record = training.fit(
            name,
            models[name],
            train_loss,
            heldout_loss,
            data,
            seed=seed,
            eval_every=max(1, steps // evaluations),
            checkpoint_every=steps + 1,
            checkpoint_path=Path(tmp) / "never.pt",
            after_step=models["value"].update_target if name == "value" else None,
            **settings,
        )
    result = {
        "steps_per_s": steps / record.seconds,
        "final": record.final_heldout_loss,
        "best": record.best_heldout_loss,
    }
    held = data.heldout()
    pair = torch.cat([held["s"], held["s_next"]], -1)
    cvae_targets = {
        "state_transition": (held["s"], held["s_next"]),
        "inverse_action": (pair, held["a"]),
        "inverse_reward": (pair, held["r"][:, None]),
    }
    with torch.no_grad():
        if name in cvae_targets:
            cond, target = cvae_targets[name]
            sample = models[name].sample(cond, 1, torch.Generator().manual_seed(0))[:, 0]
            result["sample_mse"] = float((sample - target).pow(2).mean())
        if name == "dynamics":
            dynamics = models["dynamics"].eval()
            next_mean, reward_mean = dynamics.sample(held["s"], held["a"], use_mean=True)
            result["sample_mse"] = float((next_mean - held["s_next"]).pow(2).mean())
            result["reward_mse"] = float((reward_mean - held["r"]).pow(2).mean())
    return result


def quality_table(transitions: Transitions, args: argparse.Namespace) -> list[str]:
    rows = [
        "| model | precision | threads | seed | steps | steps/s | final held-out loss "
        "| best held-out loss | prior-sample (CVAE) / ensemble-mean (dynamics) MSE |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    budgets = {name: args.cvae_steps for name in MODEL_NAMES} | {"dynamics": args.dynamics_steps}
    for name, steps in budgets.items():
        for threads in args.quality_threads:
            for precision in ("fp32", "bf16"):
                for seed in args.seeds:
                    config = at_precision(precision)
                    r = run_one(name, transitions, config, steps, threads, seed)
                    rows.append(
                        f"| {name} | {precision} | {threads} | {seed} | {steps} "
                        f"| {r['steps_per_s']:.1f} | {r['final']:.4f} | {r['best']:.4f} "
                        f"| {r.get('sample_mse', float('nan')):.5f} |"
                    )
                    print(rows[-1], flush=True)
    return rows


def spectral_norm_table(transitions: Transitions, args: argparse.Namespace) -> list[str]:
    rows = [
        "| spectral norm | held-out NLL | ensemble-mean state MSE (z-scored) | reward MSE "
        "| reward variance |",
        "|---|---|---|---|---|",
    ]
    for flag in (False, True):
        config = at_precision("fp32", dynamics_spectral_norm=flag)
        r = run_one("dynamics", transitions, config, args.dynamics_steps, 1, 0)
        rows.append(
            f"| {flag} | {r['final']:.4f} | {r['sample_mse']:.5f} | {r['reward_mse']:.5f} "
            f"| {transitions.rewards.var():.5f} |"
        )
        print(rows[-1], flush=True)
    return rows


def throughput_table(transitions: Transitions, args: argparse.Namespace) -> list[str]:
    rows = ["| model | precision | threads | steps | steps/s |", "|---|---|---|---|---|"]
    steps = args.throughput_steps
    for precision in ("fp32", "bf16"):
        for threads in args.threads:
            for name in MODEL_NAMES:
                config = at_precision(precision)
                r = run_one(name, transitions, config, steps, threads, 0)
                rows.append(
                    f"| {name} | {precision} | {threads} | {steps} | {r['steps_per_s']:.1f} |"
                )
                print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transitions", type=int, default=50_000)
    parser.add_argument("--cvae-steps", type=int, default=3000)
    parser.add_argument("--dynamics-steps", type=int, default=2000)
    parser.add_argument(
        "--throughput-steps", type=int, default=600, help="steps per model, last table"
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="throughput table")
    parser.add_argument("--quality-threads", type=int, nargs="+", default=[1])
    parser.add_argument(
        "--write", action="store_true", help="write bench/results/models_precision.md"
    )
    args = parser.parse_args()

    started, load_before = time.time(), load_average()
    transitions = hopper_random_rollouts(args.transitions, seed=0)
    quality = quality_table(transitions, args)
    spectral = spectral_norm_table(transitions, args)
    through = throughput_table(transitions, args)
    omp = os.environ.get("OMP_WAIT_POLICY", "(unset)")
    header = [
        f"Machine: {cpu_name()}, {os.cpu_count()} logical CPUs shared with other jobs, "
        f"torch {torch.__version__}, Python {sys.version.split()[0]}, OMP_WAIT_POLICY={omp}.",
        f"Load average (1, 5, 15 min) before: {load_before}; after: {load_average()}. "
        f"Wall time {time.time() - started:.0f} s.",
        f"Data: {args.transitions} random-action Hopper-v5 transitions; held-out share "
        f"{GeneratorConfig().heldout_fraction}; batch sizes are GeneratorConfig's defaults.",
    ]
    print("\n".join(header))
    if not args.write:
        return
    command = " ".join(
        ["OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/models_precision.py", *sys.argv[1:]]
    )
    sections = [
        "# Generators: fp32 vs bf16 autocast on this CPU",
        "",
        f"Command: `{command}`",
        "",
        *header,
        "",
        "## Learning quality and speed of each model (held-out losses evaluated in fp32)",
        "",
        *quality,
        "",
        f"## Dynamics with and without d3rlpy's spectral norm (fp32, 1 thread, "
        f"{args.dynamics_steps} steps)",
        "",
        *spectral,
        "",
        "## Throughput of all five models",
        "",
        *through,
        "",
    ]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text("\n".join(sections))


if __name__ == "__main__":
    main()
