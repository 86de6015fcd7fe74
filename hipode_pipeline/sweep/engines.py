"""Where a sweep's units execute: in this process (one worker), in fresh local processes
(--workers N) or as Ray tasks (--engine ray, a local Ray unless --address names a cluster).
A unit is the runs of one arm that differ only in their seed, trained together; each engine
yields the runs' records as their units finish."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from hipode_pipeline import console
from hipode_pipeline.errors import HipodeError
from hipode_pipeline.sweep.worker import (
    FINISHED_EARLIER,
    RunSpec,
    expected_settings,
    finished_scores,
    recorded_seeds,
    run_record,
    run_unit,
    unit_key,
)


def unit_dicts(units: list[list[RunSpec]]) -> list[list[dict[str, Any]]]:
    """The units as plain dicts, what a worker process or Ray task receives."""
    return [[spec.to_dict() for spec in unit] for unit in units]


def run_local(units: list[list[RunSpec]], workers: int) -> Iterator[dict[str, Any]]:
    """In this process (one worker) or in fresh spawned processes, one per unit."""
    if workers <= 1:
        for unit in unit_dicts(units):
            yield from run_unit(unit)
        return
    with get_context("spawn").Pool(workers, maxtasksperchild=1) as pool:
        for records in pool.imap_unordered(run_unit, unit_dicts(units)):
            yield from records


def read_finished(specs: list[RunSpec]) -> Iterator[dict[str, Any]]:
    """The runs already finished at the budget, read back; the others are listed on stderr."""
    missing = []
    for spec in specs:
        scores = finished_scores(spec)
        if scores is None:
            missing.append(f"{spec.task} {spec.learner} {spec.arm} seed {spec.seed}")
            continue
        yield run_record(spec, scores, FINISHED_EARLIER)
    if missing:
        console.err.print(f"[yellow]not finished at this budget, left out: {', '.join(missing)}[/]")


def read_back(spec: RunSpec) -> tuple[dict[str, Any] | None, str]:
    """A run folder's record if it is finished with the spec's settings, else why it is not."""
    from hipode_pipeline.run_folder import differing_settings, scores_if_finished

    run_dir = spec.run_dir()
    try:
        scores = scores_if_finished(run_dir, spec.steps)
        if scores is None:
            return None, f"{run_dir} (not finished at {spec.steps:,} updates)"
        differing = differing_settings(run_dir, expected_settings(spec))
        if differing:
            return None, f"{run_dir} (other settings: {', '.join(differing)} differ)"
        return run_record(spec, scores, FINISHED_EARLIER), ""
    except (HipodeError, KeyError, TypeError, IndexError) as error:
        return None, f"{run_dir} (unreadable: {error!r})"


def read_earlier(specs: list[RunSpec], asked: set[int]) -> Iterator[dict[str, Any]]:
    """The finished runs of the planned arms at seeds this invocation did not ask for (an
    earlier `--seeds 0-2` beside this `--seeds 3-4`), read back so that the report covers every
    finished run in the folder. Unfinished runs, runs of other settings and unreadable ones are
    left out and named on stderr: a stale folder never stops the report of the runs just
    trained (and --force, which retrains the asked seeds, does not apply to them)."""
    left_out = []
    for template in {unit_key(spec): spec for spec in specs}.values():
        for seed in recorded_seeds(template.out_dir, template.task, template.arm, template.learner):
            if seed not in asked:
                record, why = read_back(replace(template, seed=seed))
                if record is None:
                    left_out.append(why)
                else:
                    yield record
    if left_out:
        console.err.print(
            "[yellow]run folders of other seeds left out of the report: "
            + "; ".join(left_out)
            + "[/]"
        )


def unplanned_arms(specs: list[RunSpec]) -> list[str]:
    """The arm folders of the sweep's folder that hold runs of a planned task and learner but
    that this invocation did not plan (a `--artifact-seeds ""` sweep beside an earlier
    `--artifact-seeds 1` one): its report cannot describe their arms, so it names them."""
    planned = {(spec.out_dir, spec.task, spec.learner, spec.arm) for spec in specs}
    left_out = []
    for out_dir, task, learner in sorted({(s.out_dir, s.task, s.learner) for s in specs}):
        folder = Path(out_dir) / task
        arms = sorted(path.name for path in folder.iterdir()) if folder.is_dir() else []
        left_out += [
            f"{task} {learner} {arm}"
            for arm in arms
            if (out_dir, task, learner, arm) not in planned
            and recorded_seeds(out_dir, task, arm, learner)  # only folders, and of this learner
        ]
    return left_out


def run_ray(
    units: list[list[RunSpec]], address: str | None, workers: int
) -> Iterator[dict[str, Any]]:
    """One Ray task per unit (1 CPU each); a local Ray with `workers` CPUs unless `address`.
    A cluster's nodes need hipode-pipeline installed and --out and the dataset root at the
    same paths: a task carries only its RunSpecs."""
    try:
        import ray
    except ImportError:
        raise HipodeError(
            "--engine ray: expected Ray to be installed; install it with "
            "`pip install 'hipode-pipeline[ray]'` (ray[default]>=2.40) or pass --engine local"
        ) from None
    # busy-waiting OpenMP threads would starve the other runs on a node
    env_vars = {"OMP_WAIT_POLICY": "PASSIVE", "MINARI_DATASETS_PATH": units[0][0].root}
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(
            address=address,
            num_cpus=None if address else workers,
            include_dashboard=False,
            log_to_driver=False,
            runtime_env={"env_vars": env_vars},
        )
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(run_unit)
        pending = [remote.remote(unit) for unit in unit_dicts(units)]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield from ray.get(done[0])
    finally:
        if started_here:
            ray.shutdown()
