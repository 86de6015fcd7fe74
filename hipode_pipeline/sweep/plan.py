"""What a sweep runs: its arms, its update budget, the artifact of every arm (built through stage
one when missing) and one RunSpec per (task, learner, arm, seed).

For each task and learner, the learner trains on the source alone (arm `eta0`, η = 0) and on
source ⊕ the HIPODE artifact of its table row (arm `hipode`); ablation arms add artifacts
built with another negative-sampling weight α (Table 13), uniform candidates in the data's
bounding box instead of the state-transition model (Table 12), another selecting rate λ or
value-penalty form, another stage-one seed, or train on the union sampled uniformly instead of
η·B synthetic rows per batch.

The runs of one (task, learner, arm) that differ only in their training seed form units, each
trained in one process as one stacked model (`run_units`).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hipode_pipeline import console
from hipode_pipeline.data.transitions import SourceInfo, Transitions
from hipode_pipeline.errors import DatasetNotFoundError, HipodeError, OverwriteError, SettingError
from hipode_pipeline.sweep.worker import RunSpec, run_folder, unit_key
from hipode_pipeline.tasks import LEARNERS, Task, get_task

DEFAULT_TASKS = ("hopper-m-r", "walker2d-m-r", "halfcheetah-m-r")
BASELINE, HIPODE = "eta0", "hipode"
ENGINES = ("local", "ray")
BUDGETS = ("cpu", "paper")
LEARNER_NAMES = {"td3bc": "TD3+BC", "iql": "IQL", "cql": "CQL"}


def artifact_seed_arm(seed: int) -> str:
    """The HIPODE arm built with stage-one seed `seed`, other than the hipode arm's own."""
    return f"artifact-seed{seed}"


@dataclass(frozen=True)
class Arm:
    """One way of training a learner on a task."""

    name: str  # folder and label: eta0, hipode, alpha-1, uniform, lam1, ...
    data: str  # "source" (η = 0) or "merged"
    augment: dict[str, Any] | None = None  # run_augment overrides; None: the table's artifact
    label: str = ""  # what the arm is, for the table (the learner's name goes before it)
    mixing: str = "mixed"  # batch composition: mixed (η·B synthetic per batch) | union


@dataclass
class SweepConfig:
    """What one sweep runs and where it writes."""

    tasks: list[str] = field(default_factory=lambda: list(DEFAULT_TASKS))  # task names
    learners: list[str] = field(default_factory=lambda: ["td3bc"])  # each with its table row
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
    # baseline: plain model rollouts (behaviour-model action, ensemble next state) on the same
    # generators and η, at the artifact seed and at every --artifact-seeds seed
    model_rollouts: bool = False
    artifact_seeds: list[int] = field(default_factory=list)  # control: the hipode arm's
    # settings with artifacts of other stage-one seeds (how much one artifact differs from another)
    baseline_arms: bool = True  # run the eta0 and hipode arms (off: ablation arms only)
    source: str | None = None  # source dataset for a single task; None: its collected dataset
    artifact: Path | None = None  # the hipode arm's artifact for a single task and learner
    profile: str = "full"  # generator profile for artifacts the sweep builds
    artifact_seed: int = 0  # seed of artifacts the sweep builds (one per task and arm)
    engine: str = "local"  # local | ray
    address: str | None = None  # Ray cluster address; None: start a local Ray
    workers: int = 1  # parallel units (local processes, or the local Ray's CPUs)
    threads: int = 1  # torch threads per unit (its seeds share them)
    seeds_per_process: int | None = None  # seeds trained together per unit; None: all of them
    allow_off_band: bool = False  # use sources whose behaviour policy missed its band
    device: str | None = None  # torch device; None: CUDA when present
    out: Path = Path("runs") / "sweep"  # run folders and ablation artifacts
    results: Path | None = None  # quality.md / .json / .png; None: <out>/report
    root: Path | None = None  # dataset root; None: $MINARI_DATASETS_PATH, else ./datasets
    force: bool = False  # train every run again
    show_progress: bool = True  # the bar over runs
    report_only: bool = False  # train nothing: report the runs already finished at this budget
    note: str = ""  # free text for the report, e.g. how runs read back were trained
    program: str = "hipode sweep"  # the command the report says reproduces the sweep


def learner_text(learners: list[str]) -> str:
    """The learners as the report names them: TD3+BC, IQL / CQL."""
    return " / ".join(LEARNER_NAMES.get(learner, learner) for learner in learners)


