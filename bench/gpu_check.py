"""The GPU check: stage one on hopper-m-r, then TD3+BC with K seeds stacked in one process for as
many updates as the time budget allows, printing updates/s per seed and in total.

    bench/gpu_check.sh                 # on a lent GPU machine, within --budget-s (default 450)
    bench/gpu_check.sh --dry-run       # the same code path on CPU, tiny, in seconds (CI)

Steps: (1) `hipode collect` and `hipode augment` hopper-m-r (quick profiles in the dry run),
timed; (2) a speed probe of the update, K seeds, in each mode that might be fastest on this
device (eager fp32, eager bf16, torch.compile bf16), interleaved; (3) `train_seeds` with the
fastest mode for the updates that fit the time left, evaluated at the end. Everything prints
as plain lines, and a JSON summary goes to --json-out when given.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from hipode_pipeline.device import select_device
from hipode_pipeline.learners import TD3BC, TD3BCConfig
from hipode_pipeline.merge import load_merged
from hipode_pipeline.replay import MixedReplay

TASK = "hopper-m-r"
ANCHOR = "1M TD3+BC updates in 9 min on a GTX 1080 Ti (~1,850/s, JAX); CORL's PyTorch: 2.5 h"


def hipode(*args: str) -> dict:
    """One `hipode` command in a subprocess (its own threads and imports), JSON back."""
    command = [sys.executable, "-m", "hipode_pipeline", *args, "--json"]
    print("$ hipode " + " ".join(args), flush=True)
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        sys.stderr.write(done.stdout + done.stderr)
        raise SystemExit(f"gpu_check: `hipode {args[0]}` failed (exit {done.returncode})")
    return json.loads(done.stdout)


def probe(merged, device, seeds: list[int], mode: str, updates: int) -> float:
    """Updates/s of one stacked learner (all seeds) in `mode`, after a warm-up."""
    config = TD3BCConfig(bf16=mode != "fp32", compile=mode == "compile-bf16")
    learner = TD3BC(merged.real.obs_dim, merged.real.act_dim, config, device=device, seed=seeds)
    learner.fit_statistics(merged.real)
    replay = MixedReplay(
        merged.real, merged.synthetic, eta=0.5, mixing="mixed", device=device, seed=seeds
    )
    for _ in range(max(2, updates // 10)):  # warm-up (and compilation)
        learner.update(replay.sample(256))
    sync(device)
    start = time.perf_counter()
    for _ in range(updates):
        metrics = learner.update(replay.sample(256))
    float(metrics["critic_loss"].sum())  # waits for the device once
    return updates / (time.perf_counter() - start)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dry-run", action="store_true", help="CPU, tiny budgets (tests)")
    parser.add_argument("--root", type=Path, default=Path("datasets"))
    parser.add_argument("--out", type=Path, default=Path("bench/out/gpu_check"))
    parser.add_argument("--seeds", type=int, default=10, help="K seeds stacked")
    parser.add_argument("--budget-s", type=float, default=450.0, help="whole check")
    parser.add_argument("--json-out", type=Path, default=None)
    args = parser.parse_args()
    started = time.perf_counter()
    device = torch.device("cpu") if args.dry_run else select_device(None)
    if device.type != "cuda" and not args.dry_run:
        raise SystemExit("gpu_check: no CUDA device here; run with --dry-run on a CPU")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(f"device {device} ({name}), torch {torch.__version__}, {os.cpu_count()} CPUs", flush=True)
    profile = ["--profile", "quick"] if args.dry_run else []
    root = ["--root", str(args.root)]
    summary: dict = {"device": name, "torch": torch.__version__, "dry_run": args.dry_run}

    t0 = time.perf_counter()
    collected = hipode("collect", TASK, *root, *profile)
    summary["collect_s"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    built = hipode("augment", TASK, *root, *profile, "--device", str(device))
    summary["augment_s"] = round(time.perf_counter() - t0, 1)
    print(
        f"stage one: collect {summary['collect_s']} s ({collected.get('transitions', '?')} "
        f"transitions), augment {summary['augment_s']} s -> {built['artifact']}",
        flush=True,
    )

    merged = load_merged(TASK, Path(built["artifact"]), root=args.root)
    seeds = list(range(args.seeds))
    modes = ["fp32", "bf16"] + ([] if args.dry_run else ["compile-bf16"])
    updates = 5 if args.dry_run else 300
    rates: dict[str, list[float]] = {mode: [] for mode in modes}
    for _ in range(2):  # interleaved rounds
        for mode in modes:
            rates[mode].append(probe(merged, device, seeds, mode, updates))
    best_rate = {mode: max(values) for mode, values in rates.items()}
    for mode, rate in best_rate.items():
        print(
            f"probe {mode}: {rate:,.0f} updates/s per seed, {rate * len(seeds):,.0f} in all "
            f"(K = {len(seeds)})",
            flush=True,
        )
    fastest = max(best_rate, key=best_rate.get)
    summary["probe_updates_per_s_per_seed"] = best_rate

    left = args.budget_s - (time.perf_counter() - started)
    # evaluations (K seeds x 10 episodes) and start-up take time too: use 60 % of what is left
    steps = 20 if args.dry_run else max(1000, int(best_rate[fastest] * left * 0.6) // 1000 * 1000)
    from hipode_pipeline.train import train_seeds

    print(f"training {len(seeds)} seeds x {steps:,} updates ({fastest}), {left:.0f} s left")
    t0 = time.perf_counter()
    results = train_seeds(
        TASK,
        "td3bc",
        "merged",
        steps,
        seeds,
        eval_every=steps // 2 if steps >= 2 else 1,
        eval_episodes=2 if args.dry_run else 10,
        out_dir=args.out,
        artifact=Path(built["artifact"]),
        learner_settings={"bf16": fastest != "fp32", "compile": fastest == "compile-bf16"},
        device=str(device),
        root=args.root,
        force=True,
        show_progress=False,
    )
    wall = time.perf_counter() - t0
    per_seed = results[0].updates_per_second
    scores = [r.last.get("score_mean") for r in results]
    print(
        f"train: {per_seed:,.0f} updates/s per seed, {per_seed * len(seeds):,.0f} in all, "
        f"{wall:.0f} s wall with evaluations; last scores {scores}",
        flush=True,
    )
    print(f"anchor: {ANCHOR}; total {time.perf_counter() - started:.0f} s", flush=True)
    summary.update(
        steps=steps,
        seeds=len(seeds),
        mode=fastest,
        train_updates_per_s_per_seed=per_seed,
        train_wall_s=round(wall, 1),
        last_scores=scores,
        total_s=round(time.perf_counter() - started, 1),
    )
    if args.json_out:
        args.json_out.write_text(json.dumps(summary, indent=2) + "\n")


if __name__ == "__main__":
    main()
