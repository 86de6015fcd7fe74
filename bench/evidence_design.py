"""The campaign's design as a rule that picks runs: the sources that hold an arm's full grid.

Issue 16's design is at least 5 training seeds for η = 0 and, per artifact arm, at least
5 training seeds × 2 stage-one seeds, at the campaign's budget. The pooled reports take every
committed run, so a source stopped early (one pair, say) makes an interval impossible
(`hipode report` gives none where a source holds a single pair). The design reports take, per
source and learner, η = 0 where it holds 5 training seeds and each artifact arm's stage-one
seeds that hold 5 of η = 0's training seeds, when there are 2 such seeds; nothing else. The
rule is the issue's, fixed before any outcome was read, and applied to every source alike.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import Any

MIN_TRAINING_SEEDS = 5
MIN_STAGE_ONE_SEEDS = 2
Budget = Callable[[str, str], int | None]  # (learner, task) -> the campaign's updates per run


def design_runs(runs: Sequence[Any], budget: Budget) -> list[Any]:
    """The runs (hipode_pipeline.report.Run) that the design reports aggregate, in the order
    given."""
    cells: dict[tuple, dict[str, dict[Any, dict[int, Any]]]] = defaultdict(
        lambda: defaultdict(lambda: defaultdict(dict))
    )
    for run in runs:
        keys = run.keys
        if keys.get("steps") != budget(keys["learner"], keys["task"]):
            continue  # diagnostics at other budgets are not the campaign
        cell = (keys.get("source_sha256"), keys["learner"])
        cells[cell][keys["augmentation"]][run.artifact_seed][run.seed] = run
    chosen: set[int] = set()
    for arms in cells.values():
        baseline = arms.get("none", {}).get(None, {})
        if len(baseline) < MIN_TRAINING_SEEDS:
            continue  # no arm of this source can be paired over the design's seeds
        chosen |= {id(run) for run in baseline.values()}
        for name, by_stage_one in arms.items():
            if name == "none":
                continue
            full = [
                seeds
                for seeds in by_stage_one.values()
                if len(seeds.keys() & baseline.keys()) >= MIN_TRAINING_SEEDS
            ]
            if len(full) >= MIN_STAGE_ONE_SEEDS:
                chosen |= {id(run) for seeds in full for run in seeds.values()}
    return [run for run in runs if id(run) in chosen]
