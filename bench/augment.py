"""Stage one's wall time, measured the way a user runs it: `hipode augment TASK` as a process.

Three runs: the real one (--force, so an existing artifact does not short-cut it; generators
are trained unless already cached, which the record says), a plain rerun (the artifact is up
to date and only verified) and a --force rerun (cached generators: load, generate, write).
Machine load is sampled during every run, since the machine may be shared.

    python bench/augment.py [--task hopper-m-r] [--profile full] [--seed 0]

Writes bench/results/augment.json and bench/results/augment.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

from machine import LoadSampler, cpu_name

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "bench" / "results"
RUNS = ("stage_one", "rerun_up_to_date", "rerun_forced_cached_generators")
PHASES = ("load", "verify", "train", "generate", "write", "total")


def run_stage_one(args: list[str], log: Path) -> dict:
    """Run `hipode augment ... --json`; return its summary, wall time and the load during it."""
    command = [str(Path(sys.executable).with_name("hipode")), "augment", *args, "--json"]
    env = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    started = time.perf_counter()
    with LoadSampler() as load, open(log, "w") as stderr:
        done = subprocess.run(
            command,
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
            check=False,
        )
    wall = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(
            f"{shlex.join(command)} failed with exit code {done.returncode}; see {log}"
        )
    return {
        "command": shlex.join(["hipode", *command[1:]]),
        "wall_seconds": round(wall, 2),
        "load_average_1min": load.stats(),
        "summary": json.loads(done.stdout),
    }


def phase_text(seconds: dict[str, float]) -> str:
    """Phases in the order they run (the JSON record sorts its keys)."""
    order = [p for p in PHASES if p in seconds] + sorted(set(seconds) - set(PHASES))
    return ", ".join(f"{name} {seconds[name]:.1f}" for name in order)


def relative(path: str) -> str:
    """Paths in the committed record are relative to the repository."""
    try:
        return str(Path(path).resolve().relative_to(REPO))
    except ValueError:
        return Path(path).name


def markdown(record: dict) -> str:
    real = record["runs"]["stage_one"]
    summary = real["summary"]
    rows = [
        ("N (source transitions)", f"{summary['n_source']:,}"),
        ("eta / lambda / n", f"{summary['eta']} / {summary['lam']} / {summary['n']}"),
        ("candidates drawn", f"{summary['source_states_drawn']:,}"),
        ("next states sampled", f"{summary['next_states_sampled']:,}"),
        ("non-finite dropped", f"{summary['nonfinite_dropped']:,}"),
        ("kept", f"{summary['kept']:,}"),
        ("terminals among kept", f"{summary['terminals']:,}"),
        (
            "dynamics error mean / median (z-scored)",
            f"{summary['dynamics_error_mean']:.4f} / {summary['dynamics_error_median']:.4f}",
        ),
        (
            f"novelty mean / median (z-scored, {summary['novelty_sample']} states)",
            f"{summary['novelty_mean']:.4f} / {summary['novelty_median']:.4f}",
        ),
        ("time per phase (s)", phase_text(summary["seconds"])),
        ("generators", "cached" if summary["generators_cached"] else "trained in this run"),
        ("device / profile", f"{summary['device']} / {summary['profile']}"),
        ("artifact", summary["artifact"]),
        ("artifact sha256", summary["artifact_sha256"]),
        ("content checksum", summary.get("content_checksum")),
    ]
    up_to_date = record["runs"]["rerun_up_to_date"]["wall_seconds"]
    forced = record["runs"]["rerun_forced_cached_generators"]["wall_seconds"]
    lines = [
        f"# Stage one (`hipode augment`) on {record['task']}",
        "",
        f"Measured {record['measured_utc']} on {record['machine']['cpu']} "
        f"({record['machine']['cores']} cores, shared with other work: see the load averages), "
        f"torch {record['machine']['torch']}, profile `{record['profile']}`, "
        f"seed {record['seed']}.",
        f"Recorded with `{record['bench_command']}`.",
        "",
        "| run | command | wall (s) | in-process phases (s) | 1-min load avg (min / mean / max) |",
        "|---|---|---|---|---|",
    ]
    for name in RUNS:
        run, load = record["runs"][name], record["runs"][name]["load_average_1min"]
        lines.append(
            f"| {name} | `{run['command']}` | {run['wall_seconds']:.1f} | "
            f"{phase_text(run['summary']['seconds'])} | "
            f"{load['min']:.2f} / {load['mean']:.2f} / {load['max']:.2f} |"
        )
    lines += [
        "",
        "Summary of the real run (wall time includes process start and imports):",
        "",
        "| quantity | value |",
        "|---|---|",
    ]
    lines += [f"| {name} | {value} |" for name, value in rows]
    checksums = {run["summary"].get("content_checksum") for run in record["runs"].values()}
    if None not in checksums:
        lines += ["", f"Same content checksum in all three runs: {len(checksums) == 1}."]
    lines += [
        "",
        f"Targets: stage one <= 900 s (measured {real['wall_seconds']:.1f} s); "
        f"cached rerun <= 10 s (measured {up_to_date:.1f} s with the artifact up to date, "
        f"{forced:.1f} s regenerating with cached generators).",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="hopper-m-r")
    parser.add_argument("--profile", default="full", choices=("full", "quick"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--results", type=Path, default=RESULTS, help="folder for augment.json and augment.md"
    )
    args = parser.parse_args()
    import torch

    args.results.mkdir(parents=True, exist_ok=True)
    common = [args.task, "--profile", args.profile, "--seed", str(args.seed)]
    logs = args.results.parent / "out"
    logs.mkdir(exist_ok=True)
    runs = {
        "stage_one": run_stage_one([*common, "--force"], logs / "augment-stage-one.log"),
        "rerun_up_to_date": run_stage_one(common, logs / "augment-rerun.log"),
        "rerun_forced_cached_generators": run_stage_one(
            [*common, "--force"], logs / "augment-rerun-forced.log"
        ),
    }
    for run in runs.values():
        run["summary"]["artifact"] = relative(run["summary"]["artifact"])
    record = {
        "task": args.task,
        "profile": args.profile,
        "seed": args.seed,
        "measured_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "bench_command": shlex.join(["python", "bench/augment.py", *sys.argv[1:]]),
        "machine": {
            "cpu": cpu_name(),
            "cores": os.cpu_count(),
            "torch": torch.__version__,
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "PASSIVE"),
        },
        "runs": runs,
    }
    (args.results / "augment.json").write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    (args.results / "augment.md").write_text(markdown(record))
    print(markdown(record))


if __name__ == "__main__":
    main()
