"""`hipode tasks`: the task registry as a table or JSON."""

from __future__ import annotations

import typer

from hipode_pipeline import console
from hipode_pipeline.commands.common import JsonFlag, user_errors
from hipode_pipeline.tasks import all_tasks


@user_errors
def tasks_command(json_output: JsonFlag = False) -> None:
    """List the registered tasks with env ids, reference scores and TD3+BC's eta/lambda."""
    rows = [
        {
            "task": t.name,
            "long_name": t.long_name,
            "env_id": t.env_id,
            "ref_min": t.ref_min_score,
            "ref_max": t.ref_max_score,
            "eta": t.augment_params("td3bc").eta,
            "lambda": t.augment_params("td3bc").lam,
            "collect": t.collectable,
        }
        for t in all_tasks().values()
    ]
    if json_output:
        console.print_json(rows)
        return
    columns = list(rows[0])
    console.out.print(
        console.table(
            "Tasks (eta, lambda: TD3+BC, Table 6). Scores use D4RL's reference returns; "
            "locomotion data is collected here with Gymnasium v5 (hipode collect), "
            "not D4RL's files",
            columns,
            [[r[c] for c in columns] for r in rows],
        )
    )


def register(app: typer.Typer) -> None:
    app.command("tasks")(tasks_command)
