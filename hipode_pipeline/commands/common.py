"""What every command shares: user-error handling and common options."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from hipode_pipeline import console
from hipode_pipeline.errors import HipodeError


def user_errors(fn):
    """Turn a HipodeError into a clear message on stderr and a non-zero exit code."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except HipodeError as error:
            console.err.print(
                f"[bold red]error:[/] {escape(str(error))}", highlight=False, soft_wrap=True
            )
            raise typer.Exit(code=error.exit_code) from None

    return wrapper


JsonFlag = Annotated[bool, typer.Option("--json", help="Print machine-readable JSON on stdout.")]
RootOption = Annotated[
    Path | None,
    typer.Option("--root", help="Dataset root (default: $MINARI_DATASETS_PATH, else ./datasets)."),
]
SeedOption = Annotated[int, typer.Option("--seed", help="Seed for every random number generator.")]
ForceFlag = Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")]
EvalEveryOption = Annotated[
    int | None, typer.Option("--eval-every", help="Updates between evaluations.")
]
EvalEpisodesOption = Annotated[
    int | None, typer.Option("--eval-episodes", help="Episodes per evaluation.")
]
DeviceOption = Annotated[
    str | None,
    typer.Option("--device", help="cpu, cuda, cuda:1 or auto (default: CUDA when present)."),
]
