"""Benchmark: stage one's generators trained in fp32 against bf16 autocast on this machine's CPU.

bf16 autocast is the generators' default for the CVAEs and the dynamics ensemble, kept where
bf16 matmuls are native (AVX512-BF16 or AMX; `GeneratorConfig.on_device`). This measures what
that choice is worth on the CPU at hand: each of the five models trains for the same steps
from the same seeded init through the project's training loop (one held-out evaluation, at
the end, as stage one evaluates rarely), fp32 and bf16 in interleaved rounds (the order
alternating), one torch thread. Each row gives the median steps/s per precision over the
rounds and the median of the per-round ratios bf16 / fp32 (below 1: bf16 is slower) with their
range. The raw 1280x256 @ 256x256 matmul rate of both dtypes is measured the same way. The
value net's row is for reference: stage one trains it in fp32 everywhere.

    python bench/bf16_emulation.py [--rounds 4] [--steps 150] [--write]

With --write: bench/results/bf16_emulation.json and .md (--results DIR elsewhere).
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
from machine import LoadSampler, cpu_name, load_average
from models_precision import at_precision, hopper_random_rollouts, run_one

from hipode_pipeline.device import fast_bf16
from hipode_pipeline.files import write_json_atomic, write_text_atomic
from hipode_pipeline.models.generators import MODEL_NAMES, GeneratorConfig
from hipode_pipeline.versions import package_versions

RESULTS = Path(__file__).resolve().parent / "results"
PRECISIONS = ("fp32", "bf16")


def matmul_rate(dtype: torch.dtype, repeats: int = 50) -> float:
    """GFLOP/s of a 1280x256 @ 256x256 matmul in `dtype` (one thread)."""
    a, b = torch.randn(1280, 256, dtype=dtype), torch.randn(256, 256, dtype=dtype)
    for _ in range(3):  # first calls outside the clock: kernel selection, caches
        a @ b
    started = time.perf_counter()
    for _ in range(repeats):
        a @ b
    return 2 * 1280 * 256 * 256 * repeats / (time.perf_counter() - started) / 1e9


def train_rate(name: str, precision: str, transitions, steps: int) -> float:
    """Steps/s of model `name` trained `steps` steps at `precision`, one held-out evaluation."""
    config = at_precision(precision)
    return run_one(name, transitions, config, steps, 1, 0, evaluations=1)["steps_per_s"]


def interleaved(measure, rounds: int) -> dict[str, list[float]]:
    """measure(precision) for each precision in each round, the order alternating by round."""
    rates: dict[str, list[float]] = {p: [] for p in PRECISIONS}
    for index in range(rounds):
        for precision in PRECISIONS if index % 2 == 0 else PRECISIONS[::-1]:
            rates[precision].append(measure(precision))
    return rates


def row(name: str, rates: dict[str, list[float]], unit: str) -> dict:
    ratios = [b / f for f, b in zip(rates["fp32"], rates["bf16"], strict=True)]
    return {
        "what": name,
        "unit": unit,
        "fp32": statistics.median(rates["fp32"]),
        "bf16": statistics.median(rates["bf16"]),
        "bf16_over_fp32": statistics.median(ratios),
        "ratio_range": [min(ratios), max(ratios)],
        "rounds": len(ratios),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=4, help="even: each order as often")
    parser.add_argument("--steps", type=int, default=150, help="training steps per model and run")
    parser.add_argument("--transitions", type=int, default=20_000)
    parser.add_argument("--write", action="store_true")
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    cpu = torch.device("cpu")
    load_before = load_average()
    transitions = hopper_random_rollouts(args.transitions, seed=0)
    with LoadSampler() as load:
        dtypes = {"fp32": torch.float32, "bf16": torch.bfloat16}
        rows = [
            row(
                "matmul 1280x256 @ 256x256",
                interleaved(lambda p: matmul_rate(dtypes[p]), args.rounds),
                "GFLOP/s",
            )
        ]
        for name in MODEL_NAMES:
            rates = interleaved(
                lambda p, name=name: train_rate(name, p, transitions, args.steps),
                args.rounds,
            )
            label = f"{name} (stage one keeps it in fp32)" if name == "value" else name
            rows.append(row(label, rates, "steps/s"))
            print(rows[-1], flush=True)
    chosen, moved = GeneratorConfig().on_device(cpu)
    record = {
        "command": " ".join(["python bench/bf16_emulation.py", *sys.argv[1:]]),
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
        "machine": cpu_name(),
        "cores": os.cpu_count(),
        "native_bf16": fast_bf16(cpu),
        "stage_one_default_here": {
            **{k: v for k, v in chosen.to_dict().items() if k.endswith("_precision")},
            "moved_to_fp32": moved,
        },
        "steps_per_run": args.steps,
        "transitions": args.transitions,
        "threads": 1,
        "load_before": load_before,
        "load_after": load_average(),
        "load_sampled": load.stats(),
        "versions": package_versions(),
        "rows": rows,
    }
    lines = [
        "# Generators: fp32 against bf16 autocast on this CPU",
        "",
        f"Command: `{record['command']}` ({record['date_utc']} UTC); {record['machine']}, "
        f"{record['cores']} cores, 1 torch thread; bf16 native here: {record['native_bf16']}; "
        f"load average {record['load_before']} before, {record['load_after']} after "
        f"(sampled: {record['load_sampled']}).",
        "",
        f"Data: {args.transitions} random-action Hopper-v5 transitions; {args.steps} training "
        f"steps per model and run (default GeneratorConfig sizes, one held-out evaluation at "
        f"the end), {args.rounds} interleaved rounds; medians over rounds.",
        "",
        "| what | fp32 | bf16 | bf16 / fp32 (median; below 1: bf16 slower) | range over rounds |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['what']} ({r['unit']}) | {r['fp32']:.1f} | {r['bf16']:.1f} "
            f"| {r['bf16_over_fp32']:.2f}x | {r['ratio_range'][0]:.2f}–{r['ratio_range'][1]:.2f} |"
        )
    lines += [
        "",
        f"Stage one's default precisions here (`GeneratorConfig().on_device`): "
        f"{record['stage_one_default_here']}.",
    ]
    print("\n".join(lines))
    if args.write:
        args.results.mkdir(parents=True, exist_ok=True)
        write_json_atomic(args.results / "bf16_emulation.json", record)
        write_text_atomic(args.results / "bf16_emulation.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
