"""`hipode datasets`: what is in the local dataset root, and one source summarized."""

from __future__ import annotations

from typing import Annotated

import typer

from hipode_pipeline import console
from hipode_pipeline.commands.common import JsonFlag, RootOption, user_errors
from hipode_pipeline.data.catalog import list_local_datasets
from hipode_pipeline.data.load import describe_source
from hipode_pipeline.paths import datasets_root

datasets_app = typer.Typer(
    help="Local source datasets and synthetic artifacts.", no_args_is_help=True
)

LIST_COLUMNS = ("id", "kind", "task", "env", "N", "episodes", "refs", "schema", "size", "note")
# Widest id kept unfolded in the table; longer ones wrap
ID_WIDTH = 48
# a task, env, schema or note read from a file: a real one is far shorter
LIST_VALUE_LIMIT = 80


@datasets_app.command("list")
@user_errors
def list_command(root: RootOption = None, json_output: JsonFlag = False) -> None:
    """List the Minari datasets, artifacts and D4RL files under the dataset root."""
    entries = list_local_datasets(root)
    if json_output:
        # values read from files are capped here too: a listing never carries megabytes
        console.print_json(console.cap_strings([entry.to_dict() for entry in entries]))
        return
    where = (root or datasets_root()).resolve()
    if not entries:
        console.err.print(
            console.plain(
                f"no datasets under {where}; "
                "`hipode collect TASK` builds one, or copy a Minari dataset there"
            )
        )
    columns = [c for c in LIST_COLUMNS if c != "note" or any(e.note for e in entries)]
    rows = [
        [
            e.id,
            e.kind,
            *(_short(v) for v in (e.task, e.env_id)),
            e.transitions,
            e.episodes,
            e.ref_scores_from or "none",
            _short(e.schema_version),
            _size_text(e.size_bytes),
            # the table shows a note's gist; --json has the detail
            _short(e.note.split(" (")[0]) if e.note else None,
        ][: len(columns)]
        for e in entries
    ]
    table = console.table(f"Datasets in {where}", columns, rows)
    # ids are what a user copies into the next command: keep them on one line
    table.columns[0].min_width = min(
        ID_WIDTH, max((len(console.shorten(e.id)) for e in entries), default=2)
    )
    console.out.print(table)


@datasets_app.command("show")
@user_errors
def show_command(
    spec: Annotated[
        str, typer.Argument(help="A task name, a local Minari id, or a D4RL-format .hdf5 file.")
    ],
    root: RootOption = None,
    json_output: JsonFlag = False,
) -> None:
    """Load one source, validate it, and print its size, dims, env, refs, episodes and sha256.

    The table cuts long values; --json keeps them whole (one source, asked for on purpose)."""
    summary = describe_source(spec, root)
    if json_output:
        console.print_json(summary)
        return
    for note in summary["notes"]:
        console.err.print(console.plain(f"note: {note}"), highlight=False, soft_wrap=True)
    rows = [[key, value] for key, value in summary.items() if key != "notes"]
    console.out.print(console.table(f"Source {summary['id']}", ["field", "value"], rows))


def _short(value: str | None) -> str | None:
    return None if value is None else console.shorten(value, LIST_VALUE_LIMIT)


def _size_text(size: int) -> str:
    """Bytes in decimal units, as `ls -h --si` and Minari's dataset_size show them."""
    if size < 1000:
        return f"{size} B"
    for unit in ("KB", "MB", "GB", "TB"):
        size /= 1000
        if size < 1000 or unit == "TB":
            return f"{size:.1f} {unit}"


def register(app: typer.Typer) -> None:
    """Add this group's commands to the root app."""
    app.add_typer(datasets_app, name="datasets")
