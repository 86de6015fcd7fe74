"""`hipode augment`: stage one, source dataset -> five generators -> synthetic artifact."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from hipode_pipeline import console
from hipode_pipeline.augment import run_augment
from hipode_pipeline.commands.common import (
    AllowOffBandFlag,
    ConfigOption,
    DeviceOption,
    ForceFlag,
    JsonFlag,
    RootOption,
    SeedOption,
    SetOption,
    user_errors,
)
from hipode_pipeline.overrides import read_overrides


class Learner(StrEnum):
    td3bc = "td3bc"
    cql = "cql"
    iql = "iql"


class Profile(StrEnum):
    full = "full"
    paper = "paper"
    quick = "quick"


class Penalty(StrEnum):
    target = "target"
    l2 = "l2"
    contrastive = "contrastive"


class Selection(StrEnum):
    batch = "batch"
    global_ = "global"


class Candidates(StrEnum):
    model = "model"
    uniform = "uniform"


class Method(StrEnum):
    hipode = "hipode"
    model_rollouts = "model-rollouts"


@user_errors
def augment_command(
    task: Annotated[
        str, typer.Argument(help="Task, e.g. hopper-m-r (the learner's table row gives defaults).")
    ],
    learner: Annotated[
        Learner,
        typer.Option(
            help="Whose table row gives the defaults: td3bc (Table 6), cql (Table 5), "
            "iql (Table 7). The artifact serves any learner whose row agrees."
        ),
    ] = Learner.td3bc,
    source: Annotated[
        str | None,
        typer.Option(
            help="Source: Minari id or D4RL .hdf5 file (default: the task's collected dataset)."
        ),
    ] = None,
    eta: Annotated[
        float | None, typer.Option(min=0.0, help="Synthetic rate: keep round(eta*N) (table row).")
    ] = None,
    lam: Annotated[
        float | None,
        typer.Option(
            min=0.0,
            max=1.0,
            help="Selecting rate: fraction kept by dynamics consistency (table row).",
        ),
    ] = None,
    n: Annotated[
        int | None,
        typer.Option("--n", min=1, help="Candidate next states per source state (table row)."),
    ] = None,
    alpha: Annotated[
        float | None, typer.Option(help="Negative-sampling penalty weight (table row).")
    ] = None,
    sigma: Annotated[
        float | None,
        typer.Option(min=0.0, help="Negative-sampling scope, z-scored units (table row)."),
    ] = None,
    penalty: Annotated[Penalty | None, typer.Option(help="Negative-sampling penalty form.")] = None,
    selection: Annotated[
        Selection, typer.Option(help="Top-lambda per generation batch or over all.")
    ] = Selection.batch,
    candidates: Annotated[
        Candidates,
        typer.Option(
            help="Candidate next states: the state-transition model, or uniform (ablation)."
        ),
    ] = Candidates.model,
    dynamics_mean: Annotated[
        bool,
        typer.Option(
            "--dynamics-mean", help="Check against the ensemble mean, not a member's sample."
        ),
    ] = False,
    uncertainty_check: Annotated[
        bool,
        typer.Option(
            "--uncertainty-check",
            help="Rank candidates by their distance to the ensemble's mean prediction in its own "
            "predicted stds (members' variance plus disagreement).",
        ),
    ] = False,
    project_next_state: Annotated[
        bool,
        typer.Option(
            "--project-next-state",
            help="Write the ensemble's mean next state for (s, a~) instead of the state "
            "model's proposal (an ablation).",
        ),
    ] = False,
    method: Annotated[
        Method,
        typer.Option(
            help="hipode, or model-rollouts: the plain model-rollout baseline (behaviour-model "
            "action, dynamics-ensemble next state, every rollout kept) on the same generators.",
        ),
    ] = Method.hipode,
    profile: Annotated[
        Profile,
        typer.Option(
            help="Generator settings: full (the defaults), paper (the appendix's sizes and the "
            "first fixed budgets, whatever the defaults become) or quick (a few hundred steps per "
            "model, for tests: still η·N rows, so minutes on a large source)."
        ),
    ] = Profile.full,
    seed: SeedOption = 0,
    out: Annotated[
        Path | None,
        typer.Option(
            help="Artifact path (default: <root>/artifacts/<task>-eta<η>-lam<λ>-n<n>-alpha<α>-"
            "sigma<σ>[-variant]-seed<seed>.hdf5, named by its settings)."
        ),
    ] = None,
    root: RootOption = None,
    device: DeviceOption = None,
    force: ForceFlag = False,
    allow_off_band: AllowOffBandFlag = False,
    set_values: SetOption = None,
    config_file: ConfigOption = None,
    json_output: JsonFlag = False,
) -> None:
    """Train HIPODE's five generators on the source and write the synthetic dataset file."""
    summary = run_augment(
        task,
        learner=learner.value,
        source=source,
        eta=eta,
        lam=lam,
        n=n,
        alpha=alpha,
        sigma=sigma,
        penalty=penalty.value if penalty else None,
        selection=selection.value,
        candidates=candidates.value,
        dynamics_mean=dynamics_mean,
        uncertainty_check=uncertainty_check,
        project_next_state=project_next_state,
        method=method.value,
        profile=profile.value,
        seed=seed,
        out=out,
        root=root,
        force=force,
        allow_off_band=allow_off_band,
        generator_settings=read_overrides(set_values, config_file) or None,
        device=device,
        show_progress=True,
    )
    if json_output:
        console.print_json(summary.to_dict())
        return
    console.out.print(
        console.table(f"Stage one: {summary.task}", ["quantity", "value"], summary.rows())
    )


def register(app: typer.Typer) -> None:
    """Add this group's commands to the root app."""
    app.command("augment")(augment_command)
