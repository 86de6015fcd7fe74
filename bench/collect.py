"""Benchmark of `hipode collect`: wall time, size and behaviour score of the locomotion datasets.

Runs the real collection (profile full) into the dataset root, env by env in the order that
shares policies (medium-replay trains the medium policy, medium and medium-expert reuse it,
expert trains on), and writes bench/results/collect.json and bench/results/collect.md: per
dataset N beside D4RL's, the behaviour policies' normalized scores against their bands, wall
time and trainer. Off-band datasets are recorded as such (the run goes on). The machine may be
shared: the load average before and after each dataset is recorded beside the timings.

    python bench/collect.py --all [--fresh] [--seed 0] [--root DIR] [--workers 2]
    python bench/collect.py --tasks halfcheetah-m-r hopper-m-r

With --workers 2 the envs' chains run side by side in two processes (one torch thread each; the
longest chain, HalfCheetah's SAC, first), which is how the 2-core budget is met; the total wall
time is then the whole run's, not the sum of the rows.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import multiprocessing
import os
import shutil
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import torch
from machine import cpu_name

from hipode_pipeline.data.collect import collect, load_recipe, work_dir
from hipode_pipeline.data.minari_write import dataset_dir
from hipode_pipeline.paths import use_datasets_root
from hipode_pipeline.tasks import get_task

RESULTS = Path(__file__).resolve().parent / "results"
README = Path(__file__).resolve().parent.parent / "README.md"
TABLE_MARKERS = ("<!-- collect-table -->", "<!-- /collect-table -->")
ENVS = ("hopper", "halfcheetah", "walker2d")
# chains by length: HalfCheetah's SAC (medium and expert) takes longest
CHAIN_ORDER = ("halfcheetah", "hopper", "walker2d")
KINDS = ("m-r", "m", "r", "e", "m-e")
TASKS = tuple(f"{env}-{kind}" for env in ENVS for kind in KINDS)
# D4RL's dataset sizes (v2; medium-replay's v0 sizes were about half)
D4RL_SIZE = {
    "random": 1_000_000,
    "medium": 1_000_000,
    "expert": 1_000_000,
    "medium-expert": 2_000_000,
    "medium-replay": {"hopper": 402_000, "halfcheetah": 202_000, "walker2d": 302_000},
}
# D4RL's data scores (normalized average episode return of the v2 datasets, as commonly quoted;
# not re-measured here: D4RL's files cannot be downloaded on these machines)
D4RL_SCORE = {
    ("hopper", "random"): 1.2,
    ("hopper", "medium"): 44.3,
    ("hopper", "medium-replay"): 14.9,
    ("hopper", "expert"): 108.5,
    ("hopper", "medium-expert"): 76.4,
    ("halfcheetah", "random"): -0.3,
    ("halfcheetah", "medium"): 40.7,
    ("halfcheetah", "medium-replay"): 27.2,
    ("halfcheetah", "expert"): 88.1,
    ("halfcheetah", "medium-expert"): 64.4,
    ("walker2d", "random"): 0.0,
    ("walker2d", "medium"): 62.1,
    ("walker2d", "medium-replay"): 14.8,
    ("walker2d", "expert"): 106.7,
    ("walker2d", "medium-expert"): 84.4,
}


TRAINER_CHOICE = """## Trainer choice (HalfCheetah)

PPO (64-wide, the Hopper recipe) stayed at 15.7 normalized after 2M env steps (942 s), far below
the medium band [29, 53], so HalfCheetah uses SAC, D4RL's trainer. A first recipe, 128-wide nets
at 0.5 updates per env step (`bench/results/behaviour_trainers.json`, `.png`, from
`python bench/behaviour_trainers.py`), reached the medium band at 90-164k steps but its expert
checks (20 episodes, stochastic) levelled off: 46.4 normalized at 264k env steps, 56.7 at 524k,
60.7 at 724k and 63.9 at 984k, about 12 points under the expert band [76, 100].

The recipe now is D4RL's own SAC, 256-wide at one update per env step, with the hidden layers'
matmuls in bfloat16 autocast (weights, Q outputs, log-densities and losses in float32): about
twice float32's updates per second here (`bench/results/sac_updates.md`). Its best expert
check rose faster at every step count: 53.6 normalized at 234k env steps, 62.4 at 434k, 69.6
at 584k, 74.6 at 734k, 78.0 at 834k, 79.8 at 934k and 81.0 at 984k (checks every 50k; the
best-so-far read from the checkpoints; `expert_checks` in the dataset metadata holds every
check for runs from now on). The 984k snapshot is the expert: 81.2 on its independent
evaluation, inside [76, 100]. Its medium policy came at 84k steps (38.0 normalized, in band),
so halfcheetah-m-r is that whole 84k history (D4RL v2: 202k; v0: about 101k).

