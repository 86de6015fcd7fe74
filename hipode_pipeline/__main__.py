"""The `hipode` command and `python -m hipode_pipeline`: the CLI, with polite torch threads."""

from __future__ import annotations

import os


def main() -> None:
    """Run the `hipode` command line."""
    # OpenMP workers busy-wait by default and starve other work on a shared machine; OpenMP
    # reads the policy once, when torch loads, so it is set before the CLI imports torch
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from hipode_pipeline.cli import app

    app(prog_name="hipode")


if __name__ == "__main__":
    main()
