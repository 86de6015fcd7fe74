"""One (task, learner, arm, seed) run of a sweep: `run_training` in whatever process executes it
(the driver, a local worker process or a Ray worker).

Worker processes import only this module and the library; the driver sends a plain dict
(RunSpec.to_dict) and gets a plain dict back (the run's record). A run whose folder already
holds a finished run with the same settings is not trained again: its scores are read back,
which is what makes a sweep resumable across sessions.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any


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

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def run_dir(self) -> Path:
        """The run's own folder: the sweep names it, so arms never share one."""
        return Path(self.out_dir) / self.task / self.arm / f"{self.learner}-seed{self.seed}"


def finished_scores(spec: RunSpec) -> dict[str, Any] | None:
    """The scores.json of a finished run with this spec's settings; None if there is none yet.
    A finished run with other settings is refused rather than silently reported."""
    from hipode_pipeline.run_folder import finished_scores as folder_scores

    if spec.force:
        return None
    expected = {
        "learner": spec.learner,
        "data": spec.data,
        "eta": spec.eta,
        "mixing": spec.mixing,
        "seed": spec.seed,
        "eval_every": spec.eval_every,
        "eval_episodes": spec.eval_episodes,
        "artifact_checksum": spec.artifact_checksum,
    }
    return folder_scores(spec.run_dir(), spec.steps, expected)


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
        "worker_pid": os.getpid(),
    }


def run_one(spec_dict: dict[str, Any]) -> dict[str, Any]:
    """Execute one run (or read back its finished result) and return its record."""
    import torch

    from hipode_pipeline.train import run_training

    spec = RunSpec(**spec_dict)
    scores = finished_scores(spec)
    if scores is not None:
        return run_record(spec, scores, "finished earlier")
    torch.set_num_threads(spec.threads)
    result = run_training(
        spec.task,
        spec.learner,
        data=spec.data,
        steps=spec.steps,
        seed=spec.seed,
        eval_every=spec.eval_every,
        eval_episodes=spec.eval_episodes,
        source=spec.source,
        artifact=None if spec.artifact is None else Path(spec.artifact),
        eta=spec.eta,
        mixing=spec.mixing,
        device=spec.device,
        root=Path(spec.root),
        run_dir=spec.run_dir(),
        force=spec.force,
        show_progress=False,  # the driver shows one bar over all runs
    )
    if result.finished_earlier:
        status = "finished earlier"
    elif result.resumed_from:
        status = f"resumed from step {result.resumed_from}"
    else:
        status = "trained"
    return run_record(spec, result.to_dict(), status)
