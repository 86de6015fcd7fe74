"""Terminal output: diagnostics and progress to stderr, results to stdout."""

from __future__ import annotations

import json
import os
import sys
import time
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    Task,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table
from rich.text import Text

# a task field: when (time.monotonic()) the task expects to finish, or None for not yet known;
# for tasks whose steps are too slow and uneven for rich's estimate (the speed over the last
# 30 s) to say anything. A deadline, so that the time left counts down between updates
ETA_FIELD = "finish_at"

# width off a terminal (logs, pipes, CI) unless $COLUMNS says otherwise
LOG_WIDTH = 160
# longest text a table cell shows; a value read from a file can be megabytes
CELL_LIMIT = 300
# longest error or warning line; long enough for a path, a field and what was expected
MESSAGE_LIMIT = 1000
# longest string a listing's JSON carries (PATH_MAX, so real paths stay whole)
JSON_LIMIT = 4096


def _console(stderr: bool) -> Console:
    console = Console(stderr=stderr)
    # rich falls back to 80 columns off a terminal, which truncates progress lines in logs
    if not console.is_terminal and "COLUMNS" not in os.environ:
        console.width = LOG_WIDTH
    return console


err = _console(stderr=True)
out = _console(stderr=False)


# seconds between two plain progress lines when stderr is not a terminal (logs, CI, nohup)
LINE_EVERY_ENV = "HIPODE_PROGRESS_EVERY"
LINE_EVERY_DEFAULT = 30.0
# set in a process that works beside others on one terminal (the sweep's stage-one builds):
# its progress comes as plain lines led by this label, since live displays would overwrite
# each other
LABEL_ENV = "HIPODE_PROGRESS_LABEL"


class LineProgress(Progress):
    """Progress for a log file: no live display, a plain line per task every `every` seconds
    and when it finishes (count, share, rate, elapsed, ETA, info)."""

    def __init__(self, *columns: Any, every: float, label: str = "", **options: Any):
        super().__init__(*columns, disable=True, **options)
        self.every = every
        self.label = label
        self._printed: dict[Any, float] = {}
        self._finished: set[Any] = set()

    def add_task(self, description: str, *args: Any, **fields: Any):
        task_id = super().add_task(description, *args, **fields)
        self._printed[task_id] = time.monotonic()
        return task_id

    def update(self, task_id, **fields: Any) -> None:
        super().update(task_id, **fields)
        self._line(task_id)

    def advance(self, task_id, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._line(task_id)

    def _line(self, task_id) -> None:
        task = self._tasks[task_id]
        now = time.monotonic()
        finished = task.total is not None and task.completed >= task.total
        if task_id in self._finished or (
            not finished and now - self._printed[task_id] < self.every
        ):
            return
        self._printed[task_id] = now
        if finished:
            self._finished.add(task_id)
        share = f" ({100 * task.completed / task.total:.0f}%)" if task.total else ""
        total = f"/{task.total:,.0f}" if task.total is not None else ""
        eta = time_remaining(task)
        parts = [
            (f"{self.label}: " if self.label else "")
            + f"{task.description}: {task.completed:,.0f}{total}{share}",
            str(task.fields.get("rate", "")),
            f"elapsed {_clock(task.elapsed or 0.0)}",
            "" if finished or eta is None else f"ETA {_clock(eta)}",
            str(task.fields.get("info", "")),
        ]
        self.console.print(Text("  ".join(p for p in parts if p)), highlight=False, soft_wrap=True)


def time_remaining(task: Task) -> float | None:
    """Seconds left: to the task's own deadline where it gives one, else rich's estimate."""
    if ETA_FIELD not in task.fields:
        return task.time_remaining
    finish_at = task.fields[ETA_FIELD]
    return None if finish_at is None else max(0.0, finish_at - time.monotonic())


class RemainingColumn(TimeRemainingColumn):
    """rich's time-remaining column, showing the task's own estimate where it gives one."""

    max_refresh = None  # rich caches a render by its own clock; ours counts down on every one

    def render(self, task: Task) -> Text:
        if ETA_FIELD not in task.fields:
            return super().render(task)
        eta = time_remaining(task)
        return Text("-:--:--" if eta is None else _clock(eta), style="progress.remaining")


def _clock(seconds: float) -> str:
    minutes, secs = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}"


def progress(*, disable: bool = False) -> Progress:
    """A progress display with count, rate and ETA; task fields `rate` and `info` show extras,
    and `finish_at` (a time.monotonic() deadline, or None for not yet known) replaces rich's
    estimate of the time left.

    Off a terminal, or with $HIPODE_PROGRESS_LABEL set, it prints plain lines instead (every
    $HIPODE_PROGRESS_EVERY seconds, 30 by default, led by the label), since a live display
    would show nothing in a log until the end."""
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TaskProgressColumn(),
        TextColumn("[cyan]{task.fields[rate]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        RemainingColumn(),
        TextColumn("{task.fields[info]}"),
    )
    label = os.environ.get(LABEL_ENV, "")
    if not disable and (label or not err.is_terminal):
        every = float(os.environ.get(LINE_EVERY_ENV, LINE_EVERY_DEFAULT))
        return LineProgress(*columns, every=every, label=label, console=err)
    return Progress(*columns, console=err, disable=disable)


def rate_text(done: float, elapsed: float, unit: str = "steps") -> str:
    """Throughput as text for the progress bar's `rate` field."""
    return f"{done / elapsed:,.0f} {unit}/s" if elapsed > 0 else ""


def shorten(value: Any, limit: int = CELL_LIMIT) -> str:
    """`value` as one printable line: control characters escaped, and text over `limit`
    characters cut to its start, quoted, with its length: `'abc…' (10,485,760 characters)`."""
    text = value if isinstance(value, str) else str(value)
    if len(text) <= limit:
        return _printable(text)
    return f"{text[:limit] + '…'!r} ({len(text):,} characters)"


def _printable(text: str) -> str:
    # newlines and terminal escapes from a file must not break the line or drive the terminal
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def cap_strings(data: Any, limit: int = JSON_LIMIT) -> Any:
    """`data` with every string (keys too) over `limit` characters shortened; the rest kept."""
    if isinstance(data, str):
        return data if len(data) <= limit else shorten(data, limit)
    if isinstance(data, dict):
        return {cap_strings(k, limit): cap_strings(v, limit) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [cap_strings(v, limit) for v in data]
    return data


def plain(value: Any, limit: int = MESSAGE_LIMIT) -> Text:
    """A line for the terminal that rich prints as it is (no markup read from the value)."""
    return Text(shorten(value, limit))


def table(title: str, columns: list[str], rows: list[list[Any]]) -> Table:
    """Cells are shortened plain text: values read from files never parse as rich markup."""
    t = Table(title=plain(title), title_justify="left")
    for column in columns:
        t.add_column(column, overflow="fold")
    for row in rows:
        t.add_row(*(Text(_cell(v)) for v in row))
    return t


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:,.1f}" if abs(value) >= 100 else f"{value:.4g}"
    return "" if value is None else shorten(value)


def print_json(data: Any) -> None:
    """Machine-readable output on stdout, nothing else on that stream."""
    sys.stdout.write(json.dumps(data, indent=2, sort_keys=True, default=str) + "\n")
    sys.stdout.flush()
