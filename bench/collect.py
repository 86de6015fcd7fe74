"""Benchmark of `hipode collect`: wall time and behaviour-policy returns of hopper-m-r and -m.

Runs the real collection (profile full) into the default dataset root and writes
bench/results/collect.json and bench/results/collect.md. The machine may be shared: the load
average before and after each phase is recorded beside the timings.

    python bench/collect.py [--fresh] [--seed 0] [--root DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import torch
from machine import cpu_name

from hipode_pipeline.data.collect import collect, work_dir
from hipode_pipeline.data.minari_write import dataset_dir
from hipode_pipeline.paths import use_datasets_root
from hipode_pipeline.tasks import get_task

RESULTS = Path(__file__).resolve().parent / "results"
TASKS = ("hopper-m-r", "hopper-m")


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--fresh",
        action="store_true",
        help="delete the hopper work folder and the datasets of --tasks first (retrain)",
    )
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--root", type=Path, default=None, help="dataset root (default: ./datasets)"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    root = use_datasets_root(args.root)
    if args.fresh:
        shutil.rmtree(work_dir(root, "hopper", args.seed), ignore_errors=True)
        for name in args.tasks:
            shutil.rmtree(dataset_dir(root, get_task(name).local_dataset_id), ignore_errors=True)
    command = " ".join(["python", "bench/collect.py", *sys.argv[1:]])
    runs = []
    for name in args.tasks:
        task = get_task(name)
        load_before, started = _load(), time.perf_counter()
        result = collect(
            task, root=root, seed=args.seed, profile="full", show_progress=sys.stderr.isatty()
        )
        wall = time.perf_counter() - started
        meta = json.loads((Path(result.path) / "data" / "metadata.json").read_text())["hipode"]
        runs.append(
            {
                "task": name,
                "command": command,
                "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
                "dataset_id": result.dataset_ids[0],
                "wall_seconds": round(wall, 1),
                "reused_existing_dataset": result.reused,
                "phase_seconds": result.phase_seconds,
                "env_steps_per_second": result.steps_per_second,
                "transitions": result.transitions,
                "episodes": result.episodes,
                "behaviour_policy": {
                    k: {f: v[f] for f in ("mean", "std", "normalized", "episodes", "stochastic")}
                    for k, v in meta["behaviour_policy"].items()
                },
                "medium_training": meta["training"].get("medium"),
                "dataset_episode_return": meta["dataset_episode_return"],
                "load_average_before": load_before,
                "load_average_after": _load(),
            }
        )
        print(json.dumps(runs[-1], indent=2), flush=True)
    # a partial rerun (--tasks) keeps the other tasks' recorded runs
    previous = RESULTS / "collect.json"
    if previous.exists():
        kept = json.loads(previous.read_text()).get("runs", [])
        runs += [r for r in kept if r["task"] not in args.tasks and "command" in r]
    runs.sort(key=lambda r: TASKS.index(r["task"]))
    report = {
        "machine": {
            "cpu": cpu_name(),
            "cores": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "note": "shared machine: other jobs ran beside this one; see the load averages",
        },
        "seed": args.seed,
        "runs": runs,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "collect.json").write_text(json.dumps(report, indent=2) + "\n")
    (RESULTS / "collect.md").write_text(_markdown(report))


def _markdown(report: dict) -> str:
    machine = report["machine"]
    lines = [
        "# `hipode collect` benchmark",
        "",
        f"Profile full, seed {report['seed']}; {machine['cpu']}, {machine['cores']} cores, "
        "1 torch thread. The machine was shared with other jobs: load averages (1/5/15 min) "
        "are shown per run. Behaviour return: the medium policy's measured return (mean ± std "
        "over its evaluation episodes, stochastic actions as in the rollouts) and its "
        "D4RL-normalized score.",
        "",
        "| task | command (UTC) | wall (s) | train (s) | train steps/s | rollout steps/s "
        "| transitions | episodes | behaviour return (normalized) | load before → after |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in report["runs"]:
        medium = run["behaviour_policy"].get("medium", {})
        speeds, phases = run["env_steps_per_second"], run["phase_seconds"]
        lines.append(
            f"| {run['task']} | `{run['command']}` ({run['date_utc']}) | {run['wall_seconds']} "
            f"| {phases.get('train', 0):.1f} | {speeds.get('train', '-')} "
            f"| {speeds.get('rollout', '-')} | {run['transitions']:,} | {run['episodes']:,} "
            f"| {medium.get('mean', float('nan')):,.0f} ± {medium.get('std', float('nan')):,.0f} "
            f"({medium.get('normalized', float('nan')):.1f}) "
            f"| {run['load_average_before']} → {run['load_average_after']} |"
        )
    training = next((r["medium_training"] for r in report["runs"] if r["medium_training"]), None)
    if training:
        check = training.get("check") or {}
        lines += [
            "",
            f"The medium policy is PPO's snapshot after {training['train_steps']:,} env steps "
            f"({training['train_seconds']:.0f} s of training; recent training return "
            f"{training['train_return']:,.0f} = {training['train_normalized']:.1f} normalized; "
            f"acceptance check {check.get('normalized', float('nan')):.1f} normalized, "
            f"in range: {training['target_reached']}). Every later kind reuses it.",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
