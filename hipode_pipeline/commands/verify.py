"""`hipode verify`: check synthetic transitions against the MuJoCo simulator."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from hipode_pipeline import console
from hipode_pipeline.commands.common import (
    ForceFlag,
    JsonFlag,
    RootOption,
    SeedOption,
    output_folder,
    user_errors,
)
from hipode_pipeline.verify import DEFAULT_TOLERANCE, TABLE_COLUMNS, verify_artifact

ArtifactArgument = Annotated[Path, typer.Argument(help="The synthetic dataset file (.hdf5).")]
SampleOption = Annotated[
    int, typer.Option("--sample", help="Synthetic transitions (and baseline rollouts) to check.")
]
ToleranceOption = Annotated[
    float,
    typer.Option(
        "--tolerance",
        help="Authentic when next-state error <= this (source stds per dimension) and reward "
        "error <= this many reward stds.",
    ),
]
NoBaselineFlag = Annotated[
    bool, typer.Option("--no-baseline", help="Skip the plain model-rollout baseline.")
]
OutDirOption = Annotated[
    Path | None,
    typer.Option(
        "--out-dir",
        help="Folder for the .verify.json and .verify.png (default: the artifact's folder).",
        callback=output_folder,
    ),
]


def register(app: typer.Typer) -> None:
    """Add this group's commands to the root app."""
    app.command("verify")(verify)


@user_errors
def verify(
    file: ArtifactArgument,
    sample: SampleOption = 2000,
    seed: SeedOption = 0,
    tolerance: ToleranceOption = DEFAULT_TOLERANCE,
    no_baseline: NoBaselineFlag = False,
    out_dir: OutDirOption = None,
    root: RootOption = None,
    force: ForceFlag = False,
    json_output: JsonFlag = False,
) -> None:
    """Step the simulator from sampled synthetic transitions and report how authentic they are,
    beside plain model rollouts; writes a JSON report and a novelty-vs-error PNG."""
    report = verify_artifact(
        file,
        sample=sample,
        seed=seed,
        tolerance=tolerance,
        baseline=not no_baseline,
        root=root,
        out_dir=out_dir,
        force=force,
        show_progress=not json_output,
    )
    if json_output:
        console.print_json(report.to_dict(per_transition=False))
        return
    name = Path(report.artifact).name
    title = f"{report.env_id} simulator vs {name} (tolerance {report.tolerance})"
    console.out.print(console.table(title, TABLE_COLUMNS, report.rows()))
    console.err.print(console.plain(f"wrote {report.json_path} and {report.png_path}"))
