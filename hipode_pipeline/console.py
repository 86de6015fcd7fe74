"""Terminal output: diagnostics and progress to stderr, results to stdout."""

from __future__ import annotations

import json
import os
import sys
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

# width off a terminal (logs, pipes, CI) unless $COLUMNS says otherwise
LOG_WIDTH = 160


def _console(stderr: bool) -> Console:
    console = Console(stderr=stderr)
    # rich falls back to 80 columns off a terminal, which truncates progress lines in logs
    if not console.is_terminal and "COLUMNS" not in os.environ:
        console.width = LOG_WIDTH
    return console


err = _console(stderr=True)
out = _console(stderr=False)


def progress(*, disable: bool = False) -> Progress:
    """A progress display with count, rate and ETA; task fields `rate` and `info` show extras."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TaskProgressColumn(),
        TextColumn("[cyan]{task.fields[rate]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
        console=err,
        disable=disable,
    )


def rate_text(done: float, elapsed: float, unit: str = "steps") -> str:
    """Throughput as text for the progress bar's `rate` field."""
    return f"{done / elapsed:,.0f} {unit}/s" if elapsed > 0 else ""


def table(title: str, columns: list[str], rows: list[list[Any]]) -> Table:
    t = Table(title=title, title_justify="left")
    for column in columns:
        t.add_column(column, overflow="fold")
    for row in rows:
        t.add_row(*(_cell(v) for v in row))
    return t


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:,.1f}" if abs(value) >= 100 else f"{value:.4g}"
    return "" if value is None else str(value)


def print_json(data: Any) -> None:
    """Machine-readable output on stdout, nothing else on that stream."""
    sys.stdout.write(json.dumps(data, indent=2, sort_keys=True, default=str) + "\n")
    sys.stdout.flush()
