"""Does HIPODE help TD3+BC? Both arms, the same seeds, the same update budget.

For each task, TD3+BC trains on the source alone (arm `eta0`, η = 0) and on source ⊕ the
HIPODE artifact at the task's paper η (arm `hipode`); ablation arms add artifacts built with
another negative-sampling weight α (Table 13), uniform candidates in the data's bounding box
instead of the state-transition model (Table 12), another selecting rate λ or value-penalty
form, or train on the union sampled uniformly instead of η·B synthetic rows per batch. Every
(task, arm, seed) is one `hipode train` run folder under --out, so a sweep resumes where it
stopped: finished runs are read back, unfinished ones continue from their checkpoint.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/quality.py --tasks hopper-m-r \
        --seeds 0,1,2 --steps 50000 --workers 2
    python bench/quality.py --budget paper --engine ray --address auto    # a cluster, 1M steps
    python bench/quality.py --alpha=-1,0,1,2,4,8 --uniform --lam 0.2,1.0  # ablations
    python bench/quality.py --penalty l2,contrastive --union   # default penalty form, mixing

Writes quality.md, quality.json and quality.png (learning curves) to --results. Runs execute
in-process (--engine local --workers 1), in local worker processes (--workers N) or on Ray
(--engine ray; a local Ray unless --address names a cluster, whose nodes must see --out and
the dataset root at the same paths).
"""

from __future__ import annotations

import json
import math
import os
import platform
import shlex
import statistics
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from multiprocessing import get_context
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

sys.path.insert(0, str(Path(__file__).resolve().parent))  # quality_worker beside this file

import quality_worker  # noqa: E402
from machine import LoadSampler  # noqa: E402
from quality_worker import RunSpec, run_one  # noqa: E402

from hipode_pipeline import console  # noqa: E402
from hipode_pipeline.commands.common import (  # noqa: E402
    DeviceOption,
    EvalEpisodesOption,
    EvalEveryOption,
    ForceFlag,
    JsonFlag,
    RootOption,
    user_errors,
)
from hipode_pipeline.data.transitions import SourceInfo, Transitions  # noqa: E402
from hipode_pipeline.errors import DatasetNotFoundError, HipodeError  # noqa: E402
from hipode_pipeline.files import write_bytes_atomic, write_json_atomic, write_text_atomic  # noqa: E402
from hipode_pipeline.paths import use_datasets_root  # noqa: E402
from hipode_pipeline.tasks import get_task  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
DEFAULT_TASKS = ("hopper-m-r", "walker2d-m-r", "halfcheetah-m-r")
BASELINE, HIPODE = "eta0", "hipode"
SYNTHETIC_COLUMNS = (
    "task",
    "arm",
    "rows",
    "reward",
    "real reward, same states",
    "dynamics error",
    "terminal",
    "novelty",
)
WINDOW = 3  # evaluations averaged in the robustness column
ENGINES = ("local", "ray")
# the paper's TD3+BC numbers on D4RL v0 data (Table 11): without and with HIPODE
PAPER_TD3BC = {
    "hopper-m-r": (32.7, 36.8),
    "walker2d-m-r": (19.6, 36.4),
    "halfcheetah-m-r": (43.3, 44.0),
}


@dataclass(frozen=True)
class Arm:
    """One way of training TD3+BC on a task."""

    name: str  # folder and label: eta0, hipode, alpha-1, uniform, lam1, ...
    data: str  # "source" (η = 0) or "merged"
    augment: dict[str, Any] | None = None  # run_augment overrides; None: the task's artifact
    label: str = ""  # what the arm is, for the table
    mixing: str = "mixed"  # batch composition: mixed (η·B synthetic per batch) | union


