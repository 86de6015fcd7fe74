"""What every command shares: user-error handling and common options."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import typer
from rich.text import Text

from hipode_pipeline import console
from hipode_pipeline.errors import DataFormatError, HipodeError
from hipode_pipeline.files import check_output_file, check_output_folder
from hipode_pipeline.paths import DATASETS_ENV_VAR, datasets_root


def user_errors(fn):
    """Turn a HipodeError into a clear message on stderr and a non-zero exit code."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except HipodeError as error:
            fail(error)
        except OSError as error:
            # the machine refused (permissions, a full disk, a file where a folder must be):
            # the user's to fix, so one line naming the path, not a traceback
            where = error.filename if error.filename is not None else "a file"
            fail(HipodeError(f"{where}: {error.strerror or error}"))

    return wrapper


def fail(error: HipodeError) -> None:
    """Print `error` as one bounded line on stderr and exit with its code."""
    console.err.print(
        Text.assemble(("error:", "bold red"), " ", error_line(error)),
        highlight=False,
        soft_wrap=True,
    )
    raise typer.Exit(code=error.exit_code) from None


def error_line(error: HipodeError) -> str:
    """The message on one line; values it quotes from a file are cut to a readable length."""
    if isinstance(error, DataFormatError):
        # the path, the field and what was expected stay whole; what was found can be huge
        found = "" if error.found is None else f", found {console.shorten(error.found)}"
        message = f"{error.path}: field '{error.field}': expected {error.expected}{found}"
        return console.shorten(message, console.MESSAGE_LIMIT)
    return console.shorten(str(error), console.MESSAGE_LIMIT)


def _path_check(check: Callable[[Path, str], object]):
    """A typer callback that runs `check(value, option name)` and prints its error as one line
    (exit 2) while the command line is parsed, before any work."""

    def callback(ctx: typer.Context, param: typer.CallbackParam, value: Path | None):
        if value is not None and not ctx.resilient_parsing:
            try:
                check(value, param.opts[0] if param.opts else param.name)
            except HipodeError as error:
                fail(error)
        return value

    return callback


# `callback=` of an output option: a file path (not a folder or FIFO), or a folder
output_file = _path_check(check_output_file)
output_folder = _path_check(check_output_folder)


def _check_root(ctx: typer.Context, value: Path | None) -> Path | None:
    """--root (or $MINARI_DATASETS_PATH) must be a folder or a path where one can be made."""
    if ctx.resilient_parsing:
        return value
    try:
        if value is not None:
            check_output_folder(value, "--root")
        else:
            where = f"${DATASETS_ENV_VAR}" if DATASETS_ENV_VAR in os.environ else "default root"
            check_output_folder(datasets_root(), where)
    except HipodeError as error:
        fail(error)
    return value


JsonFlag = Annotated[bool, typer.Option("--json", help="Print machine-readable JSON on stdout.")]
RootOption = Annotated[
    Path | None,
    typer.Option(
        "--root",
        help="Dataset root (default: $MINARI_DATASETS_PATH, else ./datasets).",
        callback=_check_root,
    ),
]
SeedOption = Annotated[int, typer.Option("--seed", help="Seed for every random number generator.")]
ForceFlag = Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")]
SetOption = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="KEY=VALUE setting of the learner (train) or the generators (augment), repeatable; "
        "VALUE as in TOML (3e-4, true, [256, 256]); checked against the config's fields.",
    ),
]
ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", help="TOML file of KEY = VALUE settings, applied before any --set."),
]
AllowOffBandFlag = Annotated[
    bool,
    typer.Option(
        "--allow-off-band",
        help="Use a source whose behaviour policy scored outside the band of its kind "
        "(refused otherwise); the output records it.",
    ),
]
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
