"""How many threads torch uses: set for one scope and restored after it, never process-wide."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import torch

from hipode_pipeline.errors import SettingError

THREADS_ENV_VAR = "OMP_NUM_THREADS"
# stage one's torch threads per phase (bench/results/augment.md): training's 256-row steps run
# faster on one thread and its weights depend on the thread count, so it is fixed at one, which
# keeps the same request giving the same generators on any machine; generation's large batches
# run faster on two and give the same rows on any count, so the user's OMP_NUM_THREADS is kept
STAGE_ONE_THREADS = {"train": 1, "generate": 2}


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[int]:
    """Run the block with `n` torch threads (None: as they are) and restore the count after it.

    Yields the count in effect inside the block.
    """
    before = torch.get_num_threads()
    if n is None:
        yield before
        return
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise SettingError(f"torch threads: expected a positive integer, found {n!r}")
    torch.set_num_threads(n)
    try:
        yield n
    finally:
        torch.set_num_threads(before)


def stage_one_threads(phase: str) -> int:
    """Torch threads for a phase of stage one: "train" always the fixed count; "generate"
    $OMP_NUM_THREADS when set, else the measured default (never more than the machine's CPUs)."""
    if phase == "train":
        return STAGE_ONE_THREADS["train"]
    given = os.environ.get(THREADS_ENV_VAR, "").strip()
    if given:
        # torch reads the same variable at start-up; stage one keeps the user's choice
        if not given.isdigit() or int(given) < 1:
            raise SettingError(
                f"environment variable {THREADS_ENV_VAR}: expected a positive integer, "
                f"found {given!r}"
            )
        return int(given)
    return max(1, min(STAGE_ONE_THREADS[phase], os.cpu_count() or 1))
