"""Benchmark: stage one's wall time under the default ("full") profile against the "paper"
profile, side by side.

Runs `hipode augment TASK --profile P --force` for both profiles at once, one process each
(so both see the same machine load), each with its own stage-one seed so that neither reuses
the other's cached generators: every model trains from scratch unless an earlier run of this
bench cached it (the record says so per model). Reports each run's wall time, its per-model
training seconds and steps, and the ratio full / paper, with the load sampled throughout.

    python bench/stage_one_profiles.py [--task hopper-m-r] [--seeds 11 12]

Writes bench/results/stage_one_profiles.json (every run appended) and .md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from machine import LoadSampler, cpu_name

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hipode_pipeline.artifact import read_manifest  # noqa: E402
from hipode_pipeline.files import write_json_atomic, write_text_atomic  # noqa: E402

RESULTS = REPO / "bench" / "results"
PROFILES = ("paper", "full")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="hopper-m-r")
    parser.add_argument("--seeds", type=int, nargs=2, default=[11, 12], help="paper, full")
    args = parser.parse_args()
    hipode = Path(sys.executable).parent / "hipode"
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    with tempfile.TemporaryDirectory() as tmp, LoadSampler() as load:
        procs, started = {}, {}
        for profile, seed in zip(PROFILES, args.seeds, strict=True):
            command = [str(hipode), "augment", args.task, "--profile", profile, "--seed"]
            command += [str(seed), "--force", "--json", "--out", f"{tmp}/{profile}.hdf5"]
            started[profile] = time.perf_counter()
            procs[profile] = subprocess.Popen(
                command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL
            )
        runs = {}
        for profile, proc in procs.items():
            out, _ = proc.communicate()
            wall = time.perf_counter() - started[profile]
            if proc.returncode != 0:
                raise SystemExit(f"hipode augment --profile {profile} exited {proc.returncode}")
            summary = json.loads(out)
            # per-model records: the artifact's manifest
            manifest = read_manifest(Path(tmp) / f"{profile}.hdf5")
            training = (manifest.get("generators") or {}).get("training_report") or {}
            runs[profile] = {
                "seed": args.seeds[PROFILES.index(profile)],
                "wall_seconds": round(wall, 1),
                "phase_seconds": summary.get("seconds"),
                "models": {
                    name: {k: record.get(k) for k in ("steps", "seconds", "cached")}
                    for name, record in training.items()
                },
            }
    record = {
        "command": "python bench/stage_one_profiles.py " + " ".join(sys.argv[1:]),
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
        "machine": cpu_name(),
        "cores": os.cpu_count(),
        "task": args.task,
        "load": load.stats(),
        "runs": runs,
        "ratio_full_to_paper": round(
            runs["full"]["wall_seconds"] / runs["paper"]["wall_seconds"], 2
        ),
    }
    path = RESULTS / "stage_one_profiles.json"
    history = json.loads(path.read_text()) if path.exists() else []
    history.append(record)
    write_json_atomic(path, history)
    lines = [
        "# Stage one: default (full) profile against the paper profile, side by side",
        "",
        "`python bench/stage_one_profiles.py`: both `hipode augment --force` processes start "
        "together (one core each, own stage-one seeds, no shared cached models), so they see "
        "the same load. Sources: the Gymnasium v5 datasets built here.",
        "",
        "| date (UTC) | task | paper wall (s) | full wall (s) | full / paper | per model, "
        "paper → full (steps, s) | load 1-min min / mean / max |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in history:
        paper, full = r["runs"]["paper"], r["runs"]["full"]
        models = "; ".join(
            f"{name} {paper['models'][name]['steps']:,}/{paper['models'][name]['seconds']:.0f} → "
            f"{full['models'][name]['steps']:,}/{full['models'][name]['seconds']:.0f}"
            for name in full["models"]
            if name in paper["models"]
        )
        load_stats = r["load"]
        lines.append(
            f"| {r['date_utc']} | {r['task']} | {paper['wall_seconds']:.0f} "
            f"| {full['wall_seconds']:.0f} | {r['ratio_full_to_paper']:.2f} | {models} "
            f"| {load_stats['min']:.2f} / {load_stats['mean']:.2f} / {load_stats['max']:.2f} |"
        )
    write_text_atomic(RESULTS / "stage_one_profiles.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
