"""`hipode collect`."""

from __future__ import annotations

from typing import Annotated

import typer

from hipode_pipeline import console
from hipode_pipeline.commands.common import ForceFlag, JsonFlag, RootOption, SeedOption, user_errors
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
    json_output: JsonFlag = False,
) -> None:
    """Build a D4RL-style MuJoCo dataset here as the Minari dataset local/<env>/<kind>-v0.

    Behaviour policies are trained once per (env, seed) with PPO and reused; an interrupted
    collection resumes. --force rebuilds the dataset from the cached policies.
    """
    result = collect(
        get_task(task),
        root=root,
        seed=seed,
        profile=profile,
        force=force,
        show_progress=not json_output,
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
            f"{result.seconds:,.1f} s",
        ]
        for dataset_id in result.dataset_ids
    ]
    columns = ["dataset", "transitions", "episodes", "behaviour return", "normalized", "wall time"]
    console.out.print(console.table("Collected", columns, rows))


def register(app: typer.Typer) -> None:
    """Add this group's commands to the root app."""
    app.command("collect")(collect_command)
