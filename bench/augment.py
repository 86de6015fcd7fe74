"""Stage one's wall time, measured the way a user runs it: `hipode augment TASK` as a process.

Three runs: the real one (--force, so an existing artifact does not short-cut it; generators
are trained unless already cached, which the record says), a plain rerun (the artifact is up
to date and only verified) and a --force rerun (cached generators: load, generate, write).
Machine load is sampled during every run, since the machine may be shared.

    python bench/augment.py [--task hopper-m-r] [--profile full] [--seed 0]

Writes bench/results/augment.json and bench/results/augment.md.

With --threads-study it instead times stage one (quick profile, --force, on a seeded
Hopper-shaped D4RL-format source) with each torch thread count, on the machine as it is
("idle") and with two CPU-burning processes beside it ("busy"), in interleaved rounds, and
records that as its own section of the same two files. The count reaches the run through
OMP_NUM_THREADS, which stage one now honours for generation only: training is fixed at
threads.STAGE_ONE_THREADS["train"] (its weights depend on the count), chosen by the study
recorded in bench/results/augment.md, which ran before that was fixed.

    nice -n 10 python bench/augment.py --threads-study [--rows 30000] [--rounds 2]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from machine import LoadSampler, cpu_name, load_average

from hipode_pipeline.threads import STAGE_ONE_THREADS

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "bench" / "results"
RUNS = ("stage_one", "rerun_up_to_date", "rerun_forced_cached_generators")
PHASES = ("load", "verify", "train", "generate", "write", "total")
THREADS_HEADING = "## Torch threads in stage one"
LOADS = ("idle", "busy")
BURNERS = 2  # CPU-burning processes beside a "busy" run: as many as this machine's cores


def run_stage_one(args: list[str], log: Path, env_extra: dict[str, str] | None = None) -> dict:
    """Run `hipode augment ... --json`; return its summary, wall time and the load during it."""
    command = [str(Path(sys.executable).with_name("hipode")), "augment", *args, "--json"]
    env = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    env.update(env_extra or {})
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
    text = "\n".join(lines)
    if "threads_study" in record:
        text += "\n" + threads_markdown(record["threads_study"])
    return text


# ---- --threads-study -------------------------------------------------------------------------


def write_source(path: Path, rows: int, seed: int) -> None:
    """A seeded Hopper-shaped (11-D state, 3-D action) D4RL-format file, as the tests build."""
    sys.path.insert(0, str(REPO / "tests"))
    from builders import make_d4rl_file

    make_d4rl_file(path, n=rows, obs_dim=11, act_dim=3, seed=seed, episode_length=1000)


def torch_threads_under(env_extra: dict[str, str]) -> int:
    """The thread count torch starts with under these variables (the study's control)."""
    code = "import torch; print(torch.get_num_threads())"
    done = subprocess.run(
        [sys.executable, "-c", code],
        env={**os.environ, **env_extra},
        capture_output=True,
        text=True,
        check=True,
    )
    return int(done.stdout)


def busy_cpu_seconds() -> float:
    """CPU seconds all processes have used since boot (the first line of /proc/stat)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = fields[:8]
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def children_cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def start_burners() -> list[subprocess.Popen]:
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(BURNERS)]
    time.sleep(2.0)  # let them take their share of the cores before the clock starts
    return burners


def stop_burners(burners: list[subprocess.Popen]) -> None:
    for burner in burners:
        burner.kill()
        burner.wait()


def threads_study(args: argparse.Namespace) -> dict:
    """Stage one with each thread count, idle and busy, in interleaved rounds."""
    runs = []
    with tempfile.TemporaryDirectory(prefix="hipode-threads-") as scratch:
        scratch = Path(scratch)
        source = scratch / "hopper-synthetic.hdf5"
        write_source(source, args.rows, args.seed)
        common = [args.task, "--profile", "quick", "--seed", str(args.seed), "--force"]
        common += ["--source", str(source)]
        for threads in args.threads:
            found = torch_threads_under({"OMP_NUM_THREADS": str(threads)})
            if found != threads:
                raise SystemExit(f"OMP_NUM_THREADS={threads} gave torch {found} threads")
        logs = args.results.parent / "out"
        logs.mkdir(exist_ok=True)
        for round_ in range(args.rounds):
            for load in LOADS:
                # alternate the order each round, so a drift in the load hits both counts
                order = args.threads if round_ % 2 == 0 else args.threads[::-1]
                burners = start_burners() if load == "busy" else []
                try:
                    for threads in order:
                        # a fresh root each run: cached generators would skip the training
                        root = scratch / f"root-{len(runs)}"
                        machine, own = busy_cpu_seconds(), children_cpu_seconds()
                        run = run_stage_one(
                            [*common, "--root", str(root), "--out", str(root / "a.hdf5")],
                            logs / f"augment-threads-{threads}-{load}.log",
                            {"OMP_NUM_THREADS": str(threads)},
                        )
                        # the load average lags by a minute; this is what ran beside the run
                        # (burners are reaped after the block, so only the run counts as ours)
                        own = children_cpu_seconds() - own
                        others = busy_cpu_seconds() - machine - own
                        run["cpu_seconds"] = round(own, 2)
                        run["others_cores"] = round(max(others, 0.0) / run["wall_seconds"], 2)
                        run["command"] = f"OMP_NUM_THREADS={threads} {run['command']}"
                        run["command"] = run["command"].replace(str(scratch), "$TMP")
                        shutil.rmtree(root)
                        summary = run.pop("summary")
                        if summary["generators_cached"]:
                            raise SystemExit(f"{run['command']}: generators came from a cache")
                        run.update(
                            threads=threads,
                            load=load,
                            round=round_,
                            seconds=summary["seconds"],
                            n_source=summary["n_source"],
                            kept=summary["kept"],
                        )
                        runs.append(run)
                        print(
                            f"round {round_} {load:4} {threads} thread(s): "
                            f"{run['wall_seconds']:.1f} s ({phase_text(run['seconds'])})",
                            flush=True,
                        )
                finally:
                    stop_burners(burners)
    cells = {}
    for load in LOADS:
        for threads in args.threads:
            cell = [r for r in runs if (r["load"], r["threads"]) == (load, threads)]
            walls = [r["wall_seconds"] for r in cell]
            cells[f"{load}/{threads}"] = {
                "load": load,
                "threads": threads,
                "wall_seconds": walls,
                "median": statistics.median(walls),
                "mean": statistics.fmean(walls),
                "phase_median": {
                    phase: round(statistics.median(r["seconds"][phase] for r in cell), 2)
                    for phase in ("train", "generate")
                },
                "others_cores_median": statistics.median(r["others_cores"] for r in cell),
            }
    low, high = min(args.threads), max(args.threads)
    ratios = {
        load: round(cells[f"{load}/{high}"]["median"] / cells[f"{load}/{low}"]["median"], 3)
        for load in LOADS
    }
    phase_ratios = {
        f"{load}/{phase}": round(
            cells[f"{load}/{high}"]["phase_median"][phase]
            / cells[f"{load}/{low}"]["phase_median"][phase],
            3,
        )
        for load in LOADS
        for phase in ("train", "generate")
    }
    return {
        "measured_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "bench_command": shlex.join(["python", "bench/augment.py", *sys.argv[1:]]),
        "source": f"seeded Hopper-shaped D4RL-format file ({args.rows:,} rows, seed {args.seed})",
        "profile": "quick",
        "threads": list(args.threads),
        "rounds": args.rounds,
        "burners": BURNERS,
        "thread_control": "OMP_NUM_THREADS in the hipode process's environment",
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "PASSIVE"),
        "runs": runs,
        "cells": cells,
        "ratio_median": ratios,
        "phase_ratio_median": phase_ratios,
        "load_average_after": load_average(),
    }


def threads_markdown(study: dict) -> str:
    low, high = min(study["threads"]), max(study["threads"])
    lines = [
        THREADS_HEADING,
        "",
        f"Measured {study['measured_utc']} with `{study['bench_command']}`: stage one "
        f"(profile `{study['profile']}`, --force) on a {study['source']}, torch threads set "
        f"through {study['thread_control']}, OMP_WAIT_POLICY={study['omp_wait_policy']}. "
        f'"idle" is the machine as it was, shared with other work (the column of other processes\' '
        f'CPU says how much ran beside); "busy" adds {study["burners"]} '
        "processes spinning `while True: pass` for the run's length. "
        f"{study['rounds']} interleaved rounds; each round runs idle then busy, the thread "
        "counts in alternating order.",
        "",
        "| load | torch threads | wall per round (s) | median wall (s) | median train / "
        "generate (s) | other processes' CPU per round (cores) | 1-min load avg per round |",
        "|---|---|---|---|---|---|---|",
    ]
    for cell in (study["cells"][f"{load}/{t}"] for load in LOADS for t in study["threads"]):
        runs = [
            r for r in study["runs"] if (r["load"], r["threads"]) == (cell["load"], cell["threads"])
        ]
        loads = ", ".join(
            f"{r['load_average_1min']['min']:.2f}-{r['load_average_1min']['max']:.2f}" for r in runs
        )
        others = ", ".join(f"{r['others_cores']:.2f}" for r in runs)
        walls = ", ".join(f"{w:.1f}" for w in cell["wall_seconds"])
        phases = cell["phase_median"]
        lines.append(
            f"| {cell['load']} | {cell['threads']} | {walls} | {cell['median']:.1f} | "
            f"{phases['train']:.1f} / {phases['generate']:.1f} | {others} | {loads} |"
        )
    ratio = study["phase_ratio_median"]
    lines += [
        "",
        f"Median wall time, {high} threads / {low} thread: "
        + ", ".join(f"{load} {study['ratio_median'][load]:.2f}" for load in LOADS)
        + "; train phase "
        + ", ".join(f"{load} {ratio[f'{load}/train']:.2f}" for load in LOADS)
        + "; generate phase "
        + ", ".join(f"{load} {ratio[f'{load}/generate']:.2f}" for load in LOADS)
        + ".",
        "",
        "Other processes' CPU is the machine's busy CPU time during the run (/proc/stat) less "
        "the run's own, per second of wall time: the load average lags by a minute, so idle "
        "runs right after busy ones still show a high one. Load average (1, 5, 15 min) after "
        f"the study: {study['load_average_after']}.",
        "",
        "In-process phases per run (s):",
        "",
    ]
    for r in study["runs"]:
        lines.append(
            f"- round {r['round']}, {r['load']}, {r['threads']} thread(s): "
            f"{phase_text(r['seconds'])}; {r['cpu_seconds']:.1f} CPU-s"
        )
    lines += [
        "",
        f"Command of each run: `{study['runs'][0]['command']}` (threads varied).",
        "",
        "Stage one's defaults per phase when OMP_NUM_THREADS is unset, chosen from the phase "
        f"ratios above: `hipode_pipeline.threads.STAGE_ONE_THREADS = {STAGE_ONE_THREADS}` "
        "(at most the CPU count).",
        "",
    ]
    return "\n".join(lines)


def record_threads_study(args: argparse.Namespace) -> None:
    """Add (or replace) the study's section; the stage-one record around it is kept as it is."""
    json_path, md_path = args.results / "augment.json", args.results / "augment.md"
    record = json.loads(json_path.read_text()) if json_path.exists() else {}
    record["threads_study"] = threads_study(args)
    json_path.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    before = md_path.read_text().split(THREADS_HEADING)[0] if md_path.exists() else ""
    before = before.rstrip("\n") + "\n\n" if before.strip() else ""
    md_path.write_text(before + threads_markdown(record["threads_study"]))
    print(threads_markdown(record["threads_study"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="hopper-m-r")
    parser.add_argument("--profile", default="full", choices=("full", "quick"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--results", type=Path, default=RESULTS, help="folder for augment.json and augment.md"
    )
    parser.add_argument(
        "--threads-study",
        action="store_true",
        help="time stage one per torch thread count, idle and busy (its own section)",
    )
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="(study) counts")
    parser.add_argument("--rows", type=int, default=30_000, help="(study) source transitions")
    parser.add_argument("--rounds", type=int, default=2, help="(study) rounds per cell")
    args = parser.parse_args()
    args.results.mkdir(parents=True, exist_ok=True)
    if args.threads_study:
        record_threads_study(args)
        return
    import torch

    previous = args.results / "augment.json"
    previous = json.loads(previous.read_text()) if previous.exists() else {}
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
    if "threads_study" in previous:
        record["threads_study"] = previous["threads_study"]  # measured separately: kept
    (args.results / "augment.json").write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    (args.results / "augment.md").write_text(markdown(record))
    print(markdown(record))


if __name__ == "__main__":
    main()
