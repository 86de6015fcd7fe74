"""`hipode train`: a learner on source ⊕ synthetic, evaluated, with a score table at the end."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from hipode_pipeline import console
from hipode_pipeline.commands.common import (
    AllowOffBandFlag,
    ConfigOption,
    DeviceOption,
    EvalEpisodesOption,
    EvalEveryOption,
    ForceFlag,
    JsonFlag,
    RootOption,
    SetOption,
    output_folder,
    user_errors,
)
from hipode_pipeline.errors import SettingError
from hipode_pipeline.overrides import read_overrides


@user_errors
def train_command(
    task: Annotated[str, typer.Argument(help="Task name, e.g. hopper-m-r.")],
    learner: Annotated[
        str,
        typer.Option(
            "--learner", help="td3bc | iql | cql | d3rlpy:<AlgoName> (needs the d3rlpy extra)."
        ),
    ] = "td3bc",
    data: Annotated[
        str,
        typer.Option(
            "--data", help="merged (source + the task's synthetic artifact) or source (baseline)."
        ),
    ] = "merged",
    steps: Annotated[
        int | None,
        typer.Option(
            "--steps", help="Updates (default: stages/train.toml; shorter without a GPU)."
        ),
    ] = None,
    seed: Annotated[
        int | None,
        typer.Option("--seed", help="Seed for every random number generator (default 0)."),
    ] = None,
    seeds: Annotated[
        str | None,
        typer.Option(
            "--seeds",
            help="Several training seeds, e.g. 0-4 or 0,2,5: built-in learners train them in "
            "one process as one stacked model; each seed gets the run folder --seed writes "
            "(with --name NAME: NAME-seed<k>).",
        ),
    ] = None,
    eta: Annotated[
        float | None,
        typer.Option(
            "--eta",
            help="Synthetic fraction per batch (default: the artifact's own synthetic rate; "
            "above it each synthetic row recurs more often: warned up to 2x, refused beyond).",
        ),
    ] = None,
    mixing: Annotated[
        str,
        typer.Option("--mixing", help="mixed (eta per batch) or union (uniform over all rows)."),
    ] = "mixed",
    eval_every: EvalEveryOption = None,
    eval_episodes: EvalEpisodesOption = None,
    batch_size: Annotated[
        int | None, typer.Option("--batch-size", help="Transitions per update.")
    ] = None,
    artifact: Annotated[
        Path | None,
        typer.Option(
            "--artifact",
            help="Synthetic artifact to use as given (default: the one whose manifest matches "
            "the learner's table row, built by `hipode augment TASK --learner L`).",
        ),
    ] = None,
    artifact_seed: Annotated[
        int,
        typer.Option(
            "--artifact-seed", help="Stage-one seed of the artifact (independent of --seed)."
        ),
    ] = 0,
    source: Annotated[
        str | None,
        typer.Option(
            "--source", help="Source dataset: Minari id or D4RL .hdf5 (default: the task's)."
        ),
    ] = None,
    out: Annotated[
        Path,
        typer.Option(
            "--out",
            callback=output_folder,
            help="Runs folder; the run goes to "
            "OUT/<task>/<learner>-<data>-eta<η>-<identity>-seed<seed>/ (or OUT/<task>/<name>/).",
        ),
    ] = Path("runs"),
    name: Annotated[
        str | None,
        typer.Option("--name", help="Run folder name under OUT/<task>/ instead of the identity."),
    ] = None,
    set_values: SetOption = None,
    config_file: ConfigOption = None,
    device: DeviceOption = None,
    root: RootOption = None,
    force: ForceFlag = False,
    allow_off_band: AllowOffBandFlag = False,
    logger: Annotated[
        str,
        typer.Option(
            "--logger",
            help="Also log metrics to tensorboard (<run>/tensorboard) or wandb (offline, "
            "<run>/wandb); none: metrics.jsonl only.",
        ),
    ] = "none",
    json_output: JsonFlag = False,
) -> None:
    """Train an offline learner on the task's data, evaluate it, print its scores (resumes)."""
    from hipode_pipeline.run_folder import (
        SCORE_COLUMNS,
        SCORE_TITLE,
        score_table_rows,
        seeds_summary,
    )
    from hipode_pipeline.seeding import parse_seeds
    from hipode_pipeline.train import train_seeds

    if seeds is not None and seed is not None:
        raise SettingError("--seed and --seeds: give one of them")
    seed_list = parse_seeds(seeds) if seeds is not None else [0 if seed is None else seed]
    settings = read_overrides(set_values, config_file)
    if settings and learner.startswith("d3rlpy:"):
        raise SettingError("--set/--config: learner settings are for td3bc, iql and cql")
    results = train_seeds(
        task,
        learner,
        data,
        steps,
        seed_list,
        eval_every,
        eval_episodes,
        out,
        source=source,
        artifact=artifact,
        artifact_seed=artifact_seed,
        eta=eta,
        mixing=mixing,
        batch_size=batch_size,
        learner_settings=settings or None,
        device=device,
        root=root,
        name=name,
        force=force,
        allow_off_band=allow_off_band,
        show_progress=not json_output,
        logger=logger,
    )
    if json_output:
        dumped = [result.to_dict() for result in results]
        console.print_json(dumped[0] if seeds is None else dumped)
        return
    for result in results:
        console.err.print(f"run folder: {result.run_dir}")
    rows = [row for result in results for row in score_table_rows(result)]
    console.out.print(console.table(SCORE_TITLE, SCORE_COLUMNS, rows))
    if len(results) > 1:
        console.out.print(seeds_summary(results))


def register(app: typer.Typer) -> None:
    """Add this group's commands to the root app."""
    app.command("train")(train_command)