@dataclass
class QualityConfig:
    """What one sweep runs and where it writes."""

    tasks: list[str] = field(default_factory=lambda: list(DEFAULT_TASKS))  # task names
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])  # training seeds, every arm
    steps: int | None = None  # updates per run; None: the budget's
    budget: str | None = None  # "cpu" or "paper" (train.toml); None: paper with CUDA, else cpu
    eval_every: int | None = None  # updates between evaluations; None: train.toml's
    eval_episodes: int | None = None  # episodes per evaluation; None: train.toml's
    alphas: list[float] = field(default_factory=list)  # ablation: negative-sampling weights
    uniform: bool = False  # ablation: uniform candidates instead of the state-transition CVAE
    lams: list[float] = field(default_factory=list)  # ablation: selecting rates
    penalties: list[str] = field(default_factory=list)  # ablation: value-penalty forms
    union: bool = False  # ablation: sample the union uniformly instead of η·B per batch
    artifact_seeds: list[int] = field(default_factory=list)  # control: the hipode arm's
    # settings with artifacts of other stage-one seeds (how much one artifact differs from another)
    baseline_arms: bool = True  # run the eta0 and hipode arms (off: ablation arms only)
    source: str | None = None  # source dataset for a single task; None: its collected dataset
    artifact: Path | None = None  # the hipode arm's artifact for a single task
    profile: str = "full"  # generator profile for artifacts this script builds
    artifact_seed: int = 0  # seed of artifacts this script builds (one per task and arm)
    engine: str = "local"  # local | ray
    address: str | None = None  # Ray cluster address; None: start a local Ray
    workers: int = 1  # parallel runs (local processes, or the local Ray's CPUs)
    threads: int = 1  # torch threads per run
    device: str | None = None  # torch device; None: CUDA when present
    out: Path = REPO / "bench" / "out" / "quality"  # run folders and ablation artifacts
    results: Path = REPO / "bench" / "results"  # quality.md / .json / .png
    root: Path | None = None  # dataset root; None: $MINARI_DATASETS_PATH, else ./datasets
    force: bool = False  # train every run again
    show_progress: bool = True  # the bar over runs
    report_only: bool = False  # train nothing: report the runs already finished at this budget
    note: str = ""  # free text for the report, e.g. how runs read back were trained


@dataclass
class QualityReport:
    """What a sweep measured, as written to quality.json."""

    command: str  # the command line that reproduces it
    budget: dict[str, Any]  # steps, eval_every, eval_episodes, seeds
    machine: dict[str, Any]  # platform, cores, torch, device, engine, workers, load averages
    arms: dict[str, list[dict[str, Any]]]  # task -> arm descriptions
    runs: list[dict[str, Any]]  # one record per (task, arm, seed)
    summary: dict[str, Any]  # task -> arm -> mean ± std and paired differences
    started: str  # UTC time the sweep started
    seconds: float  # wall time of the sweep
    files: dict[str, str] = field(default_factory=dict)  # the written report files
    note: str = ""  # the --note text

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def display_path(path: str | Path | None) -> str | None:
    """A path as the report shows it: relative to the repository when inside it."""
    if path is None:
        return None
    resolved = Path(path).resolve()
    return str(resolved.relative_to(REPO)) if resolved.is_relative_to(REPO) else str(path)


def arm_name(kind: str, value: float) -> str:
    return f"{kind}{value:g}"


def arms_for(config: QualityConfig) -> list[Arm]:
    """The baseline pair, then one arm per ablation setting."""
    arms = []
    if config.baseline_arms:
        arms += [
            Arm(BASELINE, "source", None, "TD3+BC, η = 0 (source only)"),
            Arm(HIPODE, "merged", None, "TD3+BC + HIPODE (paper η, λ, α)"),
        ]
    arms += [
        Arm(arm_name("alpha", a), "merged", {"alpha": a}, f"HIPODE, α = {a:g}")
        for a in config.alphas
    ]
    if config.uniform:
        arms.append(
            Arm("uniform", "merged", {"candidates": "uniform"}, "HIPODE, uniform candidates")
        )
    arms += [
        Arm(arm_name("lam", lam), "merged", {"lam": lam}, f"HIPODE, λ = {lam:g}")
        for lam in config.lams
    ]
    arms += [
        Arm(f"penalty-{form}", "merged", {"penalty": form}, f"HIPODE, {form} value penalty")
        for form in config.penalties
    ]
    if config.artifact_seed in config.artifact_seeds:
        raise HipodeError(
            f"--artifact-seeds: expected seeds other than {config.artifact_seed}, the hipode "
            f"arm's own artifact seed, found {config.artifact_seeds}"
        )
    arms += [
        Arm(f"artifact-seed{seed}", "merged", {"seed": seed}, f"HIPODE, stage-one seed {seed}")
        for seed in config.artifact_seeds
    ]
    if config.union:
        arms.append(Arm("mixing-union", "merged", None, "HIPODE, uniform over the union", "union"))
    names = [arm.name for arm in arms]
    if not arms or len(set(names)) != len(names):
        raise HipodeError(
            f"arms: expected at least one and no repeats (check --alpha/--lam), found {names}"
        )
    return arms


def resolve_budget(config: QualityConfig) -> tuple[int, int, int, str]:
    """steps, eval_every, eval_episodes and the budget's name, from train.toml unless given."""
    from hipode_pipeline.device import select_device
    from hipode_pipeline.train import train_settings

    settings = train_settings()
    budget = config.budget or ("paper" if select_device(config.device).type == "cuda" else "cpu")
    if budget not in ("cpu", "paper"):
        raise HipodeError(f"--budget: expected 'cpu' or 'paper', found {budget!r}")
    td3bc = settings["td3bc"]
    steps = config.steps or (td3bc["steps"] if budget == "paper" else td3bc["cpu_steps"])
    eval_every = config.eval_every or td3bc["eval_every"]
    eval_episodes = config.eval_episodes or settings["run"]["eval_episodes"]
    if min(steps, eval_every, eval_episodes) < 1:
        raise HipodeError("--steps, --eval-every, --eval-episodes: expected positive integers")
    if steps % eval_every:
        raise HipodeError(
            f"--eval-every: expected a divisor of --steps ({steps}) so every run is evaluated "
            f"on the same grid, found {eval_every}"
        )
    return steps, eval_every, eval_episodes, budget


