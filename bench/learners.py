"""Stage-two learners: updates/s of our TD3+BC against d3rlpy 2.8.1's TD3PlusBC on the same
data, batch size and thread count, and (optionally) TD3+BC at η = 0 on the locally collected
hopper-medium dataset at a stated, scaled budget against the behaviour policy's score.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/learners.py \
        --d3rlpy-python .venv-d3rlpy/bin/python \
        [--quality-steps 30000 --quality-precision fp32 bf16]

d3rlpy pins gymnasium 1.0.0, so it lives in its own virtual environment and is measured in a
subprocess of that interpreter (which imports this project too, `pip install --no-deps -e .`).
Each variant runs in rounds that alternate with the others, so a load change on this shared
machine hits all of them; the report gives the median round and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from machine import load_average

RESULTS = Path(__file__).resolve().parent / "results"


def bench_data(dataset: str | None, n: int, seed: int):
    """The local dataset if it loads, else seeded Hopper-shaped (11-D state, 3-D action) rows."""
    from hipode_pipeline.data.transitions import Transitions

    if dataset:
        try:
            from hipode_pipeline.data.load import load_source

            transitions, info = load_source(dataset)
            return transitions, info, f"{info.id} ({len(transitions)} transitions)"
        except Exception as error:  # the bench still measures speed without it
            print(f"dataset {dataset} not usable ({error}); using random rows", file=sys.stderr)
    rng = np.random.default_rng(seed)
    t = Transitions(
        rng.normal(size=(n, 11)).astype(np.float32),
        rng.uniform(-1, 1, (n, 3)).astype(np.float32),
        rng.normal(size=n).astype(np.float32),
        rng.normal(size=(n, 11)).astype(np.float32),
        rng.random(n) < 0.001,
        np.zeros(n, bool),
    )
    return t, None, f"random Hopper-shaped rows ({n})"


def our_learners(transitions, variants: dict[str, dict], batch: int) -> dict:
    """One warmed-up TD3+BC (and its sampler) per variant."""
    from hipode_pipeline.learners.td3_bc import TD3BC, TD3BCConfig
    from hipode_pipeline.replay import MixedReplay

    runs = {}
    for name, settings in variants.items():
        config = TD3BCConfig(**settings)
        learner = TD3BC(transitions.obs_dim, transitions.act_dim, config, device="cpu", seed=0)
        learner.fit_statistics(transitions)
        replay = MixedReplay(transitions, device="cpu", seed=0)
        for _ in range(30):  # warm-up (and, with compile, the compilation)
            learner.update(replay.sample(batch))
        runs[name] = (learner, replay)
    return runs


def time_ours(learner, replay, updates: int, batch: int) -> float:
    """Updates/s, sampling included."""
    start = time.perf_counter()
    for _ in range(updates):
        learner.update(replay.sample(batch))
    return updates / (time.perf_counter() - start)


def d3rlpy_worker(data_path: str, threads: int, updates: int, batch: int) -> None:
    """Runs in d3rlpy's interpreter: builds TD3PlusBC on the data, then for every line read on
    stdin runs `updates` updates and answers one JSON line (updates/s with and without sampling)."""
    import d3rlpy

    from hipode_pipeline.data.transitions import Transitions
    from hipode_pipeline.learners.external import build_d3rlpy_buffer

    torch.set_num_threads(threads)
    arrays = np.load(data_path)
    transitions = Transitions(**{k: arrays[k] for k in arrays.files})
    d3rlpy.seed(0)
    scaler = d3rlpy.preprocessing.StandardObservationScaler(
        mean=transitions.observations.mean(0), std=transitions.observations.std(0)
    )
    config = d3rlpy.algos.TD3PlusBCConfig(batch_size=batch, observation_scaler=scaler)
    algo = config.create(device="cpu:0")
    real, buffer = build_d3rlpy_buffer(transitions, None, 0.0)
    algo.build_with_dataset(real)
    for _ in range(10):
        algo.update(buffer.sample_transition_batch(batch))
    print(json.dumps({"ready": d3rlpy.__version__}), flush=True)
    for _ in sys.stdin:
        sample_seconds = 0.0
        start = time.perf_counter()
        for _ in range(updates):
            t0 = time.perf_counter()
            minibatch = buffer.sample_transition_batch(batch)
            sample_seconds += time.perf_counter() - t0
            algo.update(minibatch)
        total = time.perf_counter() - start
        answer = {
            "with_sampling": updates / total,
            "update_only": updates / (total - sample_seconds),
        }
        print(json.dumps(answer), flush=True)


def start_d3rlpy(python: str, data_path: Path, threads: int, updates: int, batch: int):
    """The d3rlpy worker process, ready to take rounds; None (and why, on stderr) if it fails."""
    command = [python, __file__, "--worker", str(data_path), "--threads", str(threads)]
    command += ["--updates", str(updates), "--batch-size", str(batch)]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    try:
        worker = subprocess.Popen(
            command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
        )
    except OSError as error:
        print(f"d3rlpy worker did not start: {error}", file=sys.stderr)
        return None, None
    for line in worker.stdout:
        if line.startswith("{"):
            return worker, json.loads(line)["ready"]
    print("d3rlpy worker exited before it was ready (see its stderr above)", file=sys.stderr)
    return None, None


def d3rlpy_round(worker) -> dict:
    worker.stdin.write("go\n")
    worker.stdin.flush()
    return json.loads(worker.stdout.readline())


def quality_run(
    dataset: str, steps: int, bf16: bool, seed: int, episodes: int, threads: int
) -> dict:
    """TD3+BC at η = 0 on `dataset` for `steps` updates; the last evaluation's normalized score."""
    from hipode_pipeline.data.load import load_source
    from hipode_pipeline.evaluate import evaluate_policy
    from hipode_pipeline.learners.td3_bc import TD3BC, TD3BCConfig
    from hipode_pipeline.replay import MixedReplay

    torch.set_num_threads(threads)
    real, info = load_source(dataset)
    learner = TD3BC(real.obs_dim, real.act_dim, TD3BCConfig(bf16=bf16), device="cpu", seed=seed)
    learner.fit_statistics(real)
    replay = MixedReplay(real, device="cpu", seed=seed)
    start = time.perf_counter()
    curve = []
    for step in range(1, steps + 1):
        learner.update(replay.sample(256))
        if step % max(steps // 5, 1) == 0 or step == steps:
            r = evaluate_policy(
                learner.act,
                info.env_id,
                episodes=episodes,
                seed=seed,
                ref_min_score=info.ref_min_score,
                ref_max_score=info.ref_max_score,
            )
            curve.append(
                {
                    "step": step,
                    "score_mean": r.score_mean,
                    "score_std": r.score_std,
                    "return_mean": r.return_mean,
                }
            )
            print(
                f"  bf16={bf16} step {step}: score {r.score_mean:.1f} ± {r.score_std:.1f}",
                file=sys.stderr,
                flush=True,
            )
    episode_returns = real.episode_returns()
    # the collector records the behaviour policy's own evaluation under metadata["hipode"]
    recorded = (info.metadata.get("hipode") or {}).get("behaviour_policy") or {}
    behaviour = next(iter(recorded.values()), None) if isinstance(recorded, dict) else None
    ref = (info.ref_min_score, info.ref_max_score)
    data_score = 100 * (episode_returns.mean() - ref[0]) / (ref[1] - ref[0])
    return {
        "dataset": info.id,
        "dataset_sha256": info.sha256,
        "steps": steps,
        "bf16": bf16,
        "seed": seed,
        "episodes": episodes,
        "seconds": time.perf_counter() - start,
        "curve": curve,
        "last": curve[-1],
        "data_episode_return_mean": float(episode_returns.mean()),
        "data_score": float(data_score),
        "behaviour_policy": None
        if not isinstance(behaviour, dict)
        else {k: behaviour.get(k) for k in ("mean", "std", "normalized", "episodes")},
    }


def median(values):
    return statistics.median(values) if values else None


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--dataset", default="local/hopper/medium-v0", help="data (speed falls back to random rows)"
    )
    parser.add_argument(
        "--d3rlpy-python", default=".venv-d3rlpy/bin/python", help="interpreter with d3rlpy 2.8.1"
    )
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--updates", type=int, default=200, help="updates per round")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--compile", action="store_true", help="also measure torch.compile")
    parser.add_argument("--no-speed", action="store_true", help="skip the speed section")
    parser.add_argument("--quality-steps", type=int, default=0, help="TD3+BC eta=0 run (0: skip)")
    parser.add_argument(
        "--quality-precision", nargs="+", default=["fp32"], choices=["fp32", "bf16"]
    )
    parser.add_argument("--quality-threads", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        d3rlpy_worker(args.worker, args.threads[0], args.updates, args.batch_size)
        return

    cpu = platform.processor() or platform.machine()
    report = load_previous()
    report["machine"] = f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__}"
    section_base = {
        "command": " ".join(["python", *sys.argv]),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "unset"),
        "load_before": load_average(),
    }
    if not args.no_speed:
        report["speed"] = {**section_base, **speed_section(args)}
        report["speed"]["load_after"] = load_average()
    if args.quality_steps:
        # each (steps, precision) run is kept beside earlier ones, with its own command and load
        sections = report.setdefault("quality_runs", {})
        for precision in args.quality_precision:
            before = load_average()
            run = quality_run(
                args.dataset,
                args.quality_steps,
                precision == "bf16",
                0,
                args.episodes,
                args.quality_threads,
            )
            sections[f"{run['dataset']} {run['steps']} {precision} seed{run['seed']}"] = {
                **section_base,
                "threads": args.quality_threads,
                "load_before": before,
                "load_after": load_average(),
                "run": run,
            }
    write_report(report)


