"""One unit of a sweep: the runs of one (task, learner, arm, budget) that differ only in their
training seed, trained together by `train_seeds` as one stacked model in whatever process
executes the unit (the driver, a local worker process or a Ray worker).

Worker processes import only this module and the library; the driver sends plain dicts
(RunSpec.to_dict) and gets plain dicts back (one record per run). A run whose folder already
holds a finished run with the same settings is not trained again: its scores are read back,
which is what makes a sweep resumable across sessions.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from hipode_pipeline.errors import HipodeError

# the status of a run read back at the budget instead of trained
FINISHED_EARLIER = "finished earlier"


@dataclass(frozen=True)
class RunSpec:
    """Everything one run needs; absolute paths so that any worker can execute it."""

    task: str  # task short name, e.g. hopper-m-r
    arm: str  # arm name, also its folder: eta0, hipode, alpha-1, uniform, lam1, ...
    data: str  # run_training's data: "source" (η = 0) or "merged"
    eta: float  # synthetic fraction per batch (0 for the source arm)
    seed: int  # training and evaluation seed
    steps: int  # updates of the run (the budget)
    eval_every: int  # updates between evaluations
    eval_episodes: int  # episodes per evaluation
    out_dir: str  # the sweep's folder; runs go under <out_dir>/<task>/<arm>/
    root: str  # dataset root (source datasets and artifacts)
    source: str | None = None  # source dataset id or file; None: the task's collected dataset
    artifact: str | None = None  # synthetic artifact for data=merged
    artifact_checksum: str | None = None  # the artifact's content checksum, to detect a rebuild
    device: str | None = None  # torch device; None: CUDA when present
    threads: int = 1  # torch threads in the worker (the machine is shared by the workers)
    force: bool = False  # train again even if a finished run exists
    mixing: str = "mixed"  # batch composition: mixed (η·B synthetic per batch) | union
    learner: str = "td3bc"  # the offline learner trained
    allow_off_band: bool = False  # train on a source whose behaviour policy missed its band

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def run_dir(self) -> Path:
        """The run's own folder: the sweep names it, so arms never share one."""
        return run_folder(self.out_dir, self.task, self.arm, self.learner, self.seed)


def run_folder(out_dir: str | Path, task: str, arm: str, learner: str, seed: int) -> Path:
    """<out>/<task>/<arm>/<learner>-seed<seed>: where the sweep keeps one run."""
    return Path(out_dir) / task / arm / f"{learner}-seed{seed}"


def recorded_seeds(out_dir: str | Path, task: str, arm: str, learner: str) -> list[int]:
    """The seeds that have a run folder of this arm and learner under the sweep's folder: only
    names run_folder writes ("seed01" or "seed1.bak" is someone else's folder)."""
    folder = Path(out_dir) / task / arm
    name = re.compile(rf"{re.escape(learner)}-seed(0|[1-9][0-9]*)")
    if not folder.is_dir():
        return []
    matches = (name.fullmatch(path.name) for path in folder.iterdir() if path.is_dir())
    return sorted(int(match[1]) for match in matches if match)


def expected_settings(spec: RunSpec) -> dict[str, Any]:
    """What a finished run's config.json must say to count as this spec's run."""
    return {
        "learner": spec.learner,
        "data": spec.data,
        "eta": spec.eta,
        "mixing": spec.mixing,
        "seed": spec.seed,
        "eval_every": spec.eval_every,
        "eval_episodes": spec.eval_episodes,
        "artifact_checksum": spec.artifact_checksum,
    }


def finished_scores(spec: RunSpec) -> dict[str, Any] | None:
    """The scores.json of a finished run with this spec's settings; None if there is none yet.
    A finished run with other settings is refused rather than silently reported."""
    from hipode_pipeline.run_folder import finished_scores as folder_scores

    if spec.force:
        return None
    return folder_scores(spec.run_dir(), spec.steps, expected_settings(spec))