def ensure_source(task_name: str, source: str | None, root: Path, show_progress: bool) -> None:
    """Collect the task's own dataset if it is missing (an explicit --source must exist)."""
    from hipode_pipeline.data.load import describe_source

    task = get_task(task_name)
    try:
        describe_source(source or task.name, root)
        return
    except DatasetNotFoundError:
        if source is not None and source not in (task.name, task.local_dataset_id):
            raise
    from hipode_pipeline.data.collect import collect

    console.err.print(
        f"[yellow]{task.name}: source {task.local_dataset_id} is missing under {root}; "
        "collecting it first (hipode collect), this takes a while once[/]"
    )
    collect(task, root=root, show_progress=show_progress)


def prepare_artifact(task_name: str, arm: Arm, config: QualityConfig, root: Path) -> Path | None:
    """The arm's artifact, built through stage one if missing (said on stderr); None for η = 0.

    The hipode arm uses --artifact or the task's default artifact; an ablation arm whose
    setting equals the task's paper value shares it; other ablation arms get their own file
    under <out>/<task>/<arm>/ (an existing one built from the same request is kept)."""
    from hipode_pipeline.artifact import default_artifact_path
    from hipode_pipeline.augment import run_augment
    from hipode_pipeline.models.generators import GeneratorConfig

    if arm.data == "source":
        return None
    task = get_task(task_name)
    params = task.augment_params("td3bc")
    defaults = {
        "alpha": params.alpha,
        "lam": params.lam,
        "candidates": "model",
        "penalty": GeneratorConfig.__dataclass_fields__["penalty"].default,
        "seed": config.artifact_seed,
    }
    overrides = {"seed": config.artifact_seed, **(arm.augment or {})}
    if all(defaults[key] == value for key, value in overrides.items()):
        path = config.artifact or default_artifact_path(
            task.name, seed=config.artifact_seed, root=root
        )
        if arm.augment:
            console.err.print(f"{task.name} {arm.name}: the paper's setting; shares {path}")
        if path.is_file():
            return path
        console.err.print(
            f"[yellow]{task.name}: no HIPODE artifact at {path}; building it (stage one, "
            f"profile {config.profile}, seed {config.artifact_seed})[/]"
        )
        out = path
    else:
        out = config.out / task.name / arm.name / "artifact.hdf5"
        if not out.is_file():
            console.err.print(
                f"[yellow]{task.name} {arm.name}: building its artifact at {out} (stage one: "
                f"generators are trained unless cached for these settings)[/]"
            )
        out.parent.mkdir(parents=True, exist_ok=True)
    run_augment(
        task.name,
        source=config.source,
        profile=config.profile,
        out=out,
        root=root,
        device=config.device,
        show_progress=config.show_progress,
        **overrides,
    )
    return out


def run_specs(config: QualityConfig, root: Path) -> tuple[list[RunSpec], dict[str, list[dict]]]:
    """Every (task, arm, seed) run, seeds interleaved so paired runs finish close together."""
    from hipode_pipeline.data.load import load_source

    if (config.source or config.artifact) and len(config.tasks) != 1:
        raise HipodeError("--source/--artifact: expected exactly one task in --tasks")
    steps, eval_every, eval_episodes, _ = resolve_budget(config)
    arms = arms_for(config)
    specs, described = [], {}
    for task_name in config.tasks:
        task = get_task(task_name)
        ensure_source(task.name, config.source, root, config.show_progress)
        described[task.name] = []
        paths = {}
        for arm in arms:
            paths[arm.name] = prepare_artifact(task.name, arm, config, root)
        source = load_source(config.source or task.name, root)
        # arms that share an artifact (the paper's setting) read it once
        stats = {
            path: synthetic_stats(path, source) for path in set(paths.values()) if path is not None
        }
        for arm in arms:
            artifact = paths[arm.name]
            described[task.name].append(
                {
                    **asdict(arm),
                    "artifact": display_path(artifact),
                    "synthetic": stats.get(artifact),
                }
            )
        for seed in config.seeds:
            for arm in arms:
                artifact = paths[arm.name]
                specs.append(
                    RunSpec(
                        task=task.name,
                        arm=arm.name,
                        data=arm.data,
                        eta=0.0 if arm.data == "source" else task.augment_params("td3bc").eta,
                        seed=seed,
                        steps=steps,
                        eval_every=eval_every,
                        eval_episodes=eval_episodes,
                        out_dir=str(config.out.resolve()),
                        root=str(root),
                        source=config.source,
                        artifact=None if artifact is None else str(artifact.resolve()),
                        artifact_checksum=None if artifact is None else stats[artifact]["checksum"],
                        device=config.device,
                        threads=config.threads,
                        force=config.force,
                        mixing=arm.mixing,
                    )
                )
    return specs, described


