"""Stage-two learners: seed-updates/s of our TD3+BC, IQL and CQL (one seed, and K seeds
stacked in one process, fp32 and bf16) beside d3rlpy 2.8.1's TD3PlusBC, IQL and CQL on the same
data, batch size and thread count, against the matmul roofs measured in the same run; and
(optionally) TD3+BC at η = 0 on a locally collected dataset at a stated budget.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/learners.py \
        --d3rlpy-python .venv-d3rlpy/bin/python [--seeds 5 --rounds 3] \
        [--no-speed --quality-steps 30000 --quality-precision fp32 bf16]

d3rlpy pins gymnasium 1.0.0, so it lives in its own virtual environment and is measured in a
subprocess of that interpreter (which imports this project too, `pip install --no-deps -e .`).
Each variant runs in rounds that alternate with the others, so a load change on this shared
machine hits all of them; the report gives the median round, CPU-time and wall-time rates,
and the load average.
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


LEARNER_NAMES = ("td3bc", "iql", "cql")
# updates per round (per stacked group), sized so every variant's round lasts about a second
ROUND_UPDATES = {"td3bc": 100, "iql": 60, "cql": 4}
D3RLPY_ALGOS = {"td3bc": "TD3PlusBC", "iql": "IQL", "cql": "CQL"}


def our_learner(name: str, transitions, seeds: int, bf16: bool, batch: int):
    """One warmed-up stacked learner of `seeds` seeds and its sampler."""
    from hipode_pipeline.learners import learner_class
    from hipode_pipeline.replay import MixedReplay

    cls = learner_class(name)
    config = cls.config_class(bf16=bf16)
    ids = list(range(seeds))
    learner = cls(transitions.obs_dim, transitions.act_dim, config, device="cpu", seed=ids)
    learner.fit_statistics(transitions)
    replay = MixedReplay(transitions, device="cpu", seed=ids)
    for _ in range(3):
        learner.update(replay.sample(batch))
    return learner, replay


def update_flops(learner, replay, batch: int, updates: int = 2) -> float:
    """Matmul FLOPs of one update of one seed (forward and backward), counted by torch over
    `updates` updates (TD3+BC's actor moves every second one)."""
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    with counter:
        for _ in range(updates):
            learner.update(replay.sample(batch))
    return counter.get_total_flops() / updates / learner.n_seeds


def time_ours(learner, replay, updates: int, batch: int) -> dict[str, float]:
    """Seed-updates per CPU second and per wall second (sampling included)."""
    cpu, wall = time.process_time(), time.perf_counter()
    for _ in range(updates):
        learner.update(replay.sample(batch))
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    seed_updates = updates * learner.n_seeds
    return {"cpu": seed_updates / cpu, "wall": seed_updates / wall}


def matmul_roofs(threads: int) -> dict[str, float]:
    """GFLOP/s of a 256-wide matmul (1280 x 256 @ 256 x 256) in fp32 and bf16, as measured now."""
    torch.set_num_threads(threads)
    roofs = {}
    for name, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
        a, b = torch.randn(1280, 256, dtype=dtype), torch.randn(256, 256, dtype=dtype)
        for _ in range(20):
            a @ b
        start, n = time.perf_counter(), 400
        for _ in range(n):
            a @ b
        roofs[name] = 2 * 1280 * 256 * 256 * n / (time.perf_counter() - start) / 1e9
    return roofs


def d3rlpy_worker(data_path: str, algo_name: str, threads: int, updates: int, batch: int):
    """Runs in d3rlpy's interpreter: builds `algo_name` on the data (CORL's network sizes: CQL
    with 3 hidden layers of 256), then for every line read on stdin runs `updates` updates and
    answers one JSON line (updates per CPU and per wall second, with and without sampling)."""
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
    extra = {}
    if algo_name == "CQL":
        encoder = d3rlpy.models.encoders.VectorEncoderFactory([256, 256, 256])
        extra = {"actor_encoder_factory": encoder, "critic_encoder_factory": encoder}
    config = getattr(d3rlpy.algos, f"{algo_name}Config")(
        batch_size=batch, observation_scaler=scaler, **extra
    )
    algo = config.create(device="cpu:0")
    real, buffer = build_d3rlpy_buffer(transitions, None, 0.0)
    algo.build_with_dataset(real)
    for _ in range(3):
        algo.update(buffer.sample_transition_batch(batch))
    print(json.dumps({"ready": d3rlpy.__version__}), flush=True)
    for _ in sys.stdin:
        sample_cpu = sample_wall = 0.0
        cpu, wall = time.process_time(), time.perf_counter()
        for _ in range(updates):
            c0, w0 = time.process_time(), time.perf_counter()
            minibatch = buffer.sample_transition_batch(batch)
            sample_cpu += time.process_time() - c0
            sample_wall += time.perf_counter() - w0
            algo.update(minibatch)
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        answer = {
            "update_only": {
                "cpu": updates / (cpu - sample_cpu),
                "wall": updates / (wall - sample_wall),
            },
            "with_sampling": {"cpu": updates / cpu, "wall": updates / wall},
        }
        print(json.dumps(answer), flush=True)


def start_d3rlpy(python: str, data_path: Path, algo: str, threads: int, updates: int, batch: int):
    """The d3rlpy worker process, ready to take rounds; None (and why, on stderr) if it fails."""
    command = [python, __file__, "--worker", str(data_path), "--worker-algo", algo]
    command += ["--threads", str(threads), "--updates", str(updates), "--batch-size", str(batch)]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": str(threads)}
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
    parser.add_argument("--threads", type=int, nargs="+", default=[1])
    parser.add_argument("--updates", type=int, default=200, help=argparse.SUPPRESS)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--seeds", type=int, default=5, help="K seeds stacked (besides K = 1)")
    parser.add_argument("--learners", nargs="+", default=list(LEARNER_NAMES), choices=LEARNER_NAMES)
    parser.add_argument("--no-speed", action="store_true", help="skip the speed section")
    parser.add_argument("--quality-steps", type=int, default=0, help="TD3+BC eta=0 run (0: skip)")
    parser.add_argument(
        "--quality-precision", nargs="+", default=["fp32"], choices=["fp32", "bf16"]
    )
    parser.add_argument("--quality-threads", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--worker-algo", default="TD3PlusBC", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        d3rlpy_worker(args.worker, args.worker_algo, args.threads[0], args.updates, args.batch_size)
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
    """Every learner at K = 1 and K = --seeds, fp32 and bf16, beside d3rlpy's, interleaved."""
    transitions, _, data_text = bench_data(args.dataset, 100_000, seed=0)
    threads = args.threads[0]
    torch.set_num_threads(threads)
    section: dict = {
        "data": data_text,
        "batch_size": args.batch_size,
        "threads": threads,
        "seeds": args.seeds,
        "roofs_gflops": matmul_roofs(threads),
        "learners": {},
    }
    ours, flops = {}, {}
    for name in args.learners:
        for k in sorted({1, args.seeds}):
            for precision in ("fp32", "bf16"):
                print(f"warming up {name} K={k} {precision}", file=sys.stderr, flush=True)
                learner, replay = our_learner(
                    name, transitions, k, precision == "bf16", args.batch_size
                )
                ours[(name, k, precision)] = (learner, replay)
        flops[name] = update_flops(*ours[(name, 1, "fp32")], args.batch_size)
    with tempfile.TemporaryDirectory() as folder:
        data_path = Path(folder) / "data.npz"
        np.savez(data_path, **transitions.arrays())
        workers, version = {}, None
        for name in args.learners:
            worker, version = start_d3rlpy(
                args.d3rlpy_python,
                data_path,
                D3RLPY_ALGOS[name],
                threads,
                max(ROUND_UPDATES[name] // 4, 2),
                args.batch_size,
            )
            if worker is not None:
                workers[name] = worker
        rates: dict[str, dict[str, list[dict]]] = {name: {} for name in args.learners}
        for round_index in range(args.rounds):
            print(f"round {round_index + 1}/{args.rounds}", file=sys.stderr, flush=True)
            for name in args.learners:
                for (learner_name, k, precision), (learner, replay) in ours.items():
                    if learner_name != name:
                        continue
                    updates = max(ROUND_UPDATES[name] // k, 2)
                    rates[name].setdefault(f"ours K={k} {precision}", []).append(
                        time_ours(learner, replay, updates, args.batch_size)
                    )
                if name in workers:
                    answer = d3rlpy_round(workers[name])
                    label = f"d3rlpy {version} {D3RLPY_ALGOS[name]}"
                    for kind in ("update_only", "with_sampling"):
                        rates[name].setdefault(f"{label} ({kind.replace('_', ' ')})", []).append(
                            answer[kind]
                        )
        for worker in workers.values():
            worker.stdin.close()
            worker.wait()
    for name in args.learners:
        section["learners"][name] = {
            "update_gflop_per_seed": flops[name] / 1e9,
            "variants": {
                variant: {
                    "rounds": values,
                    "cpu_median": median([v["cpu"] for v in values]),
                    "wall_median": median([v["wall"] for v in values]),
                }
                for variant, values in rates[name].items()
            },
        }
    return section


# the speed targets: our K-seed rate over d3rlpy's update-only rate, per precision
TARGETS = {
    ("td3bc", "bf16"): 4.0,
    ("td3bc", "fp32"): 1.5,
    ("iql", "fp32"): 3.0,
    ("cql", "fp32"): 1.5,
}


def speed_markdown(speed: dict) -> list[str]:
    roofs = speed["roofs_gflops"]
    lines = [
        "## Updates/s: ours (K seeds stacked in one process) beside d3rlpy 2.8.1, same data",
        "",
        f"Command: `{speed['command']}` (OMP_WAIT_POLICY={speed['omp_wait_policy']}); "
        f"load average (1, 5, 15 min) {speed['load_before']} before, "
        f"{speed['load_after']} after. Data: {speed['data']}; batch size "
        f"{speed['batch_size']}; {speed['threads']} torch thread per process.",
        "",
        "Rates are seed-updates per second (K seeds x updates / time; K = 1 is a plain run), "
        "sampling included for ours; d3rlpy runs one seed per process, in its own interpreter, "
        "in rounds alternating with ours; medians over the rounds. CPU-time rates count the "
        "process's own CPU seconds, so they hold up under load better than wall-time rates. "
        f"Matmul roofs measured in this run (1280x256 @ 256x256): fp32 {roofs['fp32']:.0f} "
        f"GFLOP/s, bf16 {roofs['bf16']:.0f} GFLOP/s; each row's GFLOP/s is its CPU rate times "
        "the matmul FLOPs of one seed's update (counted by torch's FlopCounterMode).",
        "",
    ]
    for name, entry in speed["learners"].items():
        variants = entry["variants"]
        base_name = next((v for v in variants if v.endswith("(update only)")), None)
        base = variants.get(base_name)
        lines += [
            f"### {name} ({entry['update_gflop_per_seed']:.2f} GFLOP per seed-update)",
            "",
            "| variant | per CPU-s | per wall-s | ÷ d3rlpy update (CPU) | ÷ (wall) | GFLOP/s "
            "| of roof |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for variant, values in variants.items():
            ratio_cpu = ratio_wall = ""
            if base and variant.startswith("ours"):
                ratio_cpu = f"{values['cpu_median'] / base['cpu_median']:.2f}×"
                ratio_wall = f"{values['wall_median'] / base['wall_median']:.2f}×"
            precision = "bf16" if variant.endswith("bf16") else "fp32"
            gflops = values["cpu_median"] * entry["update_gflop_per_seed"]
            lines.append(
                f"| {variant} | {values['cpu_median']:.1f} | {values['wall_median']:.1f} | "
                f"{ratio_cpu} | {ratio_wall} | {gflops:.0f} | {gflops / roofs[precision]:.0%} |"
            )
        lines.append("")
        for (learner, precision), target in TARGETS.items():
            ours = variants.get(f"ours K={speed['seeds']} {precision}")
            if learner != name or not (ours and base):
                continue
            ratio = ours["cpu_median"] / base["cpu_median"]
            lines.append(
                f"- target K={speed['seeds']} {precision} ≥ {target:g}× d3rlpy's update: "
                f"{ratio:.2f}× ({'met' if ratio >= target else 'not met'})"
            )
        lines.append("")
    return lines


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
        "Precision: every learner defaults to fp32 (stages/train.toml [<learner>.precision]); "
        "bf16 hidden matmuls (heads, targets and losses in fp32) are an option until a parity "
        "measurement makes them a default (bench/results/learner_precision.md).",
        "",
    ]
    speed = report.get("speed")
    if speed and "learners" in speed:
        lines += speed_markdown(speed)
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
