"""The sweep end to end: plan the runs, execute them on the chosen engine, write the report.

Every (task, learner, arm, seed) is one run folder under --out
(<out>/<task>/<arm>/<learner>-seed<seed>/), so a sweep resumes where it stopped: finished runs
are read back, unfinished ones continue from their checkpoint. The runs of an arm that differ
only in their seed train together in one process (--seeds-per-process caps how many).
"""

from __future__ import annotations

import os
import platform
import shlex
import time

from hipode_pipeline import console
from hipode_pipeline.errors import HipodeError, SettingError
from hipode_pipeline.files import display_path, write_json_atomic, write_text_atomic
from hipode_pipeline.machine import LoadSampler, utc_now
from hipode_pipeline.paths import use_datasets_root
from hipode_pipeline.sweep.engines import (
    read_earlier,
    read_finished,
    run_local,
    run_ray,
    unplanned_arms,
)
from hipode_pipeline.sweep.plan import (
    ENGINES,
    SweepConfig,
    check_seeds_per_process,
    previous_synthetic,
    resolve_budget,
    results_dir,
    run_specs,
    run_units,
    synthetic_seen,
)
from hipode_pipeline.sweep.report import (
    QualityReport,
    curve_plot,
    markdown,
    summarize,
    unplanned_text,
)
from hipode_pipeline.sweep.worker import FINISHED_EARLIER, finished_scores


def command_line(config: SweepConfig) -> str:
    """A command that reproduces this sweep."""
    args = [*shlex.split(config.program), "--tasks", ",".join(config.tasks)]
    if config.learners != ["td3bc"]:
        args += ["--learners", ",".join(config.learners)]
    args += ["--seeds", ",".join(str(s) for s in config.seeds)]
    for flag, value in (
        ("--steps", config.steps),
        ("--budget", config.budget),
        ("--eval-every", config.eval_every),
        ("--eval-episodes", config.eval_episodes),
        ("--source", config.source),
        ("--artifact", config.artifact),
        ("--address", config.address),
        ("--device", config.device),
    ):
        if value is not None:
            args += [flag, str(value)]
    if config.alphas:
        args += [f"--alpha={','.join(f'{a:g}' for a in config.alphas)}"]
    if config.lams:
        args += ["--lam", ",".join(f"{x:g}" for x in config.lams)]
    args += ["--uniform"] if config.uniform else []
    if config.penalties:
        args += ["--penalty", ",".join(config.penalties)]
    args += ["--union"] if config.union else []
    args += ["--model-rollouts"] if config.model_rollouts else []
    if config.artifact_seed:
        args += ["--artifact-seed", str(config.artifact_seed)]
    if config.artifact_seeds:
        args += ["--artifact-seeds", ",".join(str(seed) for seed in config.artifact_seeds)]
    args += [] if config.baseline_arms else ["--no-baselines"]
    args += ["--report-only"] if config.report_only else []
    if config.profile != "full":
        args += ["--profile", config.profile]
    args += ["--engine", config.engine, "--workers", str(config.workers)]
    if config.seeds_per_process is not None:
        args += ["--seeds-per-process", str(config.seeds_per_process)]
    args += ["--allow-off-band"] if config.allow_off_band else []
    return shlex.join(args)


class Pace:
    """The sweep's throughput and finishing time, from the runs this call trained: runs read
    back from an earlier call arrive at once and would make any rate over them meaningless.

    With N workers the first estimate comes when the first run ends, after about a run's time,
    and is high until N runs have ended; a run resumed from its checkpoint counts as a whole one.
    """

    def __init__(self, to_train: int):
        self.to_train, self.trained = to_train, 0
        self.clock = time.monotonic()

    def add(self, record: dict) -> None:
        self.trained += record["status"] != FINISHED_EARLIER

    def fields(self) -> dict[str, object]:
        """The progress bar's `rate` and `finish_at`: None until a run trained here has ended."""
        now = time.monotonic()
        if self.trained >= self.to_train:
            return {"rate": self.rate(now), console.ETA_FIELD: now}
        if not self.trained or now <= self.clock:
            return {"rate": "", console.ETA_FIELD: None}
        per_run = (now - self.clock) / self.trained  # with N workers, about a run's time / N
        return {
            "rate": self.rate(now),
            console.ETA_FIELD: now + (self.to_train - self.trained) * per_run,
        }

    def rate(self, now: float) -> str:
        if not self.trained or now <= self.clock:
            return ""
        return f"{3600 * self.trained / (now - self.clock):.1f} runs/h"


