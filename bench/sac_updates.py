"""Benchmark: SAC gradient updates per second, float32 against bfloat16 hidden matmuls.

Times the behaviour trainer's own update (`SACTrainer._update`: twin critics, actor and
temperature, batch 256) on HalfCheetah-v5 data from the trainer's random start, at 128 and 256
wide, one torch thread, in interleaved rounds (every setting once per round, the order
rotating) so that a change in the machine's load hits all settings alike. Reports the median
updates/s over rounds and each setting's ratio to float32 at the same width, with the load
average before and after.

    python bench/sac_updates.py [--rounds 5] [--updates 300]

Writes bench/results/sac_updates.json and .md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import torch
from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hipode_pipeline.data.sac import SACConfig, SACTrainer  # noqa: E402
from hipode_pipeline.files import write_json_atomic, write_text_atomic  # noqa: E402

RESULTS = REPO / "bench" / "results"
SETTINGS = [(hidden, dtype) for hidden in (128, 256) for dtype in ("float32", "bfloat16")]


def trainer_for(hidden: int, dtype: str) -> SACTrainer:
    trainer = SACTrainer(
        "HalfCheetah-v5", SACConfig(hidden=hidden, start_steps=5_000, matmul_dtype=dtype), 0
    )
    while trainer.steps < 5_000:
        trainer.buffer.add(trainer._collect())
    for _ in range(20):  # warm-up: allocator and kernels
        trainer._update()
    return trainer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--updates", type=int, default=300)
    args = parser.parse_args()
    torch.set_num_threads(1)
    load_before = load_average()
    trainers = {s: trainer_for(*s) for s in SETTINGS}
    rates: dict[tuple[int, str], list[float]] = {s: [] for s in SETTINGS}
    for round_index in range(args.rounds):
        order = SETTINGS[round_index % len(SETTINGS) :] + SETTINGS[: round_index % len(SETTINGS)]
        for setting in order:
            trainer = trainers[setting]
            started = time.perf_counter()
            for _ in range(args.updates):
                stats = trainer._update()
            float(stats["critic_loss"])  # one host read: the updates are done
            rates[setting].append(args.updates / (time.perf_counter() - started))
    load_after = load_average()
    rows = []
    for hidden, dtype in SETTINGS:
        median = statistics.median(rates[(hidden, dtype)])
        base = statistics.median(rates[(hidden, "float32")])
        rows.append(
            {
                "hidden": hidden,
                "matmul_dtype": dtype,
                "updates_per_second_median": round(median, 1),
                "updates_per_second_rounds": [round(r, 1) for r in rates[(hidden, dtype)]],
                "ratio_to_float32": round(median / base, 2),
            }
        )
    record = {
        "command": "python bench/sac_updates.py " + " ".join(sys.argv[1:]),
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
        "machine": cpu_name(),
        "cores": os.cpu_count(),
        "threads": 1,
        "rounds": args.rounds,
        "updates_per_round": args.updates,
        "load_before": load_before,
        "load_after": load_after,
        "rows": rows,
    }
    write_json_atomic(RESULTS / "sac_updates.json", record)
    lines = [
        "# SAC updates per second: float32 against bfloat16 hidden matmuls",
        "",
        f"`{record['command']}` on {record['machine']} ({record['cores']} cores, 1 torch "
        f"thread), {record['date_utc']} UTC; load average {load_before} before, {load_after} "
        f"after. {args.rounds} interleaved rounds of {args.updates} updates (batch 256, "
        "HalfCheetah-v5); median over rounds.",
        "",
        "| width | hidden matmuls | updates/s (median) | ratio to float32 | rounds |",
        "|---|---|---|---|---|",
    ]
    for row in rows:
        rounds = ", ".join(map(str, row["updates_per_second_rounds"]))
        lines.append(
            f"| {row['hidden']} | {row['matmul_dtype']} | {row['updates_per_second_median']} "
            f"| {row['ratio_to_float32']} | {rounds} |"
        )
    write_text_atomic(RESULTS / "sac_updates.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
