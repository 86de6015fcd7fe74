"""`hipode validate`, `hipode inspect`, `hipode export`, `hipode import`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.text import Text

from hipode_pipeline import console
from hipode_pipeline.commands.common import (
    ForceFlag,
    JsonFlag,
    RootOption,
    output_file,
    user_errors,
)

FileArgument = Annotated[Path, typer.Argument(help="An artifact .hdf5 file.")]


@user_errors
def validate_command(file: FileArgument, json_output: JsonFlag = False) -> None:
    """Check FILE against the artifact schema; list every violation. Exit 0 if valid, else 1."""
    from hipode_pipeline.validation import validate_artifact

    report = validate_artifact(file)
    if json_output:
        console.print_json(report.to_dict())
    elif report.violations:
        rows = [[v.severity, v.field, v.expected, v.found] for v in report.violations]
        title = f"{'Valid' if report.valid else 'Invalid'}: {file}"
        console.out.print(console.table(title, ["severity", "field", "expected", "found"], rows))
    if not json_output:
        errors = len(report.errors)
        verdict = ("valid", "green") if report.valid else ("invalid", "red")
        count = "" if report.valid else f" ({errors} error(s))"
        line = Text.assemble(console.plain(f"{file}: "), verdict, count)
        console.err.print(line, highlight=False)
    if not report.valid:
        raise typer.Exit(code=1)


@user_errors
def inspect_command(file: FileArgument, json_output: JsonFlag = False) -> None:
    """Verify FILE, then show its manifest highlights and per-dataset statistics.

    The table cuts long values; --json keeps the manifest's values whole (it is one file's
    record, asked for on purpose)."""
    from hipode_pipeline.artifact import inspect_artifact

    summary = inspect_artifact(file)
    if json_output:
        console.print_json(summary)
        return
    manifest_rows = [[key, value] for key, value in summary["manifest"].items()]
    manifest_rows += [[f"fraction.{k}", v] for k, v in summary["fractions"].items()]
    manifest_rows.append(["file_sha256", summary["file_sha256"]])
    console.out.print(console.table(f"Artifact {file}", ["field", "value"], manifest_rows))
    stat_columns = ["shape", "dtype", "mean", "std", "min", "max"]
    rows = [
        [name, "×".join(map(str, s["shape"])), *(s[c] for c in stat_columns[1:])]
        for name, s in summary["statistics"].items()
    ]
    console.out.print(console.table("Datasets", ["dataset", *stat_columns], rows))


@user_errors
def export_command(
    artifact: FileArgument,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", help="Where to write the copy (not with --minari).", callback=output_file
        ),
    ] = None,
    d4rl: Annotated[
        bool,
        typer.Option("--d4rl", help="Write source ⊕ synthetic as one D4RL-format HDF5 file."),
    ] = False,
    minari_id: Annotated[
        str | None,
        typer.Option(
            "--minari",
            help="Write source ⊕ synthetic as Minari dataset ID under --root "
            "(synthetic rows as one-step episodes, flagged).",
            show_default=False,
        ),
    ] = None,
    source: Annotated[
        str | None,
        typer.Option(
            "--source", help="With --d4rl or --minari: the source (task, Minari id or .hdf5)."
        ),
    ] = None,
    root: RootOption = None,
    force: ForceFlag = False,
    json_output: JsonFlag = False,
) -> None:
    """Copy a validated ARTIFACT to --out with a .sha256 sidecar (or, with --d4rl or --minari,
    write it merged with its source)."""
    from hipode_pipeline.sharing import export_artifact, export_d4rl, export_minari

    merged = d4rl or minari_id is not None
    if d4rl and minari_id is not None:
        raise typer.BadParameter("choose one of --d4rl and --minari", param_hint="--minari")
    if merged and source is None:
        raise typer.BadParameter(
            "--d4rl and --minari need the dataset the artifact was built from",
            param_hint="--source",
        )
    if source is not None and not merged:
        raise typer.BadParameter("is used only with --d4rl or --minari", param_hint="--source")
    if minari_id is not None and out is not None:
        raise typer.BadParameter(
            "is not used with --minari (it writes under --root)", param_hint="--out"
        )
    if minari_id is None and out is None:
        raise typer.BadParameter("is needed: where to write the copy", param_hint="--out")
    if minari_id is not None:
        summary = export_minari(artifact, source, minari_id, root=root, force=force)
    elif d4rl:
        summary = export_d4rl(artifact, source, out, root=root, force=force)
    else:
        summary = export_artifact(artifact, out, force=force)
    _print_summary("Exported", summary, json_output)


@user_errors
def import_command(
    file: FileArgument,
    root: RootOption = None,
    force: ForceFlag = False,
    json_output: JsonFlag = False,
) -> None:
    """Validate FILE (schema, checksum, FILE.sha256 if any); copy it into <root>/artifacts/."""
    from hipode_pipeline.sharing import import_artifact

    summary = import_artifact(file, root=root, force=force)
    for warning in summary["warnings"]:
        found = console.shorten(warning["found"])
        line = f"warning: {warning['field']}: expected {warning['expected']}, found {found}"
        console.err.print(console.plain(line), highlight=False, soft_wrap=True)
    _print_summary("Imported", summary, json_output)


def _print_summary(title: str, summary: dict, json_output: bool) -> None:
    if json_output:
        console.print_json(summary)
        return
    rows = [[k, v] for k, v in summary.items() if k != "warnings"]
    console.out.print(console.table(title, ["field", "value"], rows))


def register(app: typer.Typer) -> None:
    """Add this group's commands to the root app."""
    app.command("validate")(validate_command)
    app.command("inspect")(inspect_command)
    app.command("export")(export_command)
    app.command("import")(import_command)