def evaluation_at(evaluations: list[dict[str, Any]], step: int, run_dir: Path) -> dict[str, Any]:
    """The evaluation at `step` (a longer run is reported at the budget asked for)."""
    from hipode_pipeline.errors import OverwriteError

    for evaluation in evaluations:
        if evaluation["step"] == step:
            return evaluation
    raise OverwriteError(
        f"{run_dir}: field 'evaluations': expected one at step {step} (the budget), "
        f"found steps {[e['step'] for e in evaluations]}; pass --force or another --out"
    )


def run_record(spec: RunSpec, scores: dict[str, Any], status: str) -> dict[str, Any]:
    """The plain-dict result the driver aggregates: final score at the budget and the curve."""
    run_dir = spec.run_dir()
    curve = [e for e in scores["evaluations"] if e["step"] <= spec.steps]
    final = evaluation_at(curve, spec.steps, run_dir)
    return {
        "task": spec.task,
        "learner": spec.learner,
        "arm": spec.arm,
        "seed": spec.seed,
        "data": spec.data,
        "eta": spec.eta,
        "steps": spec.steps,
        "final_score": final["score_mean"],
        "final_score_std_episodes": final["score_std"],
        "final_return": final["return_mean"],
        "curve": [[e["step"], e["score_mean"], e["score_std"]] for e in curve],
        "updates_per_second": scores.get("updates_per_second"),
        "run_dir": str(run_dir),
        "status": status,
        "seeds_trained_together": trained_together(run_dir),
        "worker_pid": os.getpid(),
    }


def trained_together(run_dir: Path) -> list[int] | None:
    """The seeds the run's last training session stacked with it (config.json); None if the
    folder does not record them."""
    try:
        seeds = json.loads((run_dir / "config.json").read_text()).get("seeds_trained_together")
    except (OSError, ValueError, AttributeError):
        return None
    return seeds if isinstance(seeds, list) else None


def unit_key(spec: RunSpec) -> RunSpec:
    """What the runs of one unit share: everything but the training seed."""
    return replace(spec, seed=0)


def run_unit(spec_dicts: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Execute one unit: read back its finished runs, train the others in one `train_seeds`
    call, and return one record per run in the order given."""
    specs = [RunSpec(**spec_dict) for spec_dict in spec_dicts]
    if not specs or len({unit_key(spec) for spec in specs}) != 1:
        raise HipodeError(
            "sweep unit: expected runs that differ only in their seed, found "
            f"{[(s.task, s.learner, s.arm, s.seed) for s in specs]}"
        )
    records: dict[int, dict[str, Any]] = {}
    pending = []
    for spec in specs:
        scores = finished_scores(spec)
        if scores is None:
            pending.append(spec)
        else:
            records[spec.seed] = run_record(spec, scores, FINISHED_EARLIER)
    if pending:
        records.update(train_unit(pending))
    return [records[spec.seed] for spec in specs]


def train_unit(specs: list[RunSpec]) -> dict[int, dict[str, Any]]:
    """The unit's unfinished runs trained side by side; each seed's record by seed."""
    import torch

    from hipode_pipeline.train import train_seeds

    spec = specs[0]
    torch.set_num_threads(spec.threads)
    results = train_seeds(
        spec.task,
        spec.learner,
        data=spec.data,
        steps=spec.steps,
        seeds=[s.seed for s in specs],
        eval_every=spec.eval_every,
        eval_episodes=spec.eval_episodes,
        source=spec.source,
        artifact=None if spec.artifact is None else Path(spec.artifact),
        eta=None if spec.data == "source" else spec.eta,  # source runs take no η (no note)
        mixing=spec.mixing,
        device=spec.device,
        root=Path(spec.root),
        run_dirs=[s.run_dir() for s in specs],
        force=spec.force,
        show_progress=False,  # the driver shows one bar over all runs
        allow_off_band=spec.allow_off_band,
    )
    records = {}
    for run_spec, result in zip(specs, results, strict=True):
        if result.finished_earlier:
            status = FINISHED_EARLIER
        elif result.resumed_from:
            status = f"resumed from step {result.resumed_from}"
        else:
            status = "trained"
        records[run_spec.seed] = run_record(run_spec, result.to_dict(), status)
    return records
