"""`hipode merge`: source ⊕ synthetic as one D4RL-layout file any library can read."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from hipode_pipeline import console
from hipode_pipeline.commands.common import (
    ForceFlag,
    JsonFlag,
    RootOption,
    output_file,
    user_errors,
)


@user_errors
def merge_command(
    source: Annotated[
        str, typer.Argument(help="Source dataset: task name, Minari id or D4RL .hdf5 file.")
    ],
    artifact: Annotated[
        Path,
        typer.Argument(help="Synthetic artifact written by `hipode augment` from that source."),
    ],
    out: Annotated[
        Path, typer.Option("--out", help="The merged .hdf5 file to write.", callback=output_file)
    ],
    root: RootOption = None,
    force: ForceFlag = False,
    json_output: JsonFlag = False,
) -> None:
    """Write SOURCE and ARTIFACT as one flat file with an is_synthetic mask and provenance."""
    from hipode_pipeline.files import output_lock
    from hipode_pipeline.merge import merge_files

    with output_lock(out, command="hipode merge"):
        summary = merge_files(source, artifact, out, root=root, force=force)
    if json_output:
        console.print_json(summary)
        return
    console.out.print(
        console.table("Merged", ["field", "value"], [[k, v] for k, v in summary.items()])
    )


def register(app: typer.Typer) -> None:
    """Add this group's commands to the root app."""
    app.command("merge")(merge_command)
