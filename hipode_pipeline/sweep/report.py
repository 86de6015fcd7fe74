"""What a sweep measured: statistics over seeds, paired differences, the tables, and the report
files (quality.md, quality.json, quality.png)."""

from __future__ import annotations

import math
import statistics
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hipode_pipeline.files import write_bytes_atomic
from hipode_pipeline.sweep.plan import (
    BASELINE,
    HIPODE,
    SyntheticRows,
    artifact_seed_arm,
    learner_text,
)

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
# the paper's TD3+BC numbers on D4RL v0 data (Table 11): without and with HIPODE
PAPER_TD3BC = {
    "hopper-m-r": (32.7, 36.8),
    "walker2d-m-r": (19.6, 36.4),
    "halfcheetah-m-r": (43.3, 44.0),
}


@dataclass
class QualityReport:
    """What a sweep measured, as written to quality.json."""

    command: str  # the command line that reproduces it
    budget: dict[str, Any]  # learners, steps, eval_every, eval_episodes, seeds
    machine: dict[str, Any]  # platform, cores, torch, device, engine, workers, load averages
    arms: dict[str, list[dict[str, Any]]]  # task -> arm descriptions (one per learner and arm)
    sources: dict[str, dict[str, Any]]  # task -> the source: sha256, rows, reward, terminals
    runs: list[dict[str, Any]]  # one record per (task, learner, arm, seed)
    summary: dict[str, Any]  # task -> arm key -> mean ± std and paired differences
    started: str  # UTC time the sweep started
    seconds: float  # wall time of the sweep
    files: dict[str, str] = field(default_factory=dict)  # the written report files
    # task -> artifact checksum -> synthetic-data row: this report's and the earlier reports'
    synthetic_seen: SyntheticRows = field(default_factory=dict)
    note: str = ""  # the --note text
    unplanned_arms: list[str] = field(default_factory=list)  # "<task> <learner> <arm>" left out

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def learners(self) -> list[str]:
        return self.budget.get("learners", ["td3bc"])


def mean_std(values: list[float]) -> tuple[float, float | None]:
    """Mean and sample standard deviation (None for a single value: it has no spread)."""
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else None


def window_score(run: dict[str, Any]) -> float:
    """Mean of the run's last WINDOW evaluations: one evaluation of a few episodes is noisy, so
    this is reported beside the final score as a robustness check (the final stays the result)."""
    return statistics.fmean(point[1] for point in run["curve"][-WINDOW:])


def curve_mean(run: dict[str, Any]) -> float:
    """Mean over all of the run's evaluations (area under the curve per update): how early an
    arm gets good, which a final score alone does not show."""
    return statistics.fmean(point[1] for point in run["curve"])


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
        "sem": None if std is None else std / math.sqrt(len(diffs)),
    }


def hipode_reference(arm: dict[str, Any], arms: list[dict[str, Any]]) -> str:
    """The HIPODE arm an arm is compared with: the one built from the same stage-one seed (its
    generators), so that a rollout arm of seed 1 meets HIPODE of seed 1, not of the hipode arm's
    seed; the hipode arm where no other HIPODE arm of that seed was planned (for a HIPODE arm of
    another seed, the difference is the stage-one seed's spread)."""
    seed, learner = arm.get("stage_one_seed"), arm.get("learner", "td3bc")
    candidates = {HIPODE, artifact_seed_arm(seed)} - {arm["name"]}
    same = (
        other["name"]
        for other in arms
        if other["name"] in candidates
        and other.get("stage_one_seed") == seed
        and other.get("learner", "td3bc") == learner
    )
    return next(same, HIPODE)


