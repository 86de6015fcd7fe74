"""Precision parity of a stage-two learner: the same seeds trained in fp32 and with bf16 hidden
matmuls (heads, targets and losses fp32 in both), on each task's source data (η = 0), compared
on the last score and on the curve mean (the mean of all evaluations) over seeds.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/learner_precision.py \
        --tasks hopper-m-r,walker2d-m-r --seeds 0-4 --steps 100000 [--write]

Each task's two precisions run one after the other as two stacked groups of all seeds
(`train_seeds`), so a load change hits both; the runs live under --out and resume when the
command is repeated (a finished group is read back, not retrained). The verdict per task:
"within noise" when the 95 % bootstrap interval of the difference of seed means (bf16 − fp32)
holds zero for both statistics. bf16 becomes a default only where every task says so.
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
from machine import LoadSampler, cpu_name, load_average

from hipode_pipeline.seeding import parse_seeds
from hipode_pipeline.train import train_seeds

RESULTS = Path(__file__).resolve().parent / "results"
PRECISIONS = ("fp32", "bf16")
BOOTSTRAP = 10_000


def difference_interval(a: list[float], b: list[float], seed: int = 0) -> tuple[float, float]:
    """95 % percentile-bootstrap interval of mean(b) − mean(a), resampling seeds in each arm."""
    rng = np.random.default_rng(seed)
    a_arr, b_arr = np.asarray(a), np.asarray(b)
    draws = b_arr[rng.integers(0, len(b_arr), (BOOTSTRAP, len(b_arr)))].mean(1) - a_arr[
        rng.integers(0, len(a_arr), (BOOTSTRAP, len(a_arr)))
    ].mean(1)
    low, high = np.percentile(draws, [2.5, 97.5])
    return float(low), float(high)


def seed_statistics(result) -> dict[str, float]:
    scores = [e["score_mean"] for e in result.evaluations]
    return {"last": scores[-1], "curve_mean": float(np.mean(scores))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", default="hopper-m-r,walker2d-m-r")
    parser.add_argument("--learner", default="td3bc")
    parser.add_argument("--seeds", default="0-4")
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--eval-every", type=int, default=5000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path("bench/out/precision"))
    parser.add_argument("--write", action="store_true", help="write bench/results/")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    seeds = parse_seeds(args.seeds)
    tasks = [t.strip() for t in args.tasks.split(",") if t.strip()]
    command = "python bench/learner_precision.py " + " ".join(sys.argv[1:])
    started, load_before = datetime.now(UTC), load_average()
    rows: dict[str, dict] = {}
    with LoadSampler() as sampler:
        for task in tasks:
            rows[task] = {}
            for precision in PRECISIONS:
                t0 = time.perf_counter()
                print(f"{task} {precision}: seeds {seeds}, {args.steps} updates", flush=True)
                results = train_seeds(
                    task,
                    args.learner,
                    "source",
                    args.steps,
                    seeds,
                    args.eval_every,
                    args.eval_episodes,
                    args.out,
                    learner_settings={"bf16": precision == "bf16"},
                    name=f"{args.learner}-{precision}",
                    show_progress=False,
                )
                per_seed = [seed_statistics(r) for r in results]
                rows[task][precision] = {
                    "seeds": seeds,
                    "last": [s["last"] for s in per_seed],
                    "curve_mean": [s["curve_mean"] for s in per_seed],
                    "updates_per_s_per_seed": results[0].updates_per_second,
                    "finished_earlier": all(r.finished_earlier for r in results),
                    "wall_s": round(time.perf_counter() - t0, 1),
                    "curves": [[e["score_mean"] for e in r.evaluations] for r in results],
                    "eval_steps": [e["step"] for e in results[0].evaluations],
                }
                print(
                    f"  last {np.mean(rows[task][precision]['last']):.1f}, curve mean "
                    f"{np.mean(rows[task][precision]['curve_mean']):.1f} "
                    f"({rows[task][precision]['wall_s']:.0f} s)",
                    flush=True,
                )
            for statistic in ("last", "curve_mean"):
                a, b = rows[task]["fp32"][statistic], rows[task]["bf16"][statistic]
                low, high = difference_interval(a, b)
                rows[task][f"{statistic}_difference"] = {
                    "mean": float(np.mean(b) - np.mean(a)),
                    "ci95": [low, high],
                    "within_noise": low <= 0.0 <= high,
                }
    load = sampler.stats()
    verdict = all(
        rows[t][f"{s}_difference"]["within_noise"] for t in tasks for s in ("last", "curve_mean")
    )
    report = {
        "command": command,
        "date": started.isoformat(timespec="seconds"),
        "learner": args.learner,
        "tasks": tasks,
        "steps": args.steps,
        "seeds": seeds,
        "threads": args.threads,
        "machine": f"{cpu_name()}, {platform.machine()}, torch {torch.__version__}",
        "load_average_before": load_before,
        "load_average_after": load_average(),
        "load_sampled": load,
        "rows": rows,
        "bf16_within_noise_on_every_task": verdict,
    }
    print(markdown(report))
    if args.write:
        RESULTS.mkdir(exist_ok=True)
        (RESULTS / "learner_precision.json").write_text(json.dumps(report, indent=2) + "\n")
        (RESULTS / "learner_precision.md").write_text(markdown(report))


def markdown(report: dict) -> str:
    lines = [
        f"# {report['learner']}: bf16 hidden matmuls against fp32",
        "",
        f"Command: `{report['command']}` ({report['date']}); {report['machine']}; "
        f"{report['threads']} torch thread(s); load average {report['load_average_before']} "
        f"before, {report['load_average_after']} after (sampled: {report['load_sampled']}).",
        "",
        "Data: each task's locally collected Gymnasium MuJoCo v5 source dataset (η = 0), scored "
        "with D4RL's reference returns; not D4RL's own data. Scores: D4RL-normalized, the "
        f"mean over 10 evaluation episodes per evaluation; {len(report['seeds'])} training "
        f"seeds {report['seeds']} per precision, {report['steps']:,} updates.",
        "",
        "| task | statistic | fp32 mean | bf16 mean | bf16 − fp32 | 95 % bootstrap CI | "
        "within noise |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for task, row in report["rows"].items():
        for statistic in ("last", "curve_mean"):
            diff = row[f"{statistic}_difference"]
            lines.append(
                f"| {task} | {statistic.replace('_', ' ')} | {np.mean(row['fp32'][statistic]):.1f} "
                f"| {np.mean(row['bf16'][statistic]):.1f} | {diff['mean']:+.1f} | "
                f"[{diff['ci95'][0]:+.1f}, {diff['ci95'][1]:+.1f}] | "
                f"{'yes' if diff['within_noise'] else 'no'} |"
            )
    lines += ["", "Per seed (last score):", ""]
    for task, row in report["rows"].items():
        for precision in PRECISIONS:
            values = ", ".join(f"{v:.1f}" for v in row[precision]["last"])
            lines.append(
                f"- {task} {precision}: {values} ({row[precision]['updates_per_s_per_seed']:.0f} "
                "updates/s per seed while the group trained)"
            )
    verdict = report["bf16_within_noise_on_every_task"]
    lines += [
        "",
        f"Verdict: bf16 {'is' if verdict else 'is not'} within noise of fp32 on every task "
        "and statistic measured here. An interval that holds zero over 5 seeds is weak "
        "evidence of equality: it says the difference is smaller than the seed noise.",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