def arm_key(learner: str, arm: str, learners: list[str]) -> str:
    """An arm's row in the report: its name, prefixed with the learner when several are swept."""
    return arm if len(learners) == 1 else f"{learner}/{arm}"


def check_learners(learners: list[str]) -> None:
    """Learners with a table row in the paper, each once."""
    unknown = [learner for learner in learners if learner not in LEARNERS]
    if not learners or unknown or len(set(learners)) != len(learners):
        raise SettingError(
            f"--learners: expected distinct learners from {LEARNERS} (each uses its own table "
            f"row's artifact and η), found {learners}"
        )


def arm_name(kind: str, value: float) -> str:
    return f"{kind}{value:g}"


def arms_for(config: SweepConfig) -> list[Arm]:
    """The baseline pair, then one arm per ablation setting."""
    arms = []
    if config.baseline_arms:
        arms += [
            Arm(BASELINE, "source", None, "η = 0 (source only)"),
            Arm(HIPODE, "merged", None, "HIPODE at its table's η, λ, α"),
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
        Arm(artifact_seed_arm(seed), "merged", {"seed": seed}, f"HIPODE, stage-one seed {seed}")
        for seed in config.artifact_seeds
    ]
    if config.model_rollouts:
        rollouts = {"method": "model-rollouts"}
        label = "plain model rollouts (MB), same models and η"
        arms.append(Arm("model-rollouts", "merged", rollouts, label))
        arms += [
            Arm(
                f"model-rollouts-seed{seed}",
                "merged",
                {**rollouts, "seed": seed},
                f"{label}, stage-one seed {seed}",
            )
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


def resolve_budget(config: SweepConfig) -> tuple[int, int, int, str]:
    """steps, eval_every, eval_episodes and the budget's name, from train.toml unless given.
    Every learner of the sweep gets the first learner's budget: one budget, one table."""
    from hipode_pipeline.device import select_device
    from hipode_pipeline.train import train_settings

    check_learners(config.learners)
    settings = train_settings()
    budget = config.budget or ("paper" if select_device(config.device).type == "cuda" else "cpu")
    if budget not in BUDGETS:
        raise SettingError(f"--budget: expected one of {BUDGETS}, found {budget!r}")
    row = settings[config.learners[0]]
    # 0 is a value the user typed, not "unset": it is refused below, never replaced
    default_steps = row["steps"] if budget == "paper" else row["cpu_steps"]
    steps = default_steps if config.steps is None else config.steps
    eval_every = row["eval_every"] if config.eval_every is None else config.eval_every
    eval_episodes = (
        settings["run"]["eval_episodes"] if config.eval_episodes is None else config.eval_episodes
    )
    if min(steps, eval_every, eval_episodes) < 1:
        raise SettingError("--steps, --eval-every, --eval-episodes: expected positive integers")
    if steps % eval_every:
        raise SettingError(
            f"--eval-every: expected a divisor of --steps ({steps}) so every run is evaluated "
            f"on the same grid, found {eval_every}"
        )
    return steps, eval_every, eval_episodes, budget


def own_source(task: Task, source: str | None) -> bool:
    """Whether `source` is the task's own collected dataset (None names it too)."""
    return source is None or source in (task.name, task.local_dataset_id)


def ensure_source(
    task: Task, source: str | None, root: Path, show_progress: bool, allow_off_band: bool = False
) -> tuple[Transitions, SourceInfo]:
    """The task's source, collected first if it is the task's own and missing (an explicit
    --source must exist); an off-band source is refused unless `allow_off_band`."""
    from hipode_pipeline.data.bands import check_source_band
    from hipode_pipeline.data.load import load_source

    try:
        loaded = load_source(source or task.name, root)
        check_source_band(loaded[1].metadata, str(loaded[1].id), allow_off_band=allow_off_band)
        return loaded
    except DatasetNotFoundError:
        if not own_source(task, source):
            raise
    from hipode_pipeline.data.collect import collect

    console.err.print(
        f"[yellow]{task.name}: source {task.local_dataset_id} is missing under {root}; "
        "collecting it first (hipode collect), this takes a while once[/]"
    )
    collect(task, root=root, show_progress=show_progress, allow_off_band=allow_off_band)
    return load_source(source or task.name, root)


def table_artifact_path(
    task: Task, learner: str, config: SweepConfig, root: Path, info: SourceInfo
) -> Path:
    """Where stage one writes the learner's table-row artifact for this sweep's profile, seed
    and source (what `hipode augment` names it by default)."""
    from hipode_pipeline.contract import ArtifactSettings, default_artifact_path, table_settings

    settings = ArtifactSettings(
        **{**table_settings(task, learner).to_dict(), "profile": config.profile}
    )
    return default_artifact_path(
        task,
        settings,
        seed=config.artifact_seed,
        root=root,
        source_tag=None if own_source(task, config.source) else info.sha256[:8],
    )


def prepare_artifact(
    task: Task, learner: str, arm: Arm, config: SweepConfig, root: Path, info: SourceInfo
) -> Path | None:
    """The arm's artifact, built through stage one if missing (said on stderr); None for η = 0.

    The hipode arm uses --artifact or the learner's table-row artifact under the dataset root;
    an ablation arm whose setting equals the table's value shares it; other ablation arms get
    their own file under <out>/<task>/<arm>/ (an existing one built from the same request is
    kept, one built from another is refused)."""
    from hipode_pipeline.augment import run_augment
    from hipode_pipeline.models.generators import GeneratorConfig

    if arm.data == "source":
        return None
    params = task.augment_params(learner)
    defaults = {
        "alpha": params.alpha,
        "lam": params.lam,
        "candidates": "model",
        "penalty": GeneratorConfig.__dataclass_fields__["penalty"].default,
        "seed": config.artifact_seed,
        "method": "hipode",
    }
    overrides = {"seed": config.artifact_seed, **(arm.augment or {})}
    out: Path | None
    table_row = all(defaults[key] == value for key, value in overrides.items())
    name = "artifact.hdf5" if learner == "td3bc" else f"artifact-{learner}.hdf5"
    expected = (
        config.artifact or table_artifact_path(task, learner, config, root, info)
        if table_row
        else config.out / task.name / arm.name / name
    )
    if config.report_only and not expected.is_file():
        # reporting trains nothing, stage one included
        console.err.print(
            f"[yellow]{task.name} {arm.name}: no artifact at {expected}; not built for "
            "--report-only (its runs are read with the checksum they record; no synthetic-data "
            "row)[/]"
        )
        return expected
    if table_row:
        path = expected
        if arm.augment:
            console.err.print(f"{task.name} {arm.name}: the table's setting; shares {path}")
        if config.artifact is not None and path.is_file():
            return path  # a given artifact is used as given
        if not path.is_file():
            console.err.print(
                f"[yellow]{task.name}: no HIPODE artifact at {path}; building it (stage one, "
                f"{learner}'s table row, profile {config.profile}, seed {config.artifact_seed})[/]"
            )
        out = config.artifact  # None: stage one's own name for the table-row artifact
    else:
        out = expected
        if not out.is_file():
            console.err.print(
                f"[yellow]{task.name} {arm.name}: building its artifact at {out} (stage one: "
                f"generators are trained unless cached for these settings)[/]"
            )
        out.parent.mkdir(parents=True, exist_ok=True)
    try:
        summary = run_augment(
            task.name,
            learner=learner,
            source=config.source,
            profile=config.profile,
            out=out,
            root=root,
            device=config.device,
            show_progress=config.show_progress,
            allow_off_band=config.allow_off_band,
            **overrides,
        )
    except OverwriteError as error:
        # the sweep never replaces an artifact; the user decides what happens to the old one
        raise OverwriteError(
            f"{task.name} {arm.name}: {error} (for the sweep: remove that file and it is "
            "rebuilt, or pass another --out)"
        ) from None
    return Path(summary.artifact)


def stage_one_seed(arm: Arm, config: SweepConfig) -> int:
    """The stage-one seed of an arm's artifact (its generators are trained with it)."""
    return (arm.augment or {}).get("seed", config.artifact_seed)


def prepare_artifacts(
    task: Task, arms: list[Arm], config: SweepConfig, root: Path, info: SourceInfo
) -> dict[tuple[str, str], Path | None]:
    """Every (learner, arm)'s artifact (`prepare_artifact`), None for η = 0.

    Artifacts of one stage-one seed are built in order in one process: they share that seed's
    cached generators. With --workers above 1, the seeds are built side by side, one spawned
    process each (up to --workers), their progress as plain lines led by the seed."""
    paths: dict[tuple[str, str], Path | None] = {}
    groups: dict[int, list[tuple[str, Arm]]] = {}
    for learner in config.learners:
        for arm in arms:
            paths[learner, arm.name] = None
            if arm.data != "source":
                groups.setdefault(stage_one_seed(arm, config), []).append((learner, arm))
    seeds = sorted(groups)
    processes = min(config.workers, len(seeds))
    if processes <= 1 or config.report_only:
        built = [prepare_group(task.name, groups[seed], config, root, info) for seed in seeds]
    else:
        from multiprocessing import get_context

        console.err.print(
            f"{task.name}: building the artifacts of stage-one seeds {seeds} in "
            f"{processes} processes"
        )
        jobs = [
            (task.name, groups[seed], config, root, info, f"{task.name} stage-one seed {seed}")
            for seed in seeds
        ]
        with get_context("spawn").Pool(processes, maxtasksperchild=1) as pool:
            built = pool.starmap(prepare_group, jobs, chunksize=1)
    for group in built:
        paths.update(group)
    return paths


def prepare_group(
    task_name: str,
    group: list[tuple[str, Arm]],
    config: SweepConfig,
    root: Path,
    info: SourceInfo,
    label: str | None = None,
) -> dict[tuple[str, str], Path | None]:
    """One stage-one seed's artifacts, in order; `label` leads the progress lines of a worker
    process building beside others."""
    import os

    if label is not None:
        os.environ[console.LABEL_ENV] = label
    task = get_task(task_name)
    return {
        (learner, arm.name): prepare_artifact(task, learner, arm, config, root, info)
        for learner, arm in group
    }


def recorded_checksum(
    config: SweepConfig, task_name: str, learner: str, arm_name: str, artifact: Path
) -> str | None:
    """The artifact checksum that an arm's run folders record, for an artifact not on this
    machine (None without any); runs that name different artifacts are refused."""
    from hipode_pipeline.run_folder import read_run_json

    found = {}
    for seed in config.seeds:
        run_config = run_folder(config.out, task_name, arm_name, learner, seed) / "config.json"
        if run_config.is_file():
            found[seed] = read_run_json(run_config).get("artifact_checksum")
    if len(set(found.values())) > 1:
        raise HipodeError(
            f"{config.out / task_name / arm_name}: field 'artifact_checksum': expected one "
            f"artifact for every seed of the arm (its artifact {artifact} is not here to "
            f"decide), found {found}"
        )
    return next(iter(found.values()), None)


# synthetic-data rows of a sweep's report: task -> artifact checksum -> row
SyntheticRows = dict[str, dict[str, dict[str, Any]]]


def results_dir(config: SweepConfig) -> Path:
    """Where the report goes: --results, else <out>/report."""
    return config.results if config.results is not None else config.out / "report"


def previous_synthetic(config: SweepConfig) -> SyntheticRows:
    """The previous report's synthetic-data rows per task and artifact checksum: its arms' rows
    and those it kept from earlier reports. For an artifact not on this machine it is the row
    of the very artifact its runs record."""
    try:
        report = json.loads((results_dir(config) / "quality.json").read_text())
        kept, arms = report.get("synthetic_seen", {}), report["arms"]
        return {
            task: by_checksum(
                [
                    *kept.get(task, {}).values(),
                    *(a["synthetic"] for a in arms.get(task, []) if a.get("synthetic")),
                ]
            )
            for task in {*kept, *arms}
        }
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}  # no or another old report only costs the rows