def run_local(specs: list[RunSpec], workers: int) -> Iterator[dict[str, Any]]:
    """In this process (one worker) or in fresh spawned processes, one per run."""
    if workers <= 1:
        for spec in specs:
            yield run_one(spec.to_dict())
        return
    with get_context("spawn").Pool(workers, maxtasksperchild=1) as pool:
        yield from pool.imap_unordered(run_one, [spec.to_dict() for spec in specs])


def read_finished(specs: list[RunSpec]) -> Iterator[dict[str, Any]]:
    """The runs already finished at the budget, read back; the others are listed on stderr."""
    missing = []
    for spec in specs:
        scores = quality_worker.finished_scores(spec)
        if scores is None:
            missing.append(f"{spec.task} {spec.arm} seed {spec.seed}")
            continue
        yield quality_worker.run_record(spec, scores, "finished earlier")
    if missing:
        console.err.print(f"[yellow]not finished at this budget, left out: {', '.join(missing)}[/]")


def run_ray(specs: list[RunSpec], address: str | None, workers: int) -> Iterator[dict[str, Any]]:
    """One Ray task per run (1 CPU each); a local Ray with `workers` CPUs unless `address`."""
    try:
        import ray
    except ImportError:
        raise HipodeError(
            "--engine ray: expected Ray to be installed; install it with "
            "`pip install 'hipode-pipeline[ray]'` (ray[default]>=2.40) or pass --engine local"
        ) from None
    # workers import only the library; this module travels with the task
    ray.cloudpickle.register_pickle_by_value(quality_worker)
    env_vars = {"OMP_WAIT_POLICY": "PASSIVE", "MINARI_DATASETS_PATH": specs[0].root}
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(
            address=address,
            num_cpus=None if address else workers,
            include_dashboard=False,
            log_to_driver=False,
            runtime_env={"env_vars": env_vars},
        )
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(run_one)
        pending = [remote.remote(spec.to_dict()) for spec in specs]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        if started_here:
            ray.shutdown()