The cost is time: about 160 env steps (and updates) a second on one core beside another job,
so the expert search to 1M steps took 107 minutes of training here: halfcheetah-m-r's 20
minute budget is met (9 min), the 60 minute budget for all 15 datasets is not (the sum of the
rows above). Hopper and Walker2d keep PPO: it reaches their medium and expert bands in minutes
here."""


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def d4rl_size(env: str, kind: str) -> int:
    size = D4RL_SIZE[kind]
    return size[env] if isinstance(size, dict) else size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--all", action="store_true", help="all 15 locomotion datasets")
    which.add_argument("--tasks", nargs="+", choices=TASKS, default=["hopper-m-r", "hopper-m"])
    parser.add_argument(
        "--fresh",
        action="store_true",
        help="delete the work folders of the envs and the datasets asked for first (retrain)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--workers", type=int, default=1, help="processes running env chains side by side"
    )
    parser.add_argument(
        "--root", type=Path, default=None, help="dataset root (default: ./datasets)"
    )
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="rewrite collect.md and the README table from collect.json; collect nothing",
    )
    args = parser.parse_args()
    if args.report_only:
        report = json.loads((RESULTS / "collect.json").read_text())
        (RESULTS / "collect.md").write_text(markdown(report))
        update_readme(report)
        return
    names = list(TASKS) if args.all else sorted(args.tasks, key=TASKS.index)
    torch.set_num_threads(1)
    root = use_datasets_root(args.root)
    if args.fresh:
        for env in {get_task(n).env for n in names}:
            shutil.rmtree(work_dir(root, env, args.seed), ignore_errors=True)
        for name in names:
            shutil.rmtree(dataset_dir(root, get_task(name).local_dataset_id), ignore_errors=True)
    command = " ".join(["python", "bench/collect.py", *sys.argv[1:]])
    # one chain per env, in the order that shares policies; the longest chain starts first
    chains = [[n for n in names if get_task(n).env == env] for env in CHAIN_ORDER]
    chains = [chain for chain in chains if chain]
    started = time.perf_counter()
    runs: list[dict] = []
    if args.workers <= 1:
        for chain in chains:
            runs += collect_chain(chain, root, args.seed, command)
            write_report(runs, args, command, names, time.perf_counter() - started)
        return
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(args.workers, mp_context=context) as pool:
        futures = [pool.submit(collect_chain, chain, root, args.seed, command) for chain in chains]
        # each finished chain is recorded at once: a later failure loses nothing before it
        for future in concurrent.futures.as_completed(futures):
            runs += future.result()
            write_report(runs, args, command, names, time.perf_counter() - started)


def write_report(
    runs: list[dict], args: argparse.Namespace, command: str, names: list[str], wall: float
) -> None:
    """collect.json, collect.md and the README table: these runs, and the recorded runs of
    tasks not asked for this time (a partial rerun keeps them)."""
    runs = list(runs)
    previous = RESULTS / "collect.json"
    if previous.exists():
        kept = json.loads(previous.read_text()).get("runs", [])
        done = {r["task"] for r in runs}
        runs += [r for r in kept if r["task"] not in done and "kind" in r]
    runs.sort(key=lambda r: TASKS.index(r["task"]))
    report = {
        "machine": {
            "cpu": cpu_name(),
            "cores": os.cpu_count(),
            "torch_threads": 1,
            "note": "shared machine: other jobs may run beside this one; see the load averages",
        },
        "seed": args.seed,
        "last_command": {
            "command": command,
            "tasks": names,
            "workers": args.workers,
            "wall_seconds": round(wall, 1),
        },
        "runs": runs,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "collect.json").write_text(json.dumps(report, indent=2) + "\n")
    (RESULTS / "collect.md").write_text(markdown(report))
    update_readme(report)


def collect_chain(names: list[str], root: Path, seed: int, command: str) -> list[dict]:
    """Collect `names` (one env's datasets, in order) and return their rows."""
    torch.set_num_threads(1)
    runs = []
    for name in names:
        task = get_task(name)
        load_before, started = _load(), time.perf_counter()
        result = collect(
            task,
            root=root,
            seed=seed,
            profile="full",
            show_progress=sys.stderr.isatty(),
            allow_off_band=True,  # recorded as off-band below; the other datasets still run
        )
        wall = time.perf_counter() - started
        meta = json.loads((Path(result.path) / "data" / "metadata.json").read_text())["hipode"]
        runs.append(
            {
                "task": name,
                "kind": task.kind,
                "env": task.env,
                "command": command,
                "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
                "dataset_id": result.dataset_ids[0],
                "trainer": load_recipe(task.env).trainer if meta["behaviour_policy"] else "-",
                "wall_seconds": round(wall, 1),
                "reused_existing_dataset": result.reused,
                "phase_seconds": result.phase_seconds,
                "env_steps_per_second": result.steps_per_second,
                "transitions": result.transitions,
                "d4rl_transitions": d4rl_size(task.env, task.kind),
                "episodes": result.episodes,
                "behaviour_policy": {
                    k: {f: v[f] for f in ("mean", "std", "normalized", "episodes", "stochastic")}
                    for k, v in meta["behaviour_policy"].items()
                },
                "band": meta.get("band"),
                "training": meta.get("training", {}),
                "medium_replay_subsampled": meta.get("medium_replay_subsampled"),
                "dataset_episode_return": meta["dataset_episode_return"],
                "d4rl_dataset_score": D4RL_SCORE[(task.env, task.kind)],
                "load_average_before": load_before,
                "load_average_after": _load(),
            }
        )
        print(json.dumps(runs[-1], indent=2), flush=True)
    return runs


def update_readme(report: dict) -> None:
    """The README's table of local datasets beside D4RL's, between its markers."""
    lines = [
        TABLE_MARKERS[0],
        "| dataset | trainer | N here | N D4RL v2 | behaviour policy here, normalized (band) "
        "| dataset return here | D4RL dataset return | in band |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run in report["runs"]:
        verdict = {True: "yes", False: "**no**", None: "-"}[(run["band"] or {}).get("in_band")]
        lines.append(
            f"| {run['task']} | {run['trainer']} | {run['transitions']:,} "
            f"| {run['d4rl_transitions']:,} | {_scores(run)} | {_dataset_score(run)} "
            f"| {run['d4rl_dataset_score']} | {verdict} |"
        )
    lines.append(TABLE_MARKERS[1])
    text = README.read_text()
    start, end = text.index(TABLE_MARKERS[0]), text.index(TABLE_MARKERS[1])
    README.write_text(text[:start] + "\n".join(lines) + text[end + len(TABLE_MARKERS[1]) :])


def _dataset_score(run: dict) -> str:
    value = run["dataset_episode_return"].get("normalized")
    return "-" if value is None else f"{value:.1f}"


def _scores(run: dict) -> str:
    parts = []
    for name, policy in (run["band"] or {}).get("policies", {}).items():
        band = policy["band"]
        inside = {True: "in", False: "**off**", None: "no band"}[policy["in_band"]]
        band_text = f"[{band[0]:g}, {band[1]:g}]" if band else "-"
        parts.append(f"{name} {policy['measured']:.1f} {band_text} {inside}")
    return "; ".join(parts) or "uniform random"


def markdown(report: dict) -> str:
    machine = report["machine"]
    lines = [
        "# `hipode collect` benchmark",
        "",
        f"Profile full, seed {report['seed']}; {machine['cpu']}, {machine['cores']} cores, "
        "1 torch thread; load averages (1/5/15 min) before and after each dataset. These are "
        "Gymnasium v5 datasets built here, scored with D4RL's reference returns; D4RL's own "
        "sizes and behaviour scores (v2) are beside them. Behaviour: each policy's measured "
        "normalized return (fresh evaluation episodes, stochastic actions as in the rollouts) "
        "against its band (D4RL's average ± 12). Wall: this dataset alone, with the policies "
        "trained for earlier rows reused (0 s training when reused).",
        "",
        "| task | trainer | N | D4RL N | behaviour (normalized, band) | dataset return "
        "(normalized) | D4RL dataset | wall (s) | train (s) | date (UTC) | load before → after |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    total = 0.0
    for run in report["runs"]:
        total += run["wall_seconds"]
        lines.append(
            f"| {run['task']} | {run['trainer']} | {run['transitions']:,} "
            f"| {run['d4rl_transitions']:,} | {_scores(run)} "
            f"| {_dataset_score(run)} "
            f"| {run['d4rl_dataset_score']} | {run['wall_seconds']} "
            f"| {run['phase_seconds'].get('train', 0):.0f} | {run['date_utc']} "
            f"| {run['load_average_before']} → {run['load_average_after']} |"
        )
    lines += ["", f"Sum of the rows' wall times: {total / 60:.1f} min."]
    last = report.get("last_command")
    if last:
        lines.append(
            f"Last command: `{last['command']}` ({len(last['tasks'])} datasets, "
            f"{last['workers']} worker process(es) running env chains side by side): "
            f"{last['wall_seconds'] / 60:.1f} min wall in total."
        )
    lines.append("")
    for run in report["runs"]:
        medium = (run.get("training") or {}).get("medium")
        if run["kind"] != "medium-replay" or not medium:
            continue
        check = medium.get("check") or {}
        sub = run.get("medium_replay_subsampled")
        lines.append(
            f"- {run['task']}: medium policy = {run['trainer'].upper()} snapshot after "
            f"{medium['train_steps']:,} env steps ({medium['train_seconds']:.0f} s of training; "
            f"acceptance check {check.get('normalized', float('nan')):.1f} normalized, target "
            f"reached: {medium['target_reached']})"
            + (
                f"; history of {sub['history_transitions']:,} transitions subsampled in order "
                f"to {sub['kept_transitions']:,}"
                if sub
                else "; the whole history is the dataset"
            )
            + "."
        )
    return "\n".join(lines + ["", TRAINER_CHOICE]) + "\n"


if __name__ == "__main__":
    main()