def by_checksum(rows: Iterable[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Synthetic-data rows by their artifact's checksum (a later row of one artifact wins)."""
    return {row["checksum"]: row for row in rows if row.get("checksum")}


def synthetic_seen(previous: SyntheticRows, arms: dict[str, list[dict]]) -> SyntheticRows:
    """The previous report's rows with this sweep's on top, per task and checksum: a sweep over
    fewer arms or tasks keeps the others' rows for a later --report-only."""
    seen = {task: dict(rows) for task, rows in previous.items()}
    for task_name, task_arms in arms.items():
        current = by_checksum(a["synthetic"] for a in task_arms if a["synthetic"])
        seen.setdefault(task_name, {}).update(current)
    return {task: dict(sorted(rows.items())) for task, rows in sorted(seen.items())}


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


def source_stats(source: tuple[Transitions, SourceInfo]) -> dict[str, Any]:
    """The source beside its arms' synthetic rows: its checksum, size, mean reward and
    terminal share."""
    transitions, info = source
    return {
        "sha256": info.sha256,
        "rows": len(transitions.rewards),
        "reward_mean": float(transitions.rewards.mean()),
        "terminal_fraction": float(transitions.terminals.mean()),
    }


def run_specs(
    config: SweepConfig,
    root: Path,
    previous: SyntheticRows,
    display: Callable[[Path], str | None] = str,
) -> tuple[list[RunSpec], dict[str, list[dict]], dict[str, dict[str, Any]]]:
    """Every (task, learner, arm, seed) run, seeds interleaved so paired runs finish close
    together, each task's arms as the report describes them and each task's source
    (`source_stats`); `display` shows a path, `previous` holds the last report's
    synthetic-data rows, for artifacts this machine lacks."""
    if (config.source or config.artifact) and len(config.tasks) != 1:
        raise SettingError("--source/--artifact: expected exactly one task in --tasks")
    if config.artifact and len(config.learners) != 1:
        raise SettingError("--artifact: expected exactly one learner in --learners")
    steps, eval_every, eval_episodes, _ = resolve_budget(config)
    arms = arms_for(config)
    specs, described, sources = [], {}, {}
    for task_name in config.tasks:
        task = get_task(task_name)
        source = ensure_source(
            task, config.source, root, config.show_progress, config.allow_off_band
        )
        sources[task.name] = source_stats(source)
        described[task.name] = []
        paths = prepare_artifacts(task, arms, config, root, source[1])
        # arms that share an artifact (the table's setting) read it once
        stats = {
            path: synthetic_stats(path, source)
            for path in set(paths.values())
            if path is not None and path.is_file()
        }
        # --report-only leaves a missing artifact unbuilt: its runs name the one they trained on
        checksums = {
            key: stats[path]["checksum"]
            if path in stats
            else recorded_checksum(config, task.name, *key, path)
            for key, path in paths.items()
            if path is not None
        }
        # artifacts this machine lacks (--report-only) keep the rows the last report had
        reported = previous.get(task.name, {})
        for learner in config.learners:
            for arm in arms:
                artifact = paths[learner, arm.name]
                described[task.name].append(
                    {
                        **asdict(arm),
                        "label": f"{LEARNER_NAMES.get(learner, learner)}: {arm.label}",
                        "learner": learner,
                        "key": arm_key(learner, arm.name, config.learners),
                        "artifact": None if artifact is None else display(artifact),
                        "stage_one_seed": None if artifact is None else stage_one_seed(arm, config),
                        "synthetic": stats.get(artifact)
                        or reported.get(checksums.get((learner, arm.name))),
                    }
                )
        for seed in config.seeds:
            for learner in config.learners:
                eta = task.augment_params(learner).eta
                for arm in arms:
                    artifact = paths[learner, arm.name]
                    specs.append(
                        RunSpec(
                            task=task.name,
                            arm=arm.name,
                            data=arm.data,
                            eta=0.0 if arm.data == "source" else eta,
                            seed=seed,
                            steps=steps,
                            eval_every=eval_every,
                            eval_episodes=eval_episodes,
                            out_dir=str(config.out.resolve()),
                            root=str(root),
                            source=config.source,
                            artifact=None if artifact is None else str(artifact.resolve()),
                            artifact_checksum=checksums.get((learner, arm.name)),
                            device=config.device,
                            threads=config.threads,
                            force=config.force,
                            mixing=arm.mixing,
                            learner=learner,
                            allow_off_band=config.allow_off_band,
                        )
                    )
    return specs, described, sources


def check_seeds_per_process(value: int | None) -> None:
    """None (all seeds of an arm in one unit) or a count train_seeds accepts."""
    from hipode_pipeline.train import MAX_SEEDS

    if value is not None and (isinstance(value, bool) or not 1 <= value <= MAX_SEEDS):
        raise SettingError(
            f"--seeds-per-process: expected an integer in [1, {MAX_SEEDS}] (1: one process per "
            f"run; default: all seeds of an arm together), found {value!r}"
        )


def run_units(specs: list[RunSpec], seeds_per_process: int | None = None) -> list[list[RunSpec]]:
    """The runs grouped into units: runs that differ only in their seed, at most
    `seeds_per_process` of them per unit (None: all, up to train_seeds' limit). Units keep the
    plan's order: the first seeds of every arm before the next ones, so paired runs finish close
    together."""
    from hipode_pipeline.train import MAX_SEEDS

    check_seeds_per_process(seeds_per_process)
    size = seeds_per_process or MAX_SEEDS
    by_unit: dict[RunSpec, list[RunSpec]] = {}
    for spec in specs:
        by_unit.setdefault(unit_key(spec), []).append(spec)
    chunks = [
        (start // size, order, runs[start : start + size])
        for order, runs in enumerate(by_unit.values())
        for start in range(0, len(runs), size)
    ]
    return [runs for _, _, runs in sorted(chunks, key=lambda chunk: chunk[:2])]