def mean_std(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for a single value)."""
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def window_score(run: dict[str, Any]) -> float:
    """Mean of the run's last WINDOW evaluations: one evaluation of a few episodes is noisy, so
    this is reported beside the final score as a robustness check (the final stays the result)."""
    return statistics.fmean(point[1] for point in run["curve"][-WINDOW:])


def curve_mean(run: dict[str, Any]) -> float:
    """Mean over all of the run's evaluations (area under the curve per update): how early an
    arm gets good, which a final score alone does not show."""
    return statistics.fmean(point[1] for point in run["curve"])


def synthetic_stats(artifact: Path, source: tuple[Transitions, SourceInfo]) -> dict[str, Any]:
    """What an arm's synthetic data is: its rewards against the real rewards at the same source
    states, its dynamics error, terminal share and novelty (from stage one's summary)."""
    from hipode_pipeline.artifact import read_artifact
    from hipode_pipeline.augment import summary_path
    from hipode_pipeline.merge import check_pair

    data = read_artifact(artifact)
    check_pair(*source, data)  # source_index must index this very source
    rewards = data.transitions.rewards
    summary = summary_path(artifact)
    novelty = json.loads(summary.read_text()).get("novelty_mean") if summary.is_file() else None
    return {
        "checksum": data.manifest.get("checksum"),
        "rows": len(rewards),
        "reward_mean": float(rewards.mean()),
        "source_reward_mean_same_states": float(
            source[0].rewards[data.diagnostics["source_index"]].mean()
        ),
        "dynamics_error_median": float(np.median(data.diagnostics["dynamics_error"])),
        "terminal_fraction": float(data.transitions.terminals.mean()),
        "novelty_mean": novelty,
    }


def paired_difference(
    runs: list[dict[str, Any]], arm: str, base: str, key: str = "final_score"
) -> dict[str, Any] | None:
    """arm − base over the seeds both have: mean, std over seeds and standard error."""
    by_seed = {(r["arm"], r["seed"]): r[key] for r in runs}
    seeds = sorted(s for a, s in by_seed if a == arm and (base, s) in by_seed)
    if not seeds or arm == base:
        return None
    diffs = [by_seed[arm, s] - by_seed[base, s] for s in seeds]
    mean, std = mean_std(diffs)
    return {
        "vs": base,
        "seeds": seeds,
        "per_seed": diffs,
        "mean": mean,
        "std": std,
        "sem": std / math.sqrt(len(diffs)),
    }


def summarize(runs: list[dict[str, Any]], arms: dict[str, list[dict]]) -> dict[str, Any]:
    """Per task and arm: final scores per seed, mean ± std, paired differences."""
    summary: dict[str, Any] = {}
    for task, task_arms in arms.items():
        task_runs = [
            {**r, "window_score": window_score(r), "curve_mean": curve_mean(r)}
            for r in runs
            if r["task"] == task
        ]
        summary[task] = {}
        for arm in task_arms:
            mine = sorted(
                (r for r in task_runs if r["arm"] == arm["name"]), key=lambda r: r["seed"]
            )
            if not mine:
                continue
            mean, std = mean_std([r["final_score"] for r in mine])
            window_mean, window_std = mean_std([r["window_score"] for r in mine])
            area_mean, area_std = mean_std([r["curve_mean"] for r in mine])
            summary[task][arm["name"]] = {
                "seeds": [r["seed"] for r in mine],
                "final_scores": [r["final_score"] for r in mine],
                "mean": mean,
                "std": std,
                "window_scores": [r["window_score"] for r in mine],
                "window_mean": window_mean,
                "window_std": window_std,
                "difference": {
                    base: paired_difference(task_runs, arm["name"], base)
                    for base in (BASELINE, HIPODE)
                    if arm["name"] != base
                },
                "window_difference": {
                    base: paired_difference(task_runs, arm["name"], base, "window_score")
                    for base in (BASELINE, HIPODE)
                    if arm["name"] != base
                },
                "curve_means": [r["curve_mean"] for r in mine],
                "curve_mean": area_mean,
                "curve_std": area_std,
                "curve_difference": {
                    base: paired_difference(task_runs, arm["name"], base, "curve_mean")
                    for base in (BASELINE, HIPODE)
                    if arm["name"] != base
                },
            }
    return summary


def curve_plot(runs: list[dict[str, Any]], path: Path) -> None:
    """Learning curves: mean ± std over seeds of the normalized score, one panel per task."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    tasks = list(dict.fromkeys(r["task"] for r in runs))
    fig, axes = plt.subplots(1, len(tasks), figsize=(5.5 * len(tasks), 4), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        for arm in dict.fromkeys(r["arm"] for r in runs if r["task"] == task):
            curves = [r["curve"] for r in runs if r["task"] == task and r["arm"] == arm]
            length = min(len(c) for c in curves)
            scores = np.array([[point[1] for point in c[:length]] for c in curves], dtype=float)
            steps = np.array([point[0] for point in curves[0][:length]])
            mean, std = scores.mean(0), scores.std(0, ddof=1) if len(curves) > 1 else 0 * scores[0]
            ax.plot(steps, mean, marker="o", ms=3, label=f"{arm} (n={len(curves)})")
            ax.fill_between(steps, mean - std, mean + std, alpha=0.2)
        ax.set(title=f"TD3+BC on {task}", xlabel="updates", ylabel="normalized score")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    write_bytes_atomic(path, buffer.getvalue())


def _pm(mean: float, std: float) -> str:
    return f"{mean:.1f} ± {std:.1f}"


def _difference_text(diff: dict[str, Any] | None) -> str:
    if diff is None:
        return ""
    return (
        f"{diff['mean']:+.1f} ± {diff['std']:.1f} (sem {diff['sem']:.1f}, n={len(diff['seeds'])})"
    )


def table_rows(report: QualityReport) -> list[list[Any]]:
    """One row per (task, arm): per-seed finals, mean ± std, paired differences."""
    rows = []
    for task, arms in report.summary.items():
        for name, arm in arms.items():
            diffs = arm["difference"]
            rows.append(
                [
                    task,
                    name,
                    ", ".join(f"{s:.1f}" for s in arm["final_scores"]),
                    _pm(arm["mean"], arm["std"]),
                    _difference_text(diffs.get(BASELINE)),
                    _difference_text(diffs.get(HIPODE)) if name not in (BASELINE, HIPODE) else "",
                    _pm(arm["window_mean"], arm["window_std"]),
                    _difference_text(arm["window_difference"].get(BASELINE)),
                    _pm(arm["curve_mean"], arm["curve_std"]),
                    _difference_text(arm["curve_difference"].get(BASELINE)),
                ]
            )
    return rows


COLUMNS = [
    "task",
    "arm",
    "final score per seed",
    "mean ± std",
    "Δ vs eta0",
    "Δ vs hipode",
    f"last {WINDOW} evals: mean ± std",
    f"last {WINDOW} evals: Δ vs eta0",
    "all evals: mean ± std",
    "all evals: Δ vs eta0",
]


def markdown(report: QualityReport) -> str:
    """quality.md: command, budget, machine and load, the table, the curves."""
    budget, machine = report.budget, report.machine
    load = machine["load_during"]
    names = {arm["name"] for arms in report.arms.values() for arm in arms}
    title = (
        "Does HIPODE help TD3+BC? Same seeds, same budget, both arms"
        if names <= {BASELINE, HIPODE}
        else "HIPODE ablations with TD3+BC: same seeds, same budget, every arm"
    )
    lines = [
        f"# {title}",
        "",
        f"Command: `{report.command}` (OMP_WAIT_POLICY=PASSIVE), started {report.started}, "
        f"{report.seconds / 60:.1f} min wall time for the runs this invocation executed "
        "(runs finished earlier are read back from their folders).",
        "",
        *([report.note, ""] if report.note else []),
        f"Budget: {budget['steps']:,} TD3+BC updates per run (batch 256), evaluation every "
        f"{budget['eval_every']:,} updates on {budget['eval_episodes']} episodes; seeds "
        f"{budget['seeds']} in every arm. The result of a run is its last evaluation "
        "(D4RL-normalized score), never the best one.",
        "",
        f"Machine: {machine['platform']}, {machine['cpu_count']} cores, torch "
        f"{machine['torch']}, device {machine['device']}, engine {machine['engine']} with "
        f"{machine['workers']} parallel run(s) of {machine['threads']} torch thread(s). "
        "The machine is shared with other jobs: 1-minute load average during the sweep "
        f"min {load['min']:.2f} / mean {load['mean']:.2f} / max {load['max']:.2f} "
        f"({load['samples']} samples)"
        + (
            "; this invocation only read finished runs back (--report-only), so that load is "
            "the reading's, not the training's."
            if budget.get("report_only")
            else "."
        ),
        "",
        "| " + " | ".join(COLUMNS) + " |",
        "| " + " | ".join("---" for _ in COLUMNS) + " |",
    ]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in table_rows(report)]
    lines += [
        "",
        "Δ: the arm minus the other arm on the same seed, mean ± std over the paired seeds "
        "(sem = std/√n). A |Δ| within about two sem is not distinguishable from noise. "
        f"The 'last {WINDOW} evals' columns average each run's last {WINDOW} evaluations "
        "instead of taking the final one alone: a robustness check against the noise of a "
        "single evaluation. "
        "'All evals' averages every evaluation of a run (the area under its learning curve): "
        "it measures how early an arm scores well, which the final score does not.",
        "",
    ]
    for task in report.summary:
        if task in PAPER_TD3BC:
            base, hipode = PAPER_TD3BC[task]
            lines.append(
                f"Paper (Table 11, D4RL v0 data): {task} TD3+BC {base} vs "
                f"HIPODE {hipode} ({hipode - base:+.1f}). Our source data is locally collected "
                "(Gymnasium v5 environments), so absolute scores are not comparable."
            )
    lines += ["", "Arms and artifacts:", ""]
    for task, arms in report.arms.items():
        for arm in arms:
            lines.append(f"- {task} `{arm['name']}`: {arm['label']}; artifact {arm['artifact']}")
    lines += [
        "",
        "Synthetic data of each arm (reward: mean over the artifact, and the real rewards "
        "at the same source states; dynamics error: median, z-scored; novelty: mean z-scored "
        "distance from a kept next state to its nearest source state, on stage one's sample):",
        "",
        "| " + " | ".join(SYNTHETIC_COLUMNS) + " |",
        "| " + " | ".join("---" for _ in SYNTHETIC_COLUMNS) + " |",
    ]
    for task, arms in report.arms.items():
        for arm in arms:
            stats = arm.get("synthetic")
            if stats is None:
                continue
            novelty = stats["novelty_mean"]
            cells = [
                task,
                arm["name"],
                f"{stats['rows']:,}",
                f"{stats['reward_mean']:.3f}",
                f"{stats['source_reward_mean_same_states']:.3f}",
                f"{stats['dynamics_error_median']:.4f}",
                f"{100 * stats['terminal_fraction']:.2f}%",
                "n/a" if novelty is None else f"{novelty:.3f}",
            ]
            lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Per run (status: trained / resumed / finished earlier):", ""]
    for run in sorted(report.runs, key=lambda r: (r["task"], r["arm"], r["seed"])):
        rate = run["updates_per_second"]
        lines.append(
            f"- {run['task']} {run['arm']} seed {run['seed']}: {run['final_score']:.1f} "
            f"({run['status']}; {'n/a' if not rate else f'{rate:.0f}'} updates/s)"
        )
    if "png" in report.files:
        lines += ["", f"![learning curves]({Path(report.files['png']).name})", ""]
    return "\n".join(lines) + "\n"


def command_line(config: QualityConfig) -> str:
    """A command that reproduces this sweep."""
    args = ["python", "bench/quality.py", "--tasks", ",".join(config.tasks)]
    args += ["--seeds", ",".join(str(s) for s in config.seeds)]
    for flag, value in (
        ("--steps", config.steps),
        ("--budget", config.budget),
        ("--eval-every", config.eval_every),
        ("--eval-episodes", config.eval_episodes),
        ("--source", config.source),
        ("--artifact", config.artifact),
        ("--address", config.address),
        ("--device", config.device),
    ):
        if value is not None:
            args += [flag, str(value)]
    if config.alphas:
        args += [f"--alpha={','.join(f'{a:g}' for a in config.alphas)}"]
    if config.lams:
        args += ["--lam", ",".join(f"{x:g}" for x in config.lams)]
    args += ["--uniform"] if config.uniform else []
    if config.penalties:
        args += ["--penalty", ",".join(config.penalties)]
    args += ["--union"] if config.union else []
    if config.artifact_seed:
        args += ["--artifact-seed", str(config.artifact_seed)]
    if config.artifact_seeds:
        args += ["--artifact-seeds", ",".join(str(seed) for seed in config.artifact_seeds)]
    args += [] if config.baseline_arms else ["--no-baselines"]
    args += ["--report-only"] if config.report_only else []
    if config.profile != "full":
        args += ["--profile", config.profile]
    args += ["--engine", config.engine, "--workers", str(config.workers)]
    return shlex.join(args)


def run_quality(config: QualityConfig) -> QualityReport:
    """Run (or resume) the sweep and write quality.md, quality.json and quality.png."""
    import torch

    if config.engine not in ENGINES:
        raise HipodeError(f"--engine: expected one of {ENGINES}, found {config.engine!r}")
    if config.workers < 1 or config.threads < 1 or not config.seeds or not config.tasks:
        raise HipodeError("--workers, --threads: expected ≥ 1; --seeds, --tasks: not empty")
    root = use_datasets_root(config.root)
    config.out = config.out.resolve()
    steps, eval_every, eval_episodes, budget = resolve_budget(config)
    started, clock = datetime.now(UTC).isoformat(timespec="seconds"), time.perf_counter()
    specs, arms = run_specs(config, root)
    runs = []
    with LoadSampler() as load, console.progress(disable=not config.show_progress) as prog:
        bar = prog.add_task("quality runs", total=len(specs), rate="", info="")
        if config.report_only:
            executed = read_finished(specs)
        elif config.engine == "local":
            executed = run_local(specs, config.workers)
        else:
            executed = run_ray(specs, config.address, config.workers)
        for record in executed:
            runs.append({**record, "run_dir": display_path(record["run_dir"])})
            elapsed = time.perf_counter() - clock
            prog.update(
                bar,
                advance=1,
                rate=f"{len(runs) / elapsed * 3600:.1f} runs/h",
                info=f"{record['task']} {record['arm']} seed {record['seed']}: "
                f"{record['final_score']:.1f}",
            )
    if not runs:
        raise HipodeError(f"{config.out}: no finished runs at {steps} steps to report")
    from hipode_pipeline.device import select_device

    report = QualityReport(
        command=command_line(config),
        budget={
            "name": budget,
            "steps": steps,
            "eval_every": eval_every,
            "eval_episodes": eval_episodes,
            "seeds": config.seeds,
            "report_only": config.report_only,
        },
        machine={
            "platform": f"{platform.system()} {platform.machine()}",
            "cpu_count": os.cpu_count(),
            "torch": torch.__version__,
            "device": str(select_device(config.device)),
            "engine": config.engine + (f" ({config.address})" if config.address else ""),
            "workers": config.workers,
            "threads": config.threads,
            "load_during": load.stats(),
        },
        arms=arms,
        runs=sorted(runs, key=lambda r: (r["task"], r["arm"], r["seed"])),
        summary=summarize(runs, arms),
        started=started,
        seconds=time.perf_counter() - clock,
        note=config.note,
    )
    config.results.mkdir(parents=True, exist_ok=True)
    png, md, js = (config.results / f"quality.{ext}" for ext in ("png", "md", "json"))
    curve_plot(report.runs, png)
    report.files = {"png": display_path(png), "md": display_path(md), "json": display_path(js)}
    write_text_atomic(md, markdown(report))
    write_json_atomic(js, report.to_dict())
    return report


def parse_list(text: str, kind: type, flag: str) -> list[Any]:
    """A comma-separated option value as a list of `kind`."""
    try:
        return [kind(item.strip()) for item in text.split(",") if item.strip()]
    except ValueError:
        raise HipodeError(
            f"{flag}: expected comma-separated {kind.__name__} values, found {text!r}"
        ) from None


app = typer.Typer(add_completion=False, help=__doc__.split("\n\n")[0])


@app.command()
@user_errors
def main(
    tasks: Annotated[str, typer.Option("--tasks", help="Comma-separated tasks.")] = ",".join(
        DEFAULT_TASKS
    ),
    seeds: Annotated[
        str, typer.Option("--seeds", help="Comma-separated seeds, every arm.")
    ] = "0,1,2",
    steps: Annotated[
        int | None, typer.Option("--steps", help="Updates per run (default: the budget's).")
    ] = None,
    budget: Annotated[
        str | None,
        typer.Option(
            "--budget", help="cpu (train.toml cpu_steps) or paper (1M); default by device."
        ),
    ] = None,
    eval_every: EvalEveryOption = None,
    eval_episodes: EvalEpisodesOption = None,
    alpha: Annotated[
        str,
        typer.Option(
            "--alpha",
            help="Ablation: comma-separated negative-sampling α (Table 13), e.g. -1,0,1,2,4,8.",
        ),
    ] = "",
    uniform: Annotated[
        bool,
        typer.Option(
            "--uniform", help="Ablation: uniform candidates in the data's bounding box (Table 12)."
        ),
    ] = False,
    penalty: Annotated[
        str,
        typer.Option("--penalty", help="Ablation: comma-separated penalty forms (l2,contrastive)."),
    ] = "",
    union: Annotated[
        bool, typer.Option("--union", help="Ablation: sample source ∪ synthetic uniformly.")
    ] = False,
    lam: Annotated[
        str,
        typer.Option("--lam", help="Ablation: comma-separated selecting rates λ, e.g. 0.2,1.0."),
    ] = "",
    artifact_seed: Annotated[
        int,
        typer.Option(
            "--artifact-seed",
            help="Stage-one seed of the hipode arm's artifact and of every artifact built here.",
        ),
    ] = 0,
    artifact_seeds: Annotated[
        str,
        typer.Option(
            "--artifact-seeds",
            help="Control: the hipode arm's settings with artifacts of other stage-one seeds.",
        ),
    ] = "",
    no_baselines: Annotated[
        bool, typer.Option("--no-baselines", help="Only the ablation arms.")
    ] = False,
    source: Annotated[
        str | None, typer.Option("--source", help="Source dataset (one task only).")
    ] = None,
    artifact: Annotated[
        Path | None, typer.Option("--artifact", help="The hipode arm's artifact (one task only).")
    ] = None,
    profile: Annotated[
        str, typer.Option("--profile", help="Generator profile of artifacts built here.")
    ] = "full",
    engine: Annotated[str, typer.Option("--engine", help="local or ray.")] = "local",
    address: Annotated[
        str | None, typer.Option("--address", help="Ray cluster address (engine ray).")
    ] = None,
    workers: Annotated[int, typer.Option("--workers", help="Parallel runs.")] = 1,
    threads: Annotated[int, typer.Option("--threads", help="Torch threads per run.")] = 1,
    device: DeviceOption = None,
    out: Annotated[
        Path, typer.Option("--out", help="Run folders and ablation artifacts.")
    ] = QualityConfig.out,
    results: Annotated[
        Path, typer.Option("--results", help="Where quality.md/.json/.png go.")
    ] = QualityConfig.results,
    root: RootOption = None,
    force: ForceFlag = False,
    report_only: Annotated[
        bool, typer.Option("--report-only", help="Train nothing; report the finished runs.")
    ] = False,
    note: Annotated[
        str, typer.Option("--note", help="Text for the report (e.g. how the runs were trained).")
    ] = "",
    as_json: JsonFlag = False,
) -> None:
    """Train TD3+BC with and without HIPODE on the same seeds and budget; write the table."""
    config = QualityConfig(
        tasks=parse_list(tasks, str, "--tasks"),
        seeds=parse_list(seeds, int, "--seeds"),
        steps=steps,
        budget=budget,
        eval_every=eval_every,
        eval_episodes=eval_episodes,
        alphas=parse_list(alpha, float, "--alpha"),
        uniform=uniform,
        lams=parse_list(lam, float, "--lam"),
        penalties=parse_list(penalty, str, "--penalty"),
        union=union,
        artifact_seed=artifact_seed,
        artifact_seeds=parse_list(artifact_seeds, int, "--artifact-seeds"),
        baseline_arms=not no_baselines,
        source=source,
        artifact=artifact,
        profile=profile,
        engine=engine,
        address=address,
        workers=workers,
        threads=threads,
        device=device,
        out=out,
        results=results,
        root=root,
        force=force,
        report_only=report_only,
        note=note,
    )
    report = run_quality(config)
    if as_json:
        console.print_json(report.to_dict())
        return
    console.out.print(console.table("TD3+BC final normalized score", COLUMNS, table_rows(report)))
    console.err.print(f"wrote {', '.join(report.files.values())}")


if __name__ == "__main__":
    app()
