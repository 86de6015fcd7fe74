"""Which SAC settings reach HalfCheetah's medium band soonest in wall time on this CPU.

Runs SAC configurations side by side (one process and one core each, started together) for a
fixed wall time and records each one's learning curve every 10k env steps: env steps, gradient
updates, seconds and the mean return of the last 20 training episodes (stochastic actions,
the average lags the policy by about 20k steps). Writes bench/results/behaviour_trainers.json;
bench/collect.py shows the curves in collect.md.

    python bench/behaviour_trainers.py [--configs 128:0.5 256:0.5] [--seconds 1000]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def curve(env_id: str, hidden: int, updates_per_step: float, seconds: float, seed: int) -> None:
    """One configuration's curve as JSON lines on stdout (the worker process)."""
    import torch

    from hipode_pipeline.data.sac import SACConfig, SACTrainer
    from hipode_pipeline.tasks import all_tasks

    torch.set_num_threads(1)
    task = next(t for t in all_tasks().values() if t.env_id == env_id)
    config = SACConfig(hidden=hidden, updates_per_step=updates_per_step)
    trainer = SACTrainer(env_id, config, seed)
    started, next_point = time.perf_counter(), 10_000
    while time.perf_counter() - started < seconds:
        trainer.train_iteration()
        if trainer.steps >= next_point:
            next_point += 10_000
            mean = trainer.recent_return()
            point = {
                "steps": trainer.steps,
                "updates": trainer.updates,
                "seconds": round(time.perf_counter() - started, 1),
                "return": round(mean, 1),
                "normalized": round(task.normalized_score(mean), 2),
            }
            print(json.dumps(point), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--configs", nargs="+", default=["128:0.5", "256:0.5"])
    parser.add_argument("--seconds", type=float, default=1000.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--worker", nargs=2, metavar=("HIDDEN", "UPDATES_PER_STEP"))
    parser.add_argument("--plot-only", action="store_true", help="redraw the PNG from the JSON")
    args = parser.parse_args()
    if args.plot_only:
        plot(json.loads((RESULTS / "behaviour_trainers.json").read_text()))
        return
    if args.worker:
        curve(args.env, int(args.worker[0]), float(args.worker[1]), args.seconds, args.seed)
        return
    load_before = list(os.getloadavg())
    workers = {}
    for spec in args.configs:
        hidden, ratio = spec.split(":")
        command = [sys.executable, __file__, "--env", args.env, "--seconds", str(args.seconds)]
        command += ["--seed", str(args.seed), "--worker", hidden, ratio]
        workers[spec] = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
    curves = {}
    for spec, process in workers.items():
        out, _ = process.communicate()
        curves[spec] = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    report = {
        "command": " ".join(["python", "bench/behaviour_trainers.py", *sys.argv[1:]]),
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
        "env_id": args.env,
        "seed": args.seed,
        "seconds": args.seconds,
        "load_average_before": load_before,
        "load_average_after": list(os.getloadavg()),
        "curves": {
            spec: {
                "hidden": int(spec.split(":")[0]),
                "updates_per_step": float(spec.split(":")[1]),
                "points": points,
            }
            for spec, points in curves.items()
        },
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "behaviour_trainers.json").write_text(json.dumps(report, indent=2) + "\n")
    plot(report)
    print(json.dumps(report, indent=2))


def plot(report: dict) -> None:
    """Normalized training return against wall time and against env steps, per configuration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (by_time, by_steps) = plt.subplots(1, 2, figsize=(10, 4))
    for entry in report["curves"].values():
        points = entry["points"]
        label = f"SAC {entry['hidden']}-wide, {entry['updates_per_step']:g} updates/step"
        normalized = [p["normalized"] for p in points]
        by_time.plot([p["seconds"] / 60 for p in points], normalized, marker=".", label=label)
        by_steps.plot([p["steps"] / 1000 for p in points], normalized, marker=".", label=label)
    for axis, name in ((by_time, "wall time (min, one core)"), (by_steps, "env steps (k)")):
        axis.axhspan(29, 53, color="green", alpha=0.1, label="medium band [29, 53]")
        axis.set_xlabel(name)
        axis.set_ylabel("normalized return (last 20 training episodes)")
        axis.grid(alpha=0.3)
    by_time.legend(fontsize=8)
    figure.suptitle(f"{report['env_id']}: behaviour-policy training on this CPU")
    figure.tight_layout()
    figure.savefig(RESULTS / "behaviour_trainers.png", dpi=110)


if __name__ == "__main__":
    main()