def speed_section(args) -> dict:
    transitions, _, data_text = bench_data(args.dataset, 100_000, seed=0)
    variants = {"ours fp32": {"bf16": False}, "ours bf16 autocast": {"bf16": True}}
    if args.compile:
        variants["ours fp32 compiled"] = {"bf16": False, "compile": True}
    section: dict = {"data": data_text, "batch_size": args.batch_size, "threads": {}}
    with tempfile.TemporaryDirectory() as folder:
        data_path = Path(folder) / "data.npz"
        np.savez(data_path, **transitions.arrays())
        for threads in args.threads:
            torch.set_num_threads(threads)
            print(f"threads={threads}: warming up ...", file=sys.stderr, flush=True)
            ours = our_learners(transitions, variants, args.batch_size)
            d3_updates = max(args.updates // 4, 10)  # d3rlpy is slower: keep its rounds short
            worker, version = start_d3rlpy(
                args.d3rlpy_python, data_path, threads, d3_updates, args.batch_size
            )
            rates: dict[str, list[float]] = {name: [] for name in variants}
            theirs = f"d3rlpy {version} TD3PlusBC"
            for round_index in range(args.rounds):
                print(f"threads={threads}: round {round_index + 1}", file=sys.stderr, flush=True)
                for name, (learner, replay) in ours.items():
                    rates[name].append(time_ours(learner, replay, args.updates, args.batch_size))
                if worker is not None:
                    answer = d3rlpy_round(worker)
                    rates.setdefault(f"{theirs} (sampling included)", []).append(
                        answer["with_sampling"]
                    )
                    rates.setdefault(f"{theirs} (update only)", []).append(answer["update_only"])
            if worker is not None:
                worker.stdin.close()
                worker.wait()
            section["threads"][str(threads)] = {
                name: {"rounds": values, "median": median(values)} for name, values in rates.items()
            }
    return section


def load_previous() -> dict:
    path = RESULTS / "learners.json"
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def write_report(report: dict) -> None:
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "learners.json").write_text(json.dumps(report, indent=2) + "\n")
    lines = [
        "# Stage-two learners: speed and a scaled-budget score",
        "",
        f"Machine: {report['machine']}, shared with other jobs while measured: "
        "the load averages below say how busy it was (2 cores, so a load above 2 means waiting).",
        "",
        "TD3BCConfig.bf16 defaults to bf16 autocast where bf16 matmuls are native (AVX512-BF16 "
        "or AMX CPUs, CUDA) because of these runs: the speed tables, and the fp32 and bf16 runs "
        "on the same data below, which score alike.",
        "",
    ]
    speed = report.get("speed")
    if speed:
        lines += [
            "## Updates/s: our TD3+BC and d3rlpy's TD3PlusBC, same data, batch and threads",
            "",
            f"Command: `{speed['command']}` (OMP_WAIT_POLICY={speed['omp_wait_policy']}); "
            f"load average (1, 5, 15 min) {speed['load_before']} before, "
            f"{speed['load_after']} after.",
            f"Data: {speed['data']}; batch size {speed['batch_size']}. Each variant runs in rounds "
            "alternating with the others (d3rlpy in its own interpreter between ours); the table "
            "gives the median round, sampling included unless marked.",
            "",
        ]
        for threads, entry in speed["threads"].items():
            lines += [
                f"### {threads} torch thread(s)",
                "",
                "| learner | updates/s (median) | rounds |",
                "| --- | --- | --- |",
            ]
            for name, values in entry.items():
                rounds = ", ".join(f"{r:.1f}" for r in values["rounds"])
                lines.append(f"| {name} | {values['median']:.1f} | {rounds} |")
            lines.append("")
            for base_name in [n for n in entry if n.startswith("d3rlpy")]:
                for name in [n for n in entry if n.startswith("ours")]:
                    ratio = entry[name]["median"] / entry[base_name]["median"]
                    lines.append(f"- {name} / {base_name}: {ratio:.2f}×")
            lines.append("")
    quality = report.get("quality_runs") or {}
    if quality:
        lines += ["## TD3+BC at η = 0 on the locally collected dataset, scaled budget", ""]
    for section in quality.values():
        run = section["run"]
        last, behaviour = run["last"], run["behaviour_policy"] or {}
        lines += [
            f"### {run['dataset']} (sha256 {run.get('dataset_sha256', 'not recorded')[:12]}), "
            f"{run['steps']} updates "
            f"({'bf16 autocast' if run['bf16'] else 'fp32'}, seed {run['seed']})",
            "",
            f"Command: `{section['command']}` ({section['threads']} torch thread); load average "
            f"{section['load_before']} before, {section['load_after']} after."
            + (f" Note: {section['note']}." if section.get("note") else ""),
            "",
            f"Last evaluation ({run['episodes']} episodes, fixed seeds): normalized score "
            f"{last['score_mean']:.1f} ± {last['score_std']:.1f} "
            f"(return {last['return_mean']:.0f}). "
            "The data's own episodes (every segment, cut ones too) average "
            f"{run['data_score']:.1f} "
            f"(return {run['data_episode_return_mean']:.0f}); the behaviour policy, as the "
            f"collector evaluated it: {behaviour.get('normalized', float('nan')):.1f} "
            f"(return {behaviour.get('mean', float('nan')):.0f} over "
            f"{behaviour.get('episodes')} episodes). Wall time {run['seconds']:.0f} s, "
            "evaluations included.",
            "",
            "| step | normalized score | return |",
            "| --- | --- | --- |",
            *[
                f"| {c['step']} | {c['score_mean']:.1f} ± {c['score_std']:.1f} "
                f"| {c['return_mean']:.0f} |"
                for c in run["curve"]
            ],
            "",
        ]
    (RESULTS / "learners.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
