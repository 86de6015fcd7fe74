"""`hipode sweep`: a learner with and without HIPODE (and ablation arms), same seeds, same budget.

`bench/quality.py` is the same command with the repository's own output folders as defaults.
"""

# no `from __future__ import annotations`: the options below read the factory's arguments,
# which string annotations evaluated later could not see
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer

from hipode_pipeline import console
from hipode_pipeline.commands.common import (
    AllowOffBandFlag,
    DeviceOption,
    ForceFlag,
    JsonFlag,
    RootOption,
    output_folder,
    user_errors,
)
from hipode_pipeline.errors import SettingError
from hipode_pipeline.seeding import parse_seeds
from hipode_pipeline.sweep.plan import DEFAULT_TASKS, SweepConfig

DEFAULT_OUT = SweepConfig.out
EPILOG = (
    "Runs execute in this process (--engine local --workers 1), in local worker processes "
    "(--workers N) or on Ray (--engine ray; a local Ray unless --address names a cluster, whose "
    "nodes need hipode-pipeline installed and must see --out and the dataset root at the same "
    "paths). Every run is a folder OUT/<task>/<arm>/<learner>-seed<seed>/: rerunning resumes. "
    "The seeds of an arm train together in one process as one stacked model; "
    "--seeds-per-process N splits them into processes of at most N seeds (1: one per run)."
)


def parse_list(text: str, kind: type, flag: str) -> list[Any]:
    """A comma-separated option value as a list of `kind`."""
    try:
        return [kind(item.strip()) for item in text.split(",") if item.strip()]
    except ValueError:
        raise SettingError(
            f"{flag}: expected comma-separated {kind.__name__} values, found {text!r}"
        ) from None