def run_sweep(config: SweepConfig) -> QualityReport:
    """Run (or resume) the sweep and write quality.md, quality.json and quality.png."""
    import torch

    from hipode_pipeline.device import select_device

    if config.engine not in ENGINES:
        raise SettingError(f"--engine: expected one of {ENGINES}, found {config.engine!r}")
    if config.workers < 1 or config.threads < 1 or not config.seeds or not config.tasks:
        raise SettingError("--workers, --threads: expected ≥ 1; --seeds, --tasks: not empty")
    if len(set(config.seeds)) != len(config.seeds):
        raise SettingError(f"--seeds: expected each seed once, found {config.seeds}")
    check_seeds_per_process(config.seeds_per_process)
    root = use_datasets_root(config.root)
    config.out = config.out.resolve()
    steps, eval_every, eval_episodes, budget = resolve_budget(config)
    started, clock = utc_now(), time.perf_counter()
    previous = previous_synthetic(config)  # read before this sweep's report replaces it
    specs, arms, sources = run_specs(config, root, previous, display_path)
    keys = {(a["learner"], a["name"]): a["key"] for task_arms in arms.values() for a in task_arms}

    def as_row(record: dict) -> dict:
        """A run's record as the report lists it: its arm's row key, its folder shown."""
        key = keys[record["learner"], record["arm"]]
        return {**record, "key": key, "run_dir": display_path(record["run_dir"])}

    runs = []
    with LoadSampler() as load, console.progress(disable=not config.show_progress) as prog:
        bar = prog.add_task(
            "sweep runs", total=len(specs), rate="", info="", **{console.ETA_FIELD: None}
        )
        units = run_units(specs, config.seeds_per_process)
        if not config.report_only and len(units) < config.workers:
            console.err.print(
                f"[yellow]note:[/] {len(units)} unit(s) of seeds for --workers "
                f"{config.workers}: some workers stay idle; --seeds-per-process 1 gives one "
                "unit per run"
            )
        if config.report_only:
            executed = read_finished(specs)
        elif config.engine == "local":
            executed = run_local(units, config.workers)
        else:
            executed = run_ray(units, config.address, config.workers)
        unfinished = sum(finished_scores(spec) is None for spec in specs)
        pace = Pace(0 if config.report_only else unfinished)
        for record in executed:
            runs.append(row := as_row(record))
            pace.add(record)
            prog.update(
                bar,
                advance=1,
                info=f"{row['task']} {row['key']} seed {row['seed']}: {row['final_score']:.1f}",
                **pace.fields(),
            )
        # runs left out (--report-only, unfinished) never arrive: the bar ends at what did
        prog.update(bar, total=len(runs))
    # the report covers the folder, not this invocation: seeds 3-4 after 0-2 report 0-4
    earlier = [as_row(record) for record in read_earlier(specs, set(config.seeds))]
    runs += earlier
    if not runs:
        raise HipodeError(f"{config.out}: no finished runs at {steps} steps to report")
    unplanned = unplanned_arms(specs)
    if unplanned:
        console.err.print(f"[yellow]note:[/] {unplanned_text(unplanned)}")
    report = QualityReport(
        command=command_line(config),
        budget={
            "name": budget,
            "learners": config.learners,
            "steps": steps,
            "eval_every": eval_every,
            "eval_episodes": eval_episodes,
            "seeds": config.seeds,
            "earlier_seeds": sorted({r["seed"] for r in earlier}),
            "report_only": config.report_only,
        },
        machine={
            "platform": f"{platform.system()} {platform.machine()}",
            "cpu_count": os.cpu_count(),
            "torch": torch.__version__,
            "device": str(select_device(config.device)),
            "engine": config.engine + (f" ({config.address})" if config.address else ""),
            "workers": config.workers,
            "threads": config.threads,
            "seeds_per_process": config.seeds_per_process,
            "load_during": load.stats(),
        },
        arms=arms,
        sources=sources,
        runs=sorted(runs, key=lambda r: (r["task"], r["learner"], r["arm"], r["seed"])),
        summary=summarize(runs, arms),
        started=started,
        seconds=time.perf_counter() - clock,
        note=config.note,
        synthetic_seen=synthetic_seen(previous, arms),
        unplanned_arms=unplanned,
    )
    results = results_dir(config)
    results.mkdir(parents=True, exist_ok=True)
    png, md, js = (results / f"quality.{ext}" for ext in ("png", "md", "json"))
    if curve_plot(report.runs, png, config.learners):
        report.files["png"] = display_path(png)
    else:
        console.err.print(
            "[yellow]no learning-curve plot: matplotlib is not installed "
            "(pip install 'hipode-pipeline[plots]')[/]"
        )
    report.files.update(md=display_path(md), json=display_path(js))
    write_text_atomic(md, markdown(report))
    write_json_atomic(js, report.to_dict())
    return report
