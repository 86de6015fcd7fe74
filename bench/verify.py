"""`hipode verify` on a real artifact: HIPODE's synthetic transitions and plain model rollouts
checked against the MuJoCo simulator, with wall times and simulator throughput.

Two runs of the library call the command makes: the first trains the baseline's behaviour CVAE
unless it is cached already (the record says which), the second loads it, so its time is what a
repeated `hipode verify` costs. The machine may be shared: the load average is recorded.

    python bench/verify.py [--artifact datasets/artifacts/<hopper-m-r's TD3+BC artifact>]
                           [--sample 2000] [--seed 0] [--threads 1]

Writes bench/results/verify.json and bench/results/verify.md; the report and plot themselves
go to bench/out/verify/.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hipode_pipeline.verify import TABLE_COLUMNS, verify_artifact  # noqa: E402

RESULTS = REPO / "bench" / "results"
OUT = REPO / "bench" / "out" / "verify"
# extra tolerances shown in the record, to see how the within-tolerance share moves with it
TOLERANCE_SWEEP = (0.01, 0.02, 0.05, 0.1, 0.2)


def within_at(checks, reward_std_tolerance_scale: float, tolerance: float) -> float:
    """Share within `tolerance` (next state, source stds) and tolerance * reward std (reward)."""
    state_ok = checks.next_state_error <= tolerance
    reward_ok = checks.reward_error <= tolerance * reward_std_tolerance_scale
    return float((state_ok & reward_ok).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--artifact",
        default=str(
            REPO / "datasets/artifacts/hopper-m-r-eta0.5-lam0.2-n10-alpha1-sigma1-seed0.hdf5"
        ),
    )
    parser.add_argument("--root", default=str(REPO / "datasets"))
    parser.add_argument("--sample", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from hipode_pipeline.data.load import load_source

    runs = []
    report = None
    for name in ("first", "repeat"):
        load_before = os.getloadavg()
        started = time.perf_counter()
        report = verify_artifact(
            args.artifact,
            sample=args.sample,
            seed=args.seed,
            root=Path(args.root),
            out_dir=OUT,
            force=True,
            show_progress=True,
        )
        wall = time.perf_counter() - started
        runs.append(
            {
                "run": name,
                "wall_seconds": round(wall, 3),
                "phases": report.seconds,
                "behaviour_cvae_cached": report.baseline_details["behaviour_cvae"]["cached"],
                "loadavg_before": load_before,
                "loadavg_after": os.getloadavg(),
            }
        )
    source, _ = load_source(report.source_id, Path(args.root))
    reward_std = float(source.rewards.astype(np.float64).std())
    sweep = {
        label: {str(t): within_at(checks, reward_std, t) for t in TOLERANCE_SWEEP}
        for label, checks in (("hipode", report.hipode), ("baseline", report.baseline))
    }
    record = {
        "measured_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "device": "cpu" if not torch.cuda.is_available() else torch.cuda.get_device_name(),
            "note": "shared machine: other work ran beside this; see the load averages",
        },
        "artifact": str(Path(args.artifact).relative_to(REPO))
        if Path(args.artifact).is_relative_to(REPO)
        else args.artifact,
        "sample": args.sample,
        "seed": args.seed,
        "report": report.to_dict(per_transition=False),
        "within_tolerance_sweep": sweep,
        "runs": runs,
    }
    for key in ("artifact", "json", "png"):
        value = record["report"].get(key)
        if value and Path(value).is_relative_to(REPO):
            record["report"][key] = str(Path(value).relative_to(REPO))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "verify.json").write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    (RESULTS / "verify.md").write_text(markdown(record, report))
    print((RESULTS / "verify.md").read_text())


def markdown(record: dict, report) -> str:
    def cell(v):
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    lines = [
        "# `hipode verify` on the real hopper-m-r artifact",
        "",
        f"Measured {record['measured_utc']} on {record['machine']['platform']}, "
        f"{record['machine']['cpu_count']} CPU cores, torch threads "
        f"{record['machine']['torch_threads']}, device {record['machine']['device']}. "
        "The machine is shared with other work; load averages (1/5/15 min) are given per run.",
        "",
        f"Artifact `{record['artifact']}`, env {report.env_id}, sample {record['sample']} "
        f"synthetic transitions and as many plain model rollouts, seed {record['seed']}, "
        f"tolerance {report.tolerance}.",
        "",
        "Next-state error: mean over dimensions of |s' - s'_simulator| / source next-state std. "
        "Reward error: |r - r_simulator|, reward units. Within tolerance: next-state error <= "
        "tolerance and reward error <= tolerance * source reward std. Novelty: L2 from s' to the "
        "nearest source state, z-scored. The simulator is put into each synthetic state "
        "(x position restored as 0) and stepped with the synthetic action.",
        "",
        "| " + " | ".join(TABLE_COLUMNS) + " |",
        "|" + "---|" * len(TABLE_COLUMNS),
    ]
    for row in report.rows():
        lines.append("| " + " | ".join(cell(v) for v in row) + " |")
    h, b = record["report"]["hipode"], record["report"]["baseline"]
    lines += [
        "",
        "p90: next-state error HIPODE "
        f"{h['next_state_error_p90']:.4g}, baseline {b['next_state_error_p90']:.4g}; "
        f"reward error HIPODE {h['reward_error_p90']:.4g}, baseline {b['reward_error_p90']:.4g}. "
        f"Rows whose input velocities sit at the observation clip (state not exactly "
        f"restorable): HIPODE {h['clipped_input_rows']}, baseline {b['clipped_input_rows']}.",
        "",
        "Within tolerance at other tolerances (same definition):",
        "",
        "| data | " + " | ".join(record["within_tolerance_sweep"]["hipode"]) + " |",
        "|---|" + "---|" * len(record["within_tolerance_sweep"]["hipode"]),
    ]
    for label, shares in record["within_tolerance_sweep"].items():
        lines.append(
            f"| {label} | " + " | ".join(f"{100 * v:.1f}%" for v in shares.values()) + " |"
        )
    lines += [
        "",
        "Baseline provenance: dynamics ensemble from the artifact's generator cache "
        f"(sha256 matches manifest: {report.baseline_details['dynamics_matches_artifact']}), "
        f"sampling: {report.baseline_details['dynamics_sampling']}; behaviour CVAE "
        f"{report.baseline_details['behaviour_cvae']['steps']} steps, held-out loss "
        f"{report.baseline_details['behaviour_cvae']['initial_heldout_loss']:.4g} -> "
        f"{report.baseline_details['behaviour_cvae']['best_heldout_loss']:.4g}, trained in "
        f"{report.baseline_details['behaviour_cvae']['seconds']:.1f} s (recorded when trained; "
        "later runs load it from the cache).",
        "",
        "Simulator throughput (set state + one env step per row, one env reused): HIPODE "
        f"{h['simulator_rows_per_second']:,.0f} rows/s, baseline "
        f"{b['simulator_rows_per_second']:,.0f} rows/s (last run).",
        "",
        "| run | wall s | phases (s) | behaviour CVAE cached | load before | load after |",
        "|---|---|---|---|---|---|",
    ]
    for run in record["runs"]:
        phases = ", ".join(f"{k} {v}" for k, v in run["phases"].items())
        load_before = "/".join(f"{v:.2f}" for v in run["loadavg_before"])
        load_after = "/".join(f"{v:.2f}" for v in run["loadavg_after"])
        lines.append(
            f"| {run['run']} | {run['wall_seconds']} | {phases} | {run['behaviour_cvae_cached']} "
            f"| {load_before} | {load_after} |"
        )
    lines += [
        "",
        f"Plot: `{record['report']['png']}` (novelty vs next-state error against the simulator; "
        "not committed, rerun the bench to draw it).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