def summarize(runs: list[dict[str, Any]], arms: dict[str, list[dict]]) -> dict[str, Any]:
    """Per task and arm: final scores per seed, mean ± std, and paired differences against the
    same learner's eta0 arm and its HIPODE arm of the same stage-one seed (keyed "hipode", its
    name in the difference's "vs")."""
    summary: dict[str, Any] = {}
    for task, task_arms in arms.items():
        summary[task] = {}
        for arm in task_arms:
            learner = arm.get("learner", "td3bc")
            # a learner's arms pair with that learner's baselines only
            task_runs = [
                {**r, "window_score": window_score(r), "curve_mean": curve_mean(r)}
                for r in runs
                if r["task"] == task and r.get("learner", "td3bc") == learner
            ]
            mine = sorted(
                (r for r in task_runs if r["arm"] == arm["name"]), key=lambda r: r["seed"]
            )
            if not mine:
                continue
            mean, std = mean_std([r["final_score"] for r in mine])
            window_mean, window_std = mean_std([r["window_score"] for r in mine])
            area_mean, area_std = mean_std([r["curve_mean"] for r in mine])
            references = {BASELINE: BASELINE, HIPODE: hipode_reference(arm, task_arms)}
            bases = {key: name for key, name in references.items() if name != arm["name"]}
            summary[task][arm.get("key", arm["name"])] = {
                "learner": learner,
                "arm": arm["name"],
                "seeds": [r["seed"] for r in mine],
                "final_scores": [r["final_score"] for r in mine],
                "mean": mean,
                "std": std,
                "window_scores": [r["window_score"] for r in mine],
                "window_mean": window_mean,
                "window_std": window_std,
                "difference": {
                    key: paired_difference(task_runs, arm["name"], base)
                    for key, base in bases.items()
                },
                "window_difference": {
                    key: paired_difference(task_runs, arm["name"], base, "window_score")
                    for key, base in bases.items()
                },
                "curve_means": [r["curve_mean"] for r in mine],
                "curve_mean": area_mean,
                "curve_std": area_std,
                "curve_difference": {
                    key: paired_difference(task_runs, arm["name"], base, "curve_mean")
                    for key, base in bases.items()
                },
            }
    return summary


