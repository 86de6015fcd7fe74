"""The evidence campaign: does HIPODE help TD3+BC and IQL on the medium-replay tasks?

One sweep per task and source (`hipode sweep`: arms eta0, hipode, hipode with other stage-one
seeds, and plain model rollouts at every stage-one seed) into
bench/evidence/runs/<task>-<first 8 hex of the source's sha256>/, then one pooled report over
every committed run in bench/evidence/report/ (`hipode report --by task,learner,augmentation
--compare augmentation=none`).

The run folders' records (config.json, metrics.jsonl, scores.json) are committed; checkpoints
and artifacts are not. Sources are collected on each machine and differ between CPUs, so runs
are kept per source: a session whose rebuilt source matches continues that folder (a finished
run is kept, an unfinished one restarts), one whose source differs starts a folder of its own,
and the report pools sources as strata, each run paired with the baseline on its own source.

    python bench/evidence.py sweep hopper-m-r --seeds 0-4              # trains / resumes
    python bench/evidence.py sweep walker2d-m-r --learner iql --seeds 0-4
    python bench/evidence.py sweep hopper-m-r --learner iql --seeds 1-5 \
        --artifact-seeds "" --no-model-rollouts          # IQL's hopper budget: 500k updates
    python bench/evidence.py sweep halfcheetah-m-r --learner iql --seeds 0-2 \
        --artifact-seeds "" --no-model-rollouts          # eta0 and hipode only, seed-major
    python bench/evidence.py sweep hopper-m-r --seeds 0-4 --report-only  # its quality.md
    python bench/evidence.py report                                    # the pooled tables
    python bench/evidence.py report --by-source                        # one row per source
    python bench/evidence.py report --by-stage-one-seed                # one row per artifact
    python bench/evidence.py report --versus-rollouts      # hipode - the same models' rollouts
    python bench/evidence.py report --design    # only the sources holding an arm's full grid
    python bench/evidence.py tables            # docs/evidence.md's marked tables from them
    python bench/evidence.py sources           # which source folders this machine can extend
    python bench/evidence.py tables --check    # fails naming each table the reports contradict
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import sys
from pathlib import Path

# OpenMP reads its wait policy once, when torch loads: busy-waiting starves a shared machine
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parent.parent
RUNS = Path("bench") / "evidence" / "runs"
REPORT = Path("bench") / "evidence" / "report"
DOC = Path("docs") / "evidence.md"
# the budgets of the campaign on CPU, per learner (the issue: at least 200k updates for TD3+BC)
CPU_STEPS = {"td3bc": 200_000, "iql": 200_000}
# longer where a learner had not learned a task at its own budget (docs/evidence.md: "IQL on
# hopper-m-r at 500k updates")
TASK_STEPS = {("iql", "hopper-m-r"): 500_000}
EVAL_EVERY = 5000
EVAL_EPISODES = 10
ARTIFACT_SEEDS = "1"  # besides seed 0: the stage-one seeds of the artifact arms


def budget(learner: str, task: str) -> int | None:
    """The campaign's updates per run of `learner` on `task`; None for a learner it lacks."""
    return TASK_STEPS.get((learner, task), CPU_STEPS.get(learner))


def source_folder(task_name: str) -> Path:
    """bench/evidence/runs/<task>-<sha8> for the task's own source, collected if missing."""
    from hipode_pipeline.paths import datasets_root
    from hipode_pipeline.sweep.plan import ensure_source
    from hipode_pipeline.tasks import get_task

    print(source_note(task_name), file=sys.stderr)
    _, info = ensure_source(get_task(task_name), None, datasets_root(), show_progress=True)
    return RUNS / f"{task_name}-{info.sha256[:8]}"


def source_note(task_name: str) -> str:
    """Which committed source folders of the task were built on this machine's CPU."""
    from evidence_sources import extendable, read_sources

    from hipode_pipeline.machine import cpu_name

    return extendable(read_sources(RUNS, budget, cpu_name()), task_name)


def sources(args: argparse.Namespace) -> int:
    """The committed source folders, the CPUs their runs record and whether this one matches."""
    from evidence_sources import markdown, read_sources

    from hipode_pipeline.machine import cpu_name

    this_cpu = cpu_name()
    entries = read_sources(RUNS, budget, this_cpu)
    if args.json:
        print(json.dumps({"this_cpu": this_cpu, "sources": entries}, indent=2))
    else:
        print(markdown(entries, this_cpu), end="")
    return 0


def sweep(args: argparse.Namespace) -> list[str]:
    out = source_folder(args.task)
    steps = args.steps or budget(args.learner, args.task)
    return [
        "sweep",
        "--tasks",
        args.task,
        "--learners",
        args.learner,
        "--seeds",
        args.seeds,
        "--steps",
        str(steps),
        "--eval-every",
        str(EVAL_EVERY),
        "--eval-episodes",
        str(EVAL_EPISODES),
        *([] if args.no_model_rollouts else ["--model-rollouts"]),
        "--artifact-seeds",
        args.artifact_seeds,
        "--workers",
        str(args.workers),
        "--seeds-per-process",
        "1",
        "--out",
        str(out),
        "--results",
        str(out / "report" / args.learner),
        "--note",
        "Gymnasium v5 medium-replay data collected on this machine (not D4RL's files); "
        f"{args.learner} {steps:,} updates on CPU",
        *(["--report-only"] if args.report_only else []),
    ]


