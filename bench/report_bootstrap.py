"""Benchmark: `hipode report`'s bootstrap intervals, rliable call by call against at once.

rliable's get_interval_estimates calls the statistic once per resample (arch's loop, scipy's
trim_mean or Mann-Whitney U each time). `hipode report` draws the same resamples the same way
and computes the statistic on all of them at once (`hipode_pipeline.report`). Both are timed on
the same scores, in interleaved rounds (the order alternating), for the IQM and mean of one
arm's runs and for the probability of improvement of one arm over another, at the report's
5,000 resamples; each row gives the median seconds over rounds, the ratio, and the largest
difference between the two intervals' bounds, IQM's and mean's alike (zero up to rounding: the
same resamples).

    python bench/report_bootstrap.py [--rounds 3] [--reps 5000]

Writes bench/results/report_bootstrap.json and .md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
import warnings
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hipode_pipeline.files import write_json_atomic, write_text_atomic  # noqa: E402
from hipode_pipeline.report import improvement, interval_estimates  # noqa: E402

RESULTS = REPO / "bench" / "results"
# (statistic, runs of the arm, runs of the baseline): the sizes of one source's groups
CASES = [("iqm and mean", 10, None), ("iqm and mean", 30, None), ("P(improvement)", 10, 5)]
CASES += [("P(improvement)", 10, 10), ("P(improvement)", 30, 15)]  # equal sizes draw at once


def rliable_interval(scores, func, reps: int, seed: int) -> np.ndarray:
    """rliable's own interval, its global stream seeded as `hipode report` seeds it."""
    from rliable import library

    np.random.seed(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # arch on RandomState
        _, interval = library.get_interval_estimates(
            {"x": scores}, func, reps=reps, random_state=np.random.RandomState(seed)
        )
    return interval["x"]


def iqm_and_mean_bounds(estimates: dict) -> np.ndarray:
    """2 x 2, laid out as rliable's interval: rows lower and upper, columns IQM and mean."""
    return np.array([estimates["iqm_ci"], estimates["mean_ci"]]).T


def both(case: tuple, reps: int, seed: int) -> dict[str, tuple]:
    """name -> (function of no arguments returning the interval's bounds)."""
    from rliable import metrics

    statistic, n, m = case
    rng = np.random.default_rng(n * 100 + (m or 0))
    x, y = rng.normal(40.0, 8.0, size=n), rng.normal(37.0, 8.0, size=m or 1)
    if m is None:

        def iqm_and_mean(scores):
            return np.array([metrics.aggregate_iqm(scores), metrics.aggregate_mean(scores)])

        return {
            "rliable": lambda: rliable_interval(x.reshape(-1, 1), iqm_and_mean, reps, seed),
            "at once": lambda: iqm_and_mean_bounds(interval_estimates(x, reps, seed)),
        }
    pair = (x.reshape(-1, 1), y.reshape(-1, 1))
    return {
        "rliable": lambda: rliable_interval(pair, metrics.probability_of_improvement, reps, seed),
        "at once": lambda: np.array(improvement(x, y, reps, seed)["ci"])[:, None],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--reps", type=int, default=5000)
    args = parser.parse_args()
    load_before = load_average()
    rows = []
    for case in CASES:
        runs = both(case, args.reps, seed=0)
        seconds: dict[str, list[float]] = {name: [] for name in runs}
        bounds = {}
        for round_index in range(args.rounds):
            order = list(runs) if round_index % 2 == 0 else list(reversed(runs))
            for name in order:
                started = time.perf_counter()
                bounds[name] = runs[name]()
                seconds[name].append(time.perf_counter() - started)
        slow, fast = (statistics.median(seconds[name]) for name in ("rliable", "at once"))
        rows.append(
            {
                "statistic": case[0],
                "runs": case[1],
                "baseline_runs": case[2],
                "rliable_seconds": round(slow, 3),
                "at_once_seconds": round(fast, 4),
                "ratio": round(slow / fast, 1),
                "max_bound_difference": float(np.abs(bounds["rliable"] - bounds["at once"]).max()),
            }
        )
    load_after = load_average()
    record = {
        "command": " ".join(["python bench/report_bootstrap.py", *sys.argv[1:]]),
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
        "machine": cpu_name(),
        "cores": os.cpu_count(),
        "rounds": args.rounds,
        "reps": args.reps,
        "load_before": load_before,
        "load_after": load_after,
        "rows": rows,
    }
    write_json_atomic(RESULTS / "report_bootstrap.json", record)
    lines = [
        "# `hipode report`'s bootstrap intervals: rliable call by call against at once",
        "",
        f"`{record['command']}` on {record['machine']} ({record['cores']} cores), "
        f"{record['date_utc']} UTC; load average {load_before} before, {load_after} after. "
        f"{args.reps} resamples, seed 0; {args.rounds} interleaved rounds, median seconds.",
        "",
        "| statistic | runs | baseline runs | rliable s | at once s | ratio "
        "| largest bound difference |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['statistic']} | {row['runs']} | {row['baseline_runs'] or '-'} "
            f"| {row['rliable_seconds']} | {row['at_once_seconds']} | {row['ratio']}x "
            f"| {row['max_bound_difference']:.1e} |"
        )
    write_text_atomic(RESULTS / "report_bootstrap.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
