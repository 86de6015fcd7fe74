"""Stacked seeds against separate runs: the same K seeds trained once as one stacked learner
(`hipode train --seeds`) and once seed by seed (`--seed k`), on a task's source data (η = 0),
compared on the last score and the curve mean, with the wall time each way.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/stacked_seeds.py \
        --task hopper-m-r --seeds 0-4 --steps 20000 [--write]

Seed k's first updates are the same in both (tested in tests/test_learners.py); after that
float rounding makes the runs part ways, so the claim measured here is statistical: the two
ways give scores from one distribution. Both ways resume when the command is repeated.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import torch
from learner_precision import difference_interval, seed_statistics
from machine import LoadSampler, cpu_name, load_average

from hipode_pipeline.seeding import parse_seeds
from hipode_pipeline.train import run_training, train_seeds

RESULTS = Path(__file__).resolve().parent / "results"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="hopper-m-r")
    parser.add_argument("--learner", default="td3bc")
    parser.add_argument("--seeds", default="0-4")
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--eval-every", type=int, default=5000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("bench/out/stacked"))
    parser.add_argument("--write", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    seeds = parse_seeds(args.seeds)
    common = dict(
        steps=args.steps,
        eval_every=args.eval_every,
        eval_episodes=args.eval_episodes,
        show_progress=False,
    )
    started, load_before = datetime.now(UTC), load_average()
    with LoadSampler() as sampler:
        t0 = time.perf_counter()
        stacked = train_seeds(
            args.task,
            args.learner,
            "source",
            seeds=seeds,
            out_dir=args.out / "stacked",
            name="run",
            **common,
        )
        stacked_wall = time.perf_counter() - t0
        separate, separate_wall = [], 0.0
        for seed in seeds:
            t0 = time.perf_counter()
            separate.append(
                run_training(
                    args.task,
                    args.learner,
                    "source",
                    seed=seed,
                    out_dir=args.out / "separate",
                    name=f"run-seed{seed}",
                    **common,
                )
            )
            separate_wall += time.perf_counter() - t0
            print(f"separate seed {seed}: {separate[-1].last['score_mean']:.1f}", flush=True)
    rows = {}
    for label, results, wall in (
        ("stacked", stacked, stacked_wall),
        ("separate", separate, separate_wall),
    ):
        per_seed = [seed_statistics(r) for r in results]
        rows[label] = {
            "last": [s["last"] for s in per_seed],
            "curve_mean": [s["curve_mean"] for s in per_seed],
            "wall_s": round(wall, 1),
            "resumed_or_read": any(r.finished_earlier or r.resumed_from for r in results),
        }
    for statistic in ("last", "curve_mean"):
        low, high = difference_interval(rows["separate"][statistic], rows["stacked"][statistic])
        rows[f"{statistic}_difference"] = {
            "mean": float(
                np.mean(rows["stacked"][statistic]) - np.mean(rows["separate"][statistic])
            ),
            "ci95": [low, high],
            "within_noise": low <= 0.0 <= high,
        }
    report = {
        "command": "python bench/stacked_seeds.py " + " ".join(sys.argv[1:]),
        "date": started.isoformat(timespec="seconds"),
        "machine": f"{cpu_name()}, {platform.machine()}, torch {torch.__version__}",
        "load_average_before": load_before,
        "load_average_after": load_average(),
        "load_sampled": sampler.stats(),
        "task": args.task,
        "learner": args.learner,
        "steps": args.steps,
        "seeds": seeds,
        "rows": rows,
    }
    text = markdown(report)
    print(text)
    if args.write:
        (RESULTS / "stacked_seeds.json").write_text(json.dumps(report, indent=2) + "\n")
        (RESULTS / "stacked_seeds.md").write_text(text)


def markdown(report: dict) -> str:
    rows = report["rows"]
    lines = [
        f"# {report['learner']}: {len(report['seeds'])} seeds stacked in one process against "
        "the same seeds run one by one",
        "",
        f"Command: `{report['command']}` ({report['date']}); {report['machine']}; 1 torch "
        f"thread; load average {report['load_average_before']} before, "
        f"{report['load_average_after']} after (sampled: {report['load_sampled']}).",
        "",
        f"Data: {report['task']}'s locally collected Gymnasium MuJoCo v5 source dataset (η = 0), "
        "scored with D4RL's reference returns. Seeds "
        f"{report['seeds']}, {report['steps']:,} updates, 10 evaluation episodes per evaluation.",
        "",
        "| statistic | stacked mean | separate mean | stacked − separate | 95 % bootstrap CI "
        "| within noise |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for statistic in ("last", "curve_mean"):
        diff = rows[f"{statistic}_difference"]
        lines.append(
            f"| {statistic.replace('_', ' ')} | {np.mean(rows['stacked'][statistic]):.1f} | "
            f"{np.mean(rows['separate'][statistic]):.1f} | {diff['mean']:+.1f} | "
            f"[{diff['ci95'][0]:+.1f}, {diff['ci95'][1]:+.1f}] | "
            f"{'yes' if diff['within_noise'] else 'no'} |"
        )
    lines += [
        "",
        "Per seed (last score): stacked "
        + ", ".join(f"{v:.1f}" for v in rows["stacked"]["last"])
        + "; separate "
        + ", ".join(f"{v:.1f}" for v in rows["separate"]["last"])
        + ".",
        "",
        f"Wall time, evaluations included: stacked {rows['stacked']['wall_s']:.0f} s, separate "
        f"{rows['separate']['wall_s']:.0f} s in all "
        f"({rows['separate']['wall_s'] / max(rows['stacked']['wall_s'], 1e-9):.2f}× as long)"
        + (
            "; some runs were resumed or read back, so these times cover only what ran now"
            if rows["stacked"]["resumed_or_read"] or rows["separate"]["resumed_or_read"]
            else ""
        )
        + ".",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