def curve_plot(runs: list[dict[str, Any]], path: Path, learners: list[str]) -> bool:
    """Learning curves: mean ± std over seeds of the normalized score, one panel per task.
    False, with nothing written, when matplotlib (the `plots` extra) is not installed."""
    import io

    try:
        import matplotlib
    except ImportError:
        return False
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    tasks = list(dict.fromkeys(r["task"] for r in runs))
    fig, axes = plt.subplots(1, len(tasks), figsize=(5.5 * len(tasks), 4), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        task_runs = [r for r in runs if r["task"] == task]
        for key in dict.fromkeys(r.get("key", r["arm"]) for r in task_runs):
            curves = [r["curve"] for r in task_runs if r.get("key", r["arm"]) == key]
            length = min(len(c) for c in curves)
            scores = np.array([[point[1] for point in c[:length]] for c in curves], dtype=float)
            steps = np.array([point[0] for point in curves[0][:length]])
            mean, std = scores.mean(0), scores.std(0, ddof=1) if len(curves) > 1 else 0 * scores[0]
            ax.plot(steps, mean, marker="o", ms=3, label=f"{key} (n={len(curves)})")
            ax.fill_between(steps, mean - std, mean + std, alpha=0.2)
        ax.set(
            title=f"{learner_text(learners)} on {task}",
            xlabel="updates",
            ylabel="normalized score",
        )
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    write_bytes_atomic(path, buffer.getvalue())
    return True


def _pm(mean: float, std: float | None) -> str:
    return f"{mean:.1f} (one run)" if std is None else f"{mean:.1f} ± {std:.1f}"


def _difference_text(diff: dict[str, Any] | None) -> str:
    if diff is None:
        return ""
    if diff["std"] is None:
        return f"{diff['mean']:+.1f} (one pair)"
    return (
        f"{diff['mean']:+.1f} ± {diff['std']:.1f} (sem {diff['sem']:.1f}, n={len(diff['seeds'])})"
    )


def _reference_text(diff: dict[str, Any] | None) -> str:
    """A difference with the HIPODE arm, naming that arm where it is not the hipode arm."""
    text = _difference_text(diff)
    return text if diff is None or diff["vs"] == HIPODE else f"{text} vs {diff['vs']}"


def table_rows(report: QualityReport) -> list[list[Any]]:
    """One row per (task, arm): per-seed finals, mean ± std, paired differences."""
    rows = []
    for task, arms in report.summary.items():
        for key, arm in arms.items():
            diffs = arm["difference"]
            baseline_pair = arm.get("arm", key) in (BASELINE, HIPODE)
            rows.append(
                [
                    task,
                    key,
                    ", ".join(f"{s:.1f}" for s in arm["final_scores"]),
                    _pm(arm["mean"], arm["std"]),
                    _difference_text(diffs.get(BASELINE)),
                    "" if baseline_pair else _reference_text(diffs.get(HIPODE)),
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


def table_title(report: QualityReport) -> str:
    return f"{learner_text(report.learners)} final normalized score"


def together(machine: dict[str, Any]) -> str:
    """How many seeds of an arm one process trains as one stacked model, as the report says it."""
    per_process = machine.get("seeds_per_process")
    if per_process is None:
        return "all seeds of an arm"
    return "one seed" if per_process == 1 else f"up to {per_process} seeds of an arm"


def unplanned_text(unplanned: list[str]) -> str:
    """What the report and the console say of the folder's arms the sweep did not plan."""
    return (
        "Not in this report: the runs in this folder of arms this sweep did not plan ("
        + ", ".join(unplanned)
        + "); a sweep with the flags that plan them (--artifact-seeds, --model-rollouts, ...) "
        "and --report-only covers the folder."
    )


def markdown(report: QualityReport) -> str:
    """quality.md: command, budget, machine and load, the table, the curves."""
    budget, machine = report.budget, report.machine
    load = machine["load_during"]
    learners = learner_text(report.learners)
    names = {arm["name"] for arms in report.arms.values() for arm in arms}
    title = (
        f"Does HIPODE help {learners}? Same seeds, same budget, both arms"
        if names <= {BASELINE, HIPODE}
        else f"HIPODE ablations with {learners}: same seeds, same budget, every arm"
    )
    lines = [
        f"# {title}",
        "",
        f"Command: `{report.command}` (OMP_WAIT_POLICY=PASSIVE), started {report.started}, "
        f"{report.seconds / 60:.1f} min wall time for the runs this invocation executed "
        "(runs finished earlier are read back from their folders).",
        "",
        *([report.note, ""] if report.note else []),
        f"Budget: {budget['steps']:,} {learners} updates per run (batch 256), evaluation every "
        f"{budget['eval_every']:,} updates on {budget['eval_episodes']} episodes; seeds "
        f"{budget['seeds']} asked in every arm"
        + (
            f", and seeds {budget['earlier_seeds']} that earlier invocations finished in this "
            "folder, read back (an arm's count is the length of its 'final score per seed')"
            if budget.get("earlier_seeds")
            else ""
        )
        + ". The result of a run is its last evaluation (D4RL-normalized score), never the "
        "best one.",
        "",
        *([unplanned_text(report.unplanned_arms), ""] if report.unplanned_arms else []),
        f"Machine: {machine['platform']}, {machine['cpu_count']} cores, torch "
        f"{machine['torch']}, device {machine['device']}, engine {machine['engine']} with "
        f"{machine['workers']} parallel process(es) of {machine['threads']} torch thread(s)"
        + ("" if budget.get("report_only") else f", each training {together(machine)} together")
        + ". "
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
        "Δ: the arm minus the same learner's other arm on the same seed, mean ± std over the "
        "paired seeds (sem = std/√n). A |Δ| within about two sem is not distinguishable from "
        f"noise. The 'last {WINDOW} evals' columns average each run's last {WINDOW} evaluations "
        "instead of taking the final one alone: a robustness check against the noise of a "
        "single evaluation. "
        "'All evals' averages every evaluation of a run (the area under its learning curve): "
        "it measures how early an arm scores well, which the final score does not.",
        "",
    ]
    for task in report.summary:
        if task in PAPER_TD3BC and "td3bc" in report.learners:
            base, hipode = PAPER_TD3BC[task]
            lines.append(
                f"Paper (Table 11, D4RL v0 data): {task} TD3+BC {base} vs "
                f"HIPODE {hipode} ({hipode - base:+.1f}). Our source data is locally collected "
                "(Gymnasium v5 environments), so absolute scores are not comparable."
            )
    lines += ["", "Arms and artifacts:", ""]
    for task, arms in report.arms.items():
        for arm in arms:
            key = arm.get("key", arm["name"])
            lines.append(f"- {task} `{key}`: {arm['label']}; artifact {arm['artifact']}")
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
        if task in report.sources:
            source = report.sources[task]
            cells = [task, "source", f"{source['rows']:,}", f"{source['reward_mean']:.3f}"]
            cells += ["", "", f"{100 * source['terminal_fraction']:.2f} %", ""]
            lines.append("| " + " | ".join(cells) + " |")
        for arm in arms:
            stats = arm.get("synthetic")
            if stats is None:
                continue
            novelty = stats["novelty_mean"]
            cells = [
                task,
                arm.get("key", arm["name"]),
                f"{stats['rows']:,}",
                f"{stats['reward_mean']:.3f}",
                f"{stats['source_reward_mean_same_states']:.3f}",
                f"{stats['dynamics_error_median']:.4f}",
                f"{100 * stats['terminal_fraction']:.2f} %",
                "n/a" if novelty is None else f"{novelty:.3f}",
            ]
            lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Per run (status: trained / resumed / finished earlier):", ""]
    for run in report.runs:
        rate = run["updates_per_second"]
        lines.append(
            f"- {run['task']} {run.get('key', run['arm'])} seed {run['seed']}: "
            f"{run['final_score']:.1f} "
            f"({run['status']}; {'n/a' if not rate else f'{rate:.0f}'} updates/s)"
        )
    if "png" in report.files:
        lines += ["", f"![learning curves]({Path(report.files['png']).name})", ""]
    return "\n".join(lines) + "\n"
