"""`hipode report`: finished runs aggregated across seeds (IQM, means, bootstrap CIs, curves)."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Annotated, Any

import typer

from hipode_pipeline import console
from hipode_pipeline.commands.common import ForceFlag, JsonFlag, output_folder, user_errors
from hipode_pipeline.errors import OverwriteError
from hipode_pipeline.machine import utc_now
from hipode_pipeline.report import (
    OUTPUTS,
    across_task_rows,
    build_report,
    comparison_rows,
    find_runs,
    parse_by,
    parse_compare,
    table_rows,
    write_report,
)
from hipode_pipeline.versions import package_versions

PROGRAM = ("hipode", "report")  # how the report names its command, wherever it was run from


def command_line(ctx: typer.Context) -> str:
    """The command as run: `hipode report` and the arguments the user passed (defaults left
    out), in the command's order. Rebuilt from the parsed parameters: click keeps no raw
    arguments, and sys.argv is another program's where the app is called from Python (tests,
    bench/evidence.py)."""
    words = list(PROGRAM)
    for param in ctx.command.params:
        source = ctx.get_parameter_source(param.name)
        # typer carries its own copy of click: its enum is compared by name
        if source is None or source.name != "COMMANDLINE":
            continue
        value = ctx.params[param.name]
        values = list(value) if isinstance(value, list | tuple) else [value]
        if param.param_type_name == "argument":
            words += [str(v) for v in values]
        elif getattr(param, "is_flag", False):
            words.append(param.opts[0] if value else param.secondary_opts[0])
        else:
            words += [word for v in values for word in (param.opts[0], str(v))]
    return shlex.join(words)


def written_block(ctx: typer.Context) -> dict[str, Any]:
    """When, by which command and on which code (package versions, git commit and local edits)
    the report was written."""
    # the statistics are rliable's and scipy's: their versions belong with the numbers
    versions = package_versions(extra=("rliable", "scipy"))
    return {"utc": utc_now(), "command": command_line(ctx), "versions": versions}


@user_errors
def report_command(
    ctx: typer.Context,
    run_dirs: Annotated[
        list[Path],
        typer.Argument(help="Run folders, or folders holding them (searched for scores.json)."),
    ],
    by: Annotated[
        str, typer.Option("--by", help="Run keys that make a group (comma-separated).")
    ] = "task,learner,data",
    compare: Annotated[
        str | None,
        typer.Option(
            "--compare",
            help="KEY=VALUE of the baseline arm; every other group that agrees on the other "
            "--by keys is compared with it (e.g. data=source).",
        ),
    ] = None,
    last_k: Annotated[int, typer.Option("--last-k", help="Evaluations in the last-k mean.")] = 3,
    reps: Annotated[int, typer.Option("--reps", help="Bootstrap resamples.")] = 5000,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the bootstrap.")] = 0,
    out: Annotated[
        Path,
        typer.Option(
            "--out",
            help="Folder for report.json/.md/.csv/.tex, curves.png and differences.png.",
            callback=output_folder,
        ),
    ] = Path("report"),
    force: ForceFlag = False,
    json_output: JsonFlag = False,
) -> None:
    """Aggregate finished runs across seeds: IQM and mean with stratified bootstrap 95 % CIs
    (rliable), probability of improvement and paired differences against a baseline arm, and
    learning curves."""
    keys, baseline = parse_by(by), parse_compare(compare)
    existing = [str(out / name) for name in OUTPUTS if (out / name).exists()]
    if existing and not force:
        raise OverwriteError(f"{', '.join(existing)} already exist(s); pass --force to replace")
    runs = find_runs(run_dirs)
    report = {
        "written": written_block(ctx),
        **build_report(runs, by=keys, compare=baseline, k=last_k, reps=reps, seed=seed),
    }
    paths = write_report(report, out)
    if json_output:
        console.print_json(report)
        return
    columns, rows = table_rows(report)
    console.out.print(console.table(f"{len(runs)} runs across seeds", columns, rows))
    if report["comparisons"]:
        columns, rows = comparison_rows(report)
        console.out.print(console.table(f"against {report['compare']}", columns, rows))
    if report["across_tasks"]:
        columns, rows = across_task_rows(report)
        console.out.print(console.table("paired differences across tasks", columns, rows))
    console.err.print(
        console.plain(
            "intervals are over runs (training and stage-one seeds; bootstrap 95 % CI); wrote "
            + ", ".join(str(p) for p in paths.values())
        )
    )


def register(app: typer.Typer) -> None:
    app.command("report")(report_command)