def sweep_command_for(
    *, program: str, out_default: Path, results_default: Path | None
) -> Callable[..., None]:
    """The sweep command with these defaults; `program` is how the report says to rerun it."""
    results_help = "Where quality.md/.json/.png go" + (
        " (default: OUT/report)." if results_default is None else "."
    )

    @user_errors
    def sweep_command(
        tasks: Annotated[str, typer.Option("--tasks", help="Comma-separated tasks.")] = ",".join(
            DEFAULT_TASKS
        ),
        learners: Annotated[
            str,
            typer.Option(
                "--learners",
                help="Comma-separated learners (td3bc, iql, cql); each trains on its own table "
                "row's artifact and η, all on the first learner's budget.",
            ),
        ] = "td3bc",
        seeds: Annotated[
            str,
            typer.Option("--seeds", help="Training seeds, every arm: 0-4, 0,2,5 or 0-2,7."),
        ] = "0,1,2",
        steps: Annotated[
            int | None, typer.Option("--steps", help="Updates per run (default: the budget's).")
        ] = None,
        budget: Annotated[
            str | None,
            typer.Option(
                "--budget",
                help="cpu (train.toml cpu_steps) or paper (train.toml steps, 1M); "
                "default: paper with CUDA, else cpu.",
            ),
        ] = None,
        eval_every: Annotated[
            int | None,
            typer.Option(
                "--eval-every",
                help="Updates between evaluations (default: the first learner's in train.toml).",
            ),
        ] = None,
        eval_episodes: Annotated[
            int | None,
            typer.Option(
                "--eval-episodes", help="Episodes per evaluation (default: train.toml's)."
            ),
        ] = None,
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
                "--uniform",
                help="Ablation: uniform candidates in the data's bounding box (Table 12).",
            ),
        ] = False,
        penalty: Annotated[
            str,
            typer.Option(
                "--penalty", help="Ablation: comma-separated penalty forms (l2,contrastive)."
            ),
        ] = "",
        union: Annotated[
            bool, typer.Option("--union", help="Ablation: sample source ∪ synthetic uniformly.")
        ] = False,
        model_rollouts: Annotated[
            bool,
            typer.Option(
                "--model-rollouts",
                help="Baseline: plain model rollouts (behaviour-model action, dynamics-ensemble "
                "next state) on the same generators and η, at every stage-one seed.",
            ),
        ] = False,
        lam: Annotated[
            str,
            typer.Option(
                "--lam", help="Ablation: comma-separated selecting rates λ, e.g. 0.2,1.0."
            ),
        ] = "",
        artifact_seed: Annotated[
            int,
            typer.Option(
                "--artifact-seed",
                help="Stage-one seed of the hipode arm's artifact and of every artifact built "
                "here.",
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
            Path | None,
            typer.Option(
                "--artifact", help="The hipode arm's artifact (one task and learner only)."
            ),
        ] = None,
        profile: Annotated[
            str, typer.Option("--profile", help="Generator profile of artifacts built here.")
        ] = "full",
        engine: Annotated[str, typer.Option("--engine", help="local or ray.")] = "local",
        address: Annotated[
            str | None,
            typer.Option(
                "--address", help="Ray cluster address (engine ray; default: a local Ray)."
            ),
        ] = None,
        workers: Annotated[
            int,
            typer.Option(
                "--workers",
                help="Parallel processes, each training an arm's seeds (see --seeds-per-process).",
            ),
        ] = 1,
        threads: Annotated[
            int, typer.Option("--threads", help="Torch threads per process (its seeds share them).")
        ] = 1,
        seeds_per_process: Annotated[
            int | None,
            typer.Option(
                "--seeds-per-process",
                help="Seeds of an arm trained together in one process as one stacked model "
                "(default: all; fewer spread an arm over more --workers; 1: one process per run).",
            ),
        ] = None,
        allow_off_band: AllowOffBandFlag = False,
        device: DeviceOption = None,
        out: Annotated[
            Path,
            typer.Option(
                "--out", callback=output_folder, help="Run folders and ablation artifacts."
            ),
        ] = out_default,
        results: Annotated[
            Path | None, typer.Option("--results", callback=output_folder, help=results_help)
        ] = results_default,
        root: RootOption = None,
        force: ForceFlag = False,
        report_only: Annotated[
            bool,
            typer.Option(
                "--report-only",
                help="Train nothing, nor build artifacts; report the finished runs.",
            ),
        ] = False,
        note: Annotated[
            str,
            typer.Option("--note", help="Text for the report (e.g. how the runs were trained)."),
        ] = "",
        as_json: JsonFlag = False,
    ) -> None:
        """Train a learner with and without HIPODE (and ablation arms) on the same seeds and
        update budget; write quality.md, quality.json and quality.png (learning curves)."""
        from hipode_pipeline.sweep.driver import run_sweep
        from hipode_pipeline.sweep.report import COLUMNS, table_rows, table_title

        config = SweepConfig(
            tasks=parse_list(tasks, str, "--tasks"),
            learners=parse_list(learners, str, "--learners"),
            seeds=parse_seeds(seeds, "--seeds"),
            steps=steps,
            budget=budget,
            eval_every=eval_every,
            eval_episodes=eval_episodes,
            alphas=parse_list(alpha, float, "--alpha"),
            uniform=uniform,
            lams=parse_list(lam, float, "--lam"),
            penalties=parse_list(penalty, str, "--penalty"),
            union=union,
            model_rollouts=model_rollouts,
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
            seeds_per_process=seeds_per_process,
            allow_off_band=allow_off_band,
            device=device,
            out=out,
            results=results,
            root=root,
            force=force,
            report_only=report_only,
            note=note,
            program=program,
        )
        report = run_sweep(config)
        if as_json:
            console.print_json(report.to_dict())
            return
        console.out.print(console.table(table_title(report), COLUMNS, table_rows(report)))
        console.err.print(f"wrote {', '.join(report.files.values())}")

    return sweep_command


def sweep_app(*, program: str, out_default: Path, results_default: Path | None) -> typer.Typer:
    """A one-command app running the sweep with these defaults (what bench/quality.py runs)."""
    app = typer.Typer(add_completion=False, pretty_exceptions_show_locals=False)
    app.command(epilog=EPILOG)(
        sweep_command_for(program=program, out_default=out_default, results_default=results_default)
    )
    return app


def register(app: typer.Typer) -> None:
    """Add this group's commands to the root app."""
    command = sweep_command_for(
        program="hipode sweep", out_default=DEFAULT_OUT, results_default=None
    )
    app.command("sweep", epilog=EPILOG)(command)
