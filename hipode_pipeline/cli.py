"""The `hipode` command line: thin typer commands that parse, call one library function, print."""

from __future__ import annotations

import typer

from hipode_pipeline.commands import (
    artifacts,
    augment,
    collect,
    datasets,
    merge,
    report,
    sweep,
    tasks,
    train,
    verify,
)

app = typer.Typer(
    help="HIPODE: policy-decoupled, high-return data augmentation for offline RL.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
    add_completion=False,
)

for group in (tasks, collect, datasets, augment, merge, train, verify, artifacts, sweep, report):
    group.register(app)


@app.callback()
def main() -> None:
    """HIPODE: policy-decoupled, high-return data augmentation for offline RL."""
