"""`hipode collect`."""

from __future__ import annotations

from typing import Annotated

import typer

from hipode_pipeline import console
from hipode_pipeline.commands.common import (
    AllowOffBandFlag,
    ForceFlag,
    JsonFlag,
    RootOption,
    SeedOption,
    user_errors,
)
from hipode_pipeline.data.collect import collect
from hipode_pipeline.tasks import get_task

ProfileOption = Annotated[
    str,
    typer.Option(
        "--profile",
        help="Recipe profile from stages/collect.toml: full (the real one) or quick (tests).",
    ),
]


@user_errors
def collect_command(
    task: Annotated[
        str, typer.Argument(help="Task to build, e.g. hopper-m-r or hopper-medium-replay.")
    ],
    seed: SeedOption = 0,
    root: RootOption = None,
    profile: ProfileOption = "full",
    force: ForceFlag = False,
    allow_off_band: AllowOffBandFlag = False,
    json_output: JsonFlag = False,
) -> None:
    """Build a D4RL-style MuJoCo dataset here as the Minari dataset local/<env>/<kind>-v0.

    Behaviour policies are trained once per (env, seed) with the env's trainer (PPO, or SAC
    for HalfCheetah; stages/collect.toml) and reused; an interrupted collection resumes, and an
    off-band one goes on training when its budget was raised. --force rebuilds the dataset
    from the cached policies. These are Gymnasium v5 datasets built here, scored with D4RL's
    reference returns, not D4RL's own files.
    """
    result = collect(
        get_task(task),
        root=root,
        seed=seed,
        profile=profile,
        force=force,
        show_progress=not json_output,
        allow_off_band=allow_off_band,
    )
    if json_output:
        console.print_json(result.to_dict())
        return
    if result.reused:
        console.err.print(
            console.plain(
                f"{result.dataset_ids[0]} already exists at {result.path}; --force rebuilds it"
            )
        )
    policies = sorted(result.policy_returns)
    rows = [
        [
            dataset_id,
            result.transitions,
            result.episodes,
            ", ".join(f"{p} {result.policy_returns[p]:,.1f}" for p in policies) or "random",
            ", ".join(f"{result.normalized_scores[p]:.1f}" for p in policies) or "",
            band_text(result.band),
            f"{result.seconds:,.1f} s",
        ]
        for dataset_id in result.dataset_ids
    ]
    columns = [
        "dataset",
        "transitions",
        "episodes",
        "behaviour return",
        "normalized",
        "band",
        "wall time",
    ]
    console.out.print(console.table("Collected", columns, rows))


def band_text(band: dict | None) -> str:
    """'in [45, 55]', 'OFF [38, 46]' or 'none recorded'."""
    if not band or band["in_band"] is None:
        return "none recorded"
    parts = [
        f"{'in' if policy['in_band'] else 'OFF'} [{policy['band'][0]:g}, {policy['band'][1]:g}]"
        for policy in band["policies"].values()
        if policy["band"] is not None
    ]
    return ", ".join(parts)


def register(app: typer.Typer) -> None:
    """Add this group's commands to the root app."""
    app.command("collect")(collect_command)