def report(args: argparse.Namespace) -> list[str]:
    by, out, baseline = "task,learner,augmentation", REPORT, "none"
    if args.versus_rollouts:
        # HIPODE against the rollouts on its own stage-one seed's dynamics ensemble (same source,
        # stage-one and training seed): what HIPODE's generation adds over model rollouts
        out, baseline = REPORT / "versus-rollouts", "model-rollouts"
    runs = [str(RUNS)]
    if args.by_stage_one_seed:
        # per artifact: a source's artifacts differ by their stage-one seed alone
        by, out = by + ",source_sha256,artifact_seed", out / "by-stage-one-seed"
    elif args.by_source:
        # per source: whether a finding holds on each dataset, not only pooled over them
        by, out = by + ",source_sha256", out / "by-source"
    elif args.design:
        # the grid only: a source stopped early leaves the pooled rows without intervals
        out, runs = out / "design", design_folders()
    return [
        "report",
        *runs,
        "--by",
        by,
        "--compare",
        f"augmentation={baseline}",
        "--out",
        str(out),
        "--force",
    ]


def design_folders() -> list[str]:
    """The committed run folders that the design reports aggregate (evidence_design)."""
    from evidence_design import design_runs

    from hipode_pipeline.report import find_runs

    return [str(run.path) for run in design_runs(find_runs([RUNS]), budget)]


def tables(args: argparse.Namespace) -> int:
    """Regenerate (or, with --check, compare) the marked tables of docs/evidence.md."""
    from evidence_tables import TableError, regenerate

    from hipode_pipeline.files import write_text_atomic

    text = DOC.read_text()
    try:
        new, changed = regenerate(text, DOC, REPORT, RUNS, budget)
    except TableError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    for where, old, new_rows in changed:
        print(f"{'differs' if args.check else 'regenerated'}: {where}")
        if args.check:
            print("\n".join(difflib.unified_diff(old, new_rows, "docs", "reports", lineterm="")))
    if args.check:
        return 1 if changed else 0
    if changed:
        write_text_atomic(DOC, new)
    print(f"{DOC}: {len(changed)} table(s) regenerated")
    return 0


def main_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("sweep", help="Train or resume one task's arms and seeds.")
    run.add_argument("task", help="e.g. hopper-m-r")
    run.add_argument("--learner", default="td3bc", choices=sorted(CPU_STEPS))
    run.add_argument("--seeds", default="0-4", help="Training seeds (0-4, 0,2,5).")
    run.add_argument("--steps", type=int, default=None, help="Updates (default: the budget).")
    run.add_argument("--artifact-seeds", default=ARTIFACT_SEEDS, help="Extra stage-one seeds.")
    run.add_argument(
        "--no-model-rollouts",
        action="store_true",
        help="Leave out the model-rollout arms (a later sweep with them keeps these runs).",
    )
    run.add_argument("--workers", type=int, default=2, help="Parallel training processes.")
    run.add_argument("--report-only", action="store_true", help="Report the finished runs.")
    pooled = commands.add_parser("report", help="The pooled report over every committed run.")
    grouping = pooled.add_mutually_exclusive_group()
    grouping.add_argument(
        "--by-source", action="store_true", help="One group per source (report/by-source/)."
    )
    grouping.add_argument(
        "--by-stage-one-seed",
        action="store_true",
        help="One group per source and artifact (report/by-stage-one-seed/).",
    )
    grouping.add_argument(
        "--design",
        action="store_true",
        help="Pooled over the sources that hold an arm's full grid (>= 5 training x 2 "
        "stage-one seeds, 5 eta0 seeds) only (report/design/).",
    )
    pooled.add_argument(
        "--versus-rollouts",
        action="store_true",
        help="Each arm against the plain model rollouts of the same stage-one seed instead of "
        "eta0 (report/versus-rollouts/, with --by-source or --by-stage-one-seed below it).",
    )
    docs = commands.add_parser("tables", help="docs/evidence.md's marked tables from the reports.")
    docs.add_argument("--check", action="store_true", help="Change nothing; fail if they differ.")
    listing = commands.add_parser(
        "sources", help="The source folders, the CPUs their runs record, and this machine's."
    )
    listing.add_argument("--json", action="store_true", help="JSON instead of a table.")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = main_parser().parse_args(argv)
    os.chdir(REPO)  # records name paths relative to the checkout
    sys.path.insert(0, str(REPO))
    if args.command == "tables":
        sys.exit(tables(args))
    if args.command == "sources":
        sys.exit(sources(args))
    from hipode_pipeline.cli import app

    app(sweep(args) if args.command == "sweep" else report(args))


if __name__ == "__main__":
    main()
