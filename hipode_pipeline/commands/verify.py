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
from hipode_pipeline.errors import OverwriteError, SettingError
from hipode_pipeline.verify import (
    DEFAULT_TOLERANCE,
    STAGE_COLUMNS,
    SUMMARY_COLUMNS,
    TABLE_COLUMNS,
    output_paths,
    stage_rows,
    summary_paths,
    summary_row,
    verify_artifact,
    write_summary,
)

ArtifactArgument = Annotated[
    list[Path],
    typer.Argument(
        help="The synthetic dataset file(s) (.hdf5); with several, also a summary table across "
        "them (verify-summary.json / .png in --out-dir, default the first file's folder)."
    ),
]
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
    files: ArtifactArgument,
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
    beside plain model rollouts, stage by stage; writes a JSON report and a novelty-vs-error PNG
    per artifact."""
    summary_dir = out_dir if out_dir is not None else Path(files[0]).parent
    # checked before any artifact is verified: nothing is half-written or written twice
    reports_of: dict[Path, Path] = {}
    for file in files:
        for path in map(Path.resolve, output_paths(Path(file), out_dir)):
            if path in reports_of:
                raise SettingError(
                    f"{reports_of[path]} and {file}: both would write {path} (the same file "
                    "name in one --out-dir); verify them with separate --out-dir"
                )
            reports_of[path] = Path(file)
    if not force:
        wanted = [*reports_of, *(summary_paths(summary_dir) if len(files) > 1 else ())]
        existing = [str(p) for p in wanted if p.exists()]
        if existing:
            raise OverwriteError(f"{', '.join(existing)} already exist(s); pass --force")
    reports = [
        verify_artifact(
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
        for file in files
    ]
    if json_output:
        data = [r.to_dict(per_transition=False) for r in reports]
        console.print_json(data[0] if len(data) == 1 else data)
    else:
        for report in reports:
            name = Path(report.artifact).name
            title = f"{report.env_id} simulator vs {name} (tolerance {report.tolerance})"
            console.out.print(console.table(title, TABLE_COLUMNS, report.rows()))
            if report.analysis is not None:
                console.out.print(
                    console.table(f"{name}: stages", STAGE_COLUMNS, stage_rows(report))
                )
            console.err.print(console.plain(f"wrote {report.json_path} and {report.png_path}"))
    if len(reports) > 1:
        json_path, png_path = write_summary(reports, summary_dir)
        if not json_output:
            rows = [summary_row(r) for r in reports]
            console.out.print(console.table("across artifacts", SUMMARY_COLUMNS, rows))
            console.err.print(console.plain(f"wrote {json_path} and {png_path}"))
